"""The front end: registration of pairs of scans.

``pairwise`` registers a pair globally (descriptor matches, a robust estimator, GICP) and scores it.
"""
