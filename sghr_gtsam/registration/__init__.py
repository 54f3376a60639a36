"""The front end: registration of pairs of scans.

``pairwise`` registers a pair globally (descriptor matches, a robust estimator, GICP) and scores it.
"""

WORKER_MODULES = ("sghr_gtsam.features.local", "sghr_gtsam.registration.batch", "sghr_gtsam.registration.refine")
"""The modules whose functions the front end runs over ``sghr_gtsam.executor`` (the fork server preloads them)."""
