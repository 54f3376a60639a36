"""GICP of one grid onto another, and the nearest-point search that scoring a registration and its information use.

A point of scan j farther than the correspondence distance from scan i adds nothing to a registration's score or its
information, yet a k-d tree's search for its nearest neighbour costs the most there: the ball around a far query
meets many cells before the search can stop. ``nearest_within`` stops at the distance that matters: on 3DMatch
fragment pairs at their robust estimates 2.0 ms a pair against 7.6 ms for small_gicp's unbounded search, the same pairs
(one core); the runs' poses stay identical (``benchmarks/bench_stages.py``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import small_gicp
from scipy.spatial import cKDTree

from sghr_gtsam.features.local import COV_NEIGHBORS, GICP_THREADS

REACH_VOXELS = 3.0
"""How far (voxels) an alignment may move a scan's points beyond the correspondence distance and still take up
points that started out of reach; ``refine.stays_near`` confirms no larger move."""


class AlignedGrid(Protocol):
    """A scan's points on one grid with GICP covariances (``cloud``), small_gicp's k-d tree over them
    (``cloud_tree``) and scipy's (``point_tree``, for searches bounded by a distance)."""

    points: np.ndarray
    cloud: small_gicp.PointCloud
    cloud_tree: small_gicp.KdTree
    point_tree: cKDTree


def nearest_within(target: AlignedGrid, moved: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """For each of ``moved`` (m, 3, in the target's frame): the index of its nearest target point and their squared
    distance, or ``len(target.points)`` and inf where none lies within ``radius``."""
    distance, nearest = target.point_tree.query(moved, k=1, distance_upper_bound=radius, workers=GICP_THREADS)
    return nearest, distance**2


def gicp(
    target: AlignedGrid,
    source: AlignedGrid,
    T_init: np.ndarray,
    max_distance: float,
    voxel: float,
    **criteria: float,
) -> small_gicp.RegistrationResult:
    """small_gicp's GICP of ``source`` onto ``target`` from ``T_init`` (``T_target_source``) with correspondences
    within ``max_distance``, on one thread (``features.local.GICP_THREADS``), on the source points within
    ``max_distance + REACH_VOXELS · voxel`` of the target at ``T_init`` (their covariances from their neighbours among
    those). ``criteria``: small_gicp's ``max_iterations``, ``rotation_epsilon``, ``translation_epsilon``."""
    moved = source.points @ T_init[:3, :3].T + T_init[:3, 3]
    reach = np.isfinite(nearest_within(target, moved, max_distance + REACH_VOXELS * voxel)[1])
    cloud = source.cloud
    if COV_NEIGHBORS <= np.count_nonzero(reach) < len(reach):
        cloud = small_gicp.PointCloud(source.points[reach])
        small_gicp.estimate_covariances(
            cloud, small_gicp.KdTree(cloud, num_threads=GICP_THREADS), COV_NEIGHBORS, GICP_THREADS
        )
    return small_gicp.align(
        target.cloud,
        cloud,
        target.cloud_tree,
        init_T_target_source=T_init,
        registration_type="GICP",
        max_correspondence_distance=max_distance,
        num_threads=GICP_THREADS,
        **criteria,
    )
