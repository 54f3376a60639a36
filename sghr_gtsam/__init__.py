"""sghr_gtsam: multiview point-cloud registration (SGHR) with a GTSAM back end."""
