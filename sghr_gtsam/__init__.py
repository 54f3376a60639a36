"""sghr_gtsam: multiview point-cloud registration (SGHR) with a GTSAM back end."""

from ._open3d_extras import defer as _defer_open3d_extras

_defer_open3d_extras()  # before any module of the package imports open3d
