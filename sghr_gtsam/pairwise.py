"""Pairwise registration of two scans' features: mutual-nearest-neighbour FPFH matches, a robust
estimator on them (kiss-matcher or open3d RANSAC), GICP refinement, and the inlier count ``r_ij`` that
SGHR uses as the edge's confidence. ``T_ij`` maps points of scan j into the frame of scan i."""

from __future__ import annotations

import time
from dataclasses import dataclass

import kiss_matcher
import numpy as np
import open3d as o3d
import small_gicp

from sghr_gtsam.features.local import NUM_THREADS, ScanFeatures
from sghr_gtsam.types import InputError

MATCHERS = ("kiss", "ransac")
# A match counts towards r_ij when the final T_ij brings its two points within this many voxels.
INLIER_DISTANCE = 1.5
# open3d RANSAC: inlier distance (voxels), and a budget that keeps it near a second a pair.
RANSAC_DISTANCE = 1.5
RANSAC_MAX_ITERATION = 100_000
RANSAC_CONFIDENCE = 0.999
# GICP stops at this many iterations or when an update moves less than these (rad; voxels).
GICP_MAX_ITERATIONS = 30
GICP_ROTATION_EPS = 1e-4
GICP_TRANSLATION_EPS = 1e-3


@dataclass
class PairResult:
    """Registration of scan j onto scan i.

    ``T``: (4, 4) ``T_ij``. ``inliers``: FPFH matches that ``T`` brings within ``INLIER_DISTANCE``
    voxels (SGHR's ``r_ij``). ``fitness``: fraction of scan j's refinement points with a scan-i point
    within the ICP distance; ``rmse``: RMS distance of those. ``information``: (6, 6) in gtsam's
    tangent order [rotation, translation] for the perturbation ``T_ij @ exp(xi)``, from those ICP
    correspondences with unit point noise (open3d's convention, scaled by 1/sigma^2 to taste);
    None when there are fewer than 3. ``seconds``: wall time of ``register_pair``.
    """

    T: np.ndarray
    inliers: int
    fitness: float
    rmse: float
    information: np.ndarray | None
    seconds: float


def mutual_matches(target_i: ScanFeatures, source_j: ScanFeatures) -> tuple[np.ndarray, np.ndarray]:
    """Indices (a, b) of FPFH mutual nearest neighbours: ``target_i.points[a]`` <-> ``source_j.points[b]``."""
    _, nn_in_i = target_i.fpfh_tree.query(source_j.fpfh, k=1, workers=NUM_THREADS)
    _, nn_in_j = source_j.fpfh_tree.query(target_i.fpfh, k=1, workers=NUM_THREADS)
    b = np.flatnonzero(nn_in_j[nn_in_i] == np.arange(len(nn_in_i)))
    return nn_in_i[b], b


def _kiss(p_i: np.ndarray, p_j: np.ndarray, voxel: float) -> np.ndarray:
    # In voxel units: kiss-matcher's noise bounds are multiples of its voxel size, and it refuses
    # voxels under 5 mm (the bunny's is ~2 mm).
    solver = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(1.0))
    solution = solver.prune_and_solve(list((p_j / voxel).astype(np.float32)), list((p_i / voxel).astype(np.float32)))
    T = np.eye(4)
    T[:3, :3] = np.asarray(solution.rotation)
    T[:3, 3] = np.asarray(solution.translation).ravel() * voxel
    return T


def _ransac(target_i: ScanFeatures, source_j: ScanFeatures, a: np.ndarray, b: np.ndarray, voxel: float, seed: int) -> np.ndarray:
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    distance = RANSAC_DISTANCE * voxel
    result = reg.registration_ransac_based_on_correspondence(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source_j.points)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target_i.points)),
        o3d.utility.Vector2iVector(np.stack([b, a], axis=1).astype(np.int32)),
        distance,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(RANSAC_MAX_ITERATION, RANSAC_CONFIDENCE),
    )
    return np.asarray(result.transformation)


def _information(p: np.ndarray) -> np.ndarray:
    """Sum of J^T J over source points p (frame j), J = [-[p]x, I] the derivative of T exp(xi) p."""
    n = len(p)
    s = p.sum(axis=0)
    S = np.array([[0.0, -s[2], s[1]], [s[2], 0.0, -s[0]], [-s[1], s[0], 0.0]])
    info = np.empty((6, 6))
    info[:3, :3] = np.sum(p * p) * np.eye(3) - p.T @ p
    info[:3, 3:] = S
    info[3:, :3] = S.T
    info[3:, 3:] = n * np.eye(3)
    return info


def register_pair(
    target_i: ScanFeatures,
    source_j: ScanFeatures,
    voxel: float,
    matcher: str = "kiss",
    icp_distance: float = 1.5,
    seed: int = 0,
) -> PairResult:
    """Estimate ``T_ij`` (scan j into scan i's frame); distances in voxels as in ``Config``."""
    if matcher not in MATCHERS:
        raise InputError(f"unknown matcher {matcher!r}; choose one of {', '.join(MATCHERS)}")
    start = time.perf_counter()
    a, b = mutual_matches(target_i, source_j)
    p_i, p_j = target_i.points[a], source_j.points[b]
    if len(a) < 3:
        return PairResult(np.eye(4), 0, 0.0, 0.0, None, time.perf_counter() - start)
    T = _kiss(p_i, p_j, voxel) if matcher == "kiss" else _ransac(target_i, source_j, a, b, voxel, seed)

    max_distance = icp_distance * voxel
    T = small_gicp.align(
        target_i.refine_cloud,
        source_j.refine_cloud,
        target_i.refine_tree,
        init_T_target_source=T,
        registration_type="GICP",
        max_correspondence_distance=max_distance,
        num_threads=NUM_THREADS,
        max_iterations=GICP_MAX_ITERATIONS,
        rotation_epsilon=GICP_ROTATION_EPS,
        translation_epsilon=GICP_TRANSLATION_EPS * voxel,
    ).T_target_source

    residual = np.linalg.norm(p_j @ T[:3, :3].T + T[:3, 3] - p_i, axis=1)
    inliers = int(np.count_nonzero(residual < INLIER_DISTANCE * voxel))

    q = source_j.refine_points
    _, sq = target_i.refine_tree.batch_nearest_neighbor_search(q @ T[:3, :3].T + T[:3, 3], num_threads=NUM_THREADS)
    sq = np.asarray(sq)
    close = sq < max_distance**2
    n = int(np.count_nonzero(close))
    return PairResult(
        T=T,
        inliers=inliers,
        fitness=n / max(len(q), 1),
        rmse=float(np.sqrt(sq[close].mean())) if n else 0.0,
        information=_information(q[close]) if n >= 3 else None,
        seconds=time.perf_counter() - start,
    )
