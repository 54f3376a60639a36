"""sghr_gtsam: multiview point-cloud registration (SGHR) with a GTSAM back end.

The everyday names, ``import sghr_gtsam as sg``: ``sg.run`` (a scan folder in, a results folder out),
``sg.register`` (scans in, a ``RunResult`` out), ``sg.Config`` (every option), ``sg.synchronize`` (a pose graph's
poses), ``sg.load_results`` (a results folder back into a ``RunResult``), ``sg.to_gtsam`` (a result as gtsam factors
and values) and ``sg.Session`` (scan by scan, with the caller's own factors). Each is imported when first used:
``import sghr_gtsam`` stays as quick as before (gtsam, open3d and the pipeline take seconds)."""

from typing import TYPE_CHECKING

from sghr_gtsam._open3d_extras import defer as _defer_open3d_extras

_defer_open3d_extras()  # before any module of the package imports open3d

_LAZY = {
    "run": "pipeline",
    "register": "pipeline",
    "Config": "config",
    "synchronize": "sync",
    "load_results": "io.results",
    "to_gtsam": "gtsam_api",
    "Session": "incremental",
}
"""Top-level name -> the module (under the package) that defines it."""
__all__ = ["run", "register", "Config", "synchronize", "load_results", "to_gtsam", "Session"]

if TYPE_CHECKING:
    from sghr_gtsam.config import Config
    from sghr_gtsam.gtsam_api import to_gtsam
    from sghr_gtsam.incremental import Session
    from sghr_gtsam.io.results import load_results
    from sghr_gtsam.pipeline import register, run
    from sghr_gtsam.sync import synchronize


def __getattr__(name: str) -> object:
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from importlib import import_module

    value = getattr(import_module(f".{_LAZY[name]}", __name__), name)
    globals()[name] = value  # the next lookup does not come here
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
