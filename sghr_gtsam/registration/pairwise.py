"""Pairwise registration of two scans' features: mutual-nearest-neighbour descriptor matches (FPFH, or
keypoints and descriptors given per scan), a robust estimator on them (second-order spatial compatibility,
kiss-matcher or open3d RANSAC), GICP refinement, and the inlier count ``r_ij`` that
SGHR uses as the edge's confidence. ``T_ij`` maps points of scan j into the frame of scan i."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import kiss_matcher
import numpy as np
import open3d as o3d

from sghr_gtsam.cache import Kind
from sghr_gtsam.cells import unique_cells
from sghr_gtsam.config import MATCHERS
from sghr_gtsam.features.local import ScanFeatures, query_threads
from sghr_gtsam.registration.estimators import sc2_estimate
from sghr_gtsam.registration.icp import gicp, nearest_within
from sghr_gtsam.registration.information import Information, registration_information
from sghr_gtsam.se3 import non_rigid
from sghr_gtsam.types import InputError

# Approximate k-d search in 33-d: the neighbour returned is within (1 + eps) of the nearest. With 2
# matching is 4-6x faster than exact search and registers the same pairs (+-1) on the 3DMatch fragments and
# an object's range scans; with 3 both lose pairs. On the authors' 32-d YOHO descriptors (six fragments) it
# finds 97-101 % as many mutual matches as exact search and gets the same 14 of 15 pairs right.
MATCH_EPS = 2.0
# A match counts towards r_ij when the final T_ij brings its two points this close (voxels).
INLIER_DISTANCE = 1.5
# ``PairResult.coverage`` counts the cells of this size (voxels) that the inliers occupy in scan i. A
# consensus-maximising estimator (sc2) also finds chance agreement between unrelated parts, but there the
# inliers crowd on one object: on two 3DMatch scenes and an object's range scans no grossly wrong pair
# (> 10 deg or 0.5 m) covered more than 10 cells, where its r_ij reached 27 (benchmarks/bench_pairwise.py).
COVERAGE_CELL = 5.0
# open3d RANSAC on the matches: inlier distance (voxels) and its stopping rule.
RANSAC_DISTANCE = 1.5
RANSAC_MAX_ITERATION = 100_000
RANSAC_CONFIDENCE = 0.999
# GICP stops after this many iterations or when an update is below these (radians; voxels). From a
# robust estimate it converges in 2-7 iterations (36 of the 44 right 3DMatch and object pairs); the
# rest creep along low-overlap surfaces, and a cap of 10 registers the same pairs as 30 at half the
# cost (wrong pairs never converge, so they always use the whole cap).
GICP_MAX_ITERATIONS = 10
GICP_ROTATION_EPS = 1e-4
GICP_TRANSLATION_EPS = 1e-3


@dataclass
class PairResult:
    """Registration of scan j onto scan i.

    ``T``: (4, 4) ``T_ij``. ``inliers``: descriptor matches that ``T`` brings within ``INLIER_DISTANCE``
    voxels (SGHR's ``r_ij``). ``fitness``: fraction of scan j's grid points with a scan-i point within
    the ICP distance after ``T``; ``rmse``: RMS distance of those pairs. ``information``: (6, 6) in
    gtsam's tangent order [rotation, translation] for ``T_ij @ exp(xi)``, point-to-plane over the close
    pairs of the grid ``T`` was aligned on (those pairs here; the finest pyramid level for a refined edge or
    a loop closure) with the point noise estimated from their residuals
    (``information.registration_information``); None with too few pairs, or for a registration under the inlier bar
    (``register_pair``'s ``min_inliers``, ``refine.refine_pair``). ``seconds``: wall time.
    ``coverage``: cells of ``COVERAGE_CELL`` voxels
    (a grid in scan i's frame) that hold at least one of the ``inliers``: how spread the agreement is.
    ``matches``: the mutual descriptor matches (a, b) it was scored on; they depend on the two scans only, so
    scoring the pair again at another ``T`` (refinement) reuses them.
    """

    T: np.ndarray
    inliers: int
    fitness: float
    rmse: float
    information: np.ndarray | None
    seconds: float
    coverage: int = 0
    matches: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    free: int = 0
    """Directions of ``T`` the pair's geometry does not fix (a plane, a corridor, a cylinder: ``information.
    free_directions``); ``bounded`` bounds them only by the overlap's extent."""
    bounded: np.ndarray | None = None
    """``information`` with those directions bounded only by the overlap (``information.Information.matrix``):
    what the reported covariances use; None when none is free."""
    loose: np.ndarray | None = None
    """The part of ``bounded`` along those directions (``information.Information.loose``)."""
    grid: np.ndarray | None = None
    """(6,) tangent at ``T`` to the transform the next coarser grid gave (``refine.refine_pair``; None for a single
    grid): how far the estimate moves with the grid it is aligned on, an error of the sampling that the information
    does not see. ``gtsam_api.pose_covariances`` adds ``grid gridᵀ`` to the edge's covariance."""


_PAIR_ARRAYS = ("information", "bounded", "loose", "grid")


def _encode_pair(p: PairResult) -> dict[str, np.ndarray]:
    out = {"T": p.T, "numbers": np.array([p.inliers, p.fitness, p.rmse, p.seconds, p.coverage, p.free])}
    out.update({name: getattr(p, name) for name in _PAIR_ARRAYS if getattr(p, name) is not None})
    if p.matches is not None:
        out["match_i"], out["match_j"] = p.matches
    return out


def _decode_pair(a: dict[str, np.ndarray]) -> PairResult:
    inliers, fitness, rmse, seconds, coverage, free = a["numbers"].tolist()
    matches = (a["match_i"], a["match_j"]) if "match_i" in a else None
    T = a["T"]  # a scaled or reflected rotation failed the run downstream, as a NaN did
    if T.shape != (4, 4) or not np.isfinite(T).all() or non_rigid(T):
        raise ValueError(f"T of shape {T.shape}, not finite or no rigid transform")
    return PairResult(
        a["T"],
        int(inliers),
        fitness,
        rmse,
        a.get("information"),
        seconds,
        int(coverage),
        matches,
        int(free),
        a.get("bounded"),
        a.get("loose"),
        a.get("grid"),
    )


PAIRS = Kind("pairs", _encode_pair, _decode_pair)
"""A pair's global registration in the cache (``cache.Kind``)."""


def mutual_matches(target_i: ScanFeatures, source_j: ScanFeatures) -> tuple[np.ndarray, np.ndarray]:
    """Indices (a, b), int32: ``target_i.keypoints[a]`` and ``source_j.keypoints[b]`` are mutual nearest
    neighbours in descriptor space (every registered pair keeps them for the run: half the bytes of int64).
    Only the points of scan i that are some point's nearest neighbour can be mutual, and a k-d query's answer for one
    point does not depend on the others queried with it: those alone are looked back (about a third of scan i's on
    3DMatch fragment pairs: 32 ms a pair against 46 ms, one core, the same matches)."""
    threads = query_threads()
    _, nn_in_i = target_i.descriptor_tree.query(source_j.descriptors, k=1, eps=MATCH_EPS, workers=threads)
    hit, index = np.unique(nn_in_i, return_inverse=True)
    _, nn_in_j = source_j.descriptor_tree.query(target_i.descriptors[hit], k=1, eps=MATCH_EPS, workers=threads)
    b = np.flatnonzero(nn_in_j[index] == np.arange(len(nn_in_i)))
    return nn_in_i[b].astype(np.int32), b.astype(np.int32)


def _kiss(p_i: np.ndarray, p_j: np.ndarray, voxel: float) -> np.ndarray:
    # Solved in voxel units: kiss-matcher's noise bounds are multiples of its voxel size, and it
    # refuses voxels under 5 mm (an object's scans get 2.5 mm). ROBIN's max-core pruning before the GNC
    # solver matters: the solver alone got 14 3DMatch pairs right where pruning got 17 (3 cm grid).
    solver = kiss_matcher.KISSMatcher(kiss_matcher.KISSMatcherConfig(1.0))
    solution = solver.prune_and_solve(list((p_j / voxel).astype(np.float32)), list((p_i / voxel).astype(np.float32)))
    T = np.eye(4)
    T[:3, :3] = np.asarray(solution.rotation)
    T[:3, 3] = np.asarray(solution.translation).ravel() * voxel
    return T


def _ransac(
    target_i: ScanFeatures, source_j: ScanFeatures, a: np.ndarray, b: np.ndarray, voxel: float, seed: int
) -> np.ndarray:
    reg = o3d.pipelines.registration
    o3d.utility.random.seed(seed)
    distance = RANSAC_DISTANCE * voxel
    result = reg.registration_ransac_based_on_correspondence(
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(source_j.keypoints)),
        o3d.geometry.PointCloud(o3d.utility.Vector3dVector(target_i.keypoints)),
        o3d.utility.Vector2iVector(np.stack([b, a], axis=1).astype(np.int32)),
        distance,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(distance)],
        reg.RANSACConvergenceCriteria(RANSAC_MAX_ITERATION, RANSAC_CONFIDENCE),
    )
    return np.asarray(result.transformation)


def register_pair(
    target_i: ScanFeatures,
    source_j: ScanFeatures,
    voxel: float,
    matcher: str = "sc2",
    icp_distance: float = 1.5,
    seed: int = 0,
    min_inliers: int = 0,
) -> PairResult:
    """Estimate ``T_ij`` (scan j into scan i's frame). ``icp_distance`` in voxels, as in ``Config``;
    ``seed`` drives RANSAC (sc2 and kiss-matcher are deterministic). Only a result with at least ``min_inliers``
    inliers gets an ``information``: one under the bar enters no graph. Every estimate is polished by GICP, also
    one under the bar: GICP brings some to it (``benchmarks/bench_learned_descriptor.py calibrate``), and skipping
    it there turned a generated hotel's model (docs/benchmarks.md, not kept)."""
    if matcher not in MATCHERS:
        raise InputError(f"unknown matcher {matcher!r}; choose one of: {', '.join(MATCHERS)}")
    start = time.perf_counter()
    a, b = mutual_matches(target_i, source_j)
    if len(a) < 3:
        return PairResult(np.eye(4), 0, 0.0, 0.0, None, time.perf_counter() - start, matches=(a, b))
    p_i, p_j = target_i.keypoints[a], source_j.keypoints[b]
    if matcher == "sc2":
        T = sc2_estimate(p_i, p_j, voxel).T
    elif matcher == "kiss":
        T = _kiss(p_i, p_j, voxel)
    else:
        T = _ransac(target_i, source_j, a, b, voxel, seed)

    # GICP on the matching grid itself: on an object's right pairs it lands 0.15 deg / 0.16 mm (median)
    # from ground truth; a 2x finer grid gained 0.02 deg for 7x the time. Started at ground truth,
    # open3d's point-to-plane ICP drifted 1.4-4 deg on object pairs of overlap 0.3-0.55 where GICP
    # stayed within 0.2-0.7 deg, and took 9x longer.
    T = gicp(
        target_i,
        source_j,
        T,
        icp_distance * voxel,
        max_iterations=GICP_MAX_ITERATIONS,
        rotation_epsilon=GICP_ROTATION_EPS,
        translation_epsilon=GICP_TRANSLATION_EPS * voxel,
    ).T_target_source

    result, search = scored(target_i, source_j, T, voxel, icp_distance, (a, b))
    if result.inliers >= min_inliers:  # one that enters no graph needs no information
        result = informed(target_i, source_j, result, search, voxel, icp_distance)
    result.seconds = time.perf_counter() - start
    return result


def agreeing_matches(
    target_i: ScanFeatures, source_j: ScanFeatures, T: np.ndarray, voxel: float, search: tuple[np.ndarray, np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """The ``mutual_matches`` that ``T`` brings within ``INLIER_DISTANCE`` voxels, for keypoints that are the grid
    points (FPFH, the learned descriptor; not given keypoints). Only a point of scan j with a point of scan i that
    close can be one, so only those are looked up in descriptor space, and only their partners looked back
    (``score_pair`` in 0.55× the time on 3DMatch pairs).
    A k-d query's answer for one point does not depend on the others queried with it, so the pairs are exactly
    those of ``mutual_matches`` that agree. ``search``: ``icp.nearest_within`` of scan j's points moved by
    ``T``."""
    threads = query_threads()
    # Slack on the bound: a pair whose residual rounds the other way is judged below, as score_pair judges it.
    near = np.flatnonzero(search[1] < (1.0 + 1e-6) * (INLIER_DISTANCE * voxel) ** 2)
    _, nn_in_i = target_i.descriptor_tree.query(source_j.descriptors[near], k=1, eps=MATCH_EPS, workers=threads)
    _, nn_in_j = source_j.descriptor_tree.query(target_i.descriptors[nn_in_i], k=1, eps=MATCH_EPS, workers=threads)
    mutual = nn_in_j == near
    return nn_in_i[mutual].astype(np.int32), near[mutual].astype(np.int32)


def score_pair(
    target_i: ScanFeatures,
    source_j: ScanFeatures,
    T: np.ndarray,
    voxel: float,
    icp_distance: float,
    matches: tuple[np.ndarray, np.ndarray] | None = None,
    information: Information | None = None,
) -> PairResult:
    """The ``PairResult`` of ``T`` (however it was found): its mutual descriptor ``matches`` within
    ``INLIER_DISTANCE`` voxels (``r_ij``) and the cells they cover, fitness, rmse, and ``information`` when given
    (from the grid ``T`` was aligned on), else the matching grid's; ``seconds`` 0. Without ``matches``, on keypoints
    that are the grid points only those that agree are found (``agreeing_matches``) and the result keeps none;
    otherwise all are found and kept."""
    result, search = scored(target_i, source_j, T, voxel, icp_distance, matches)
    return informed(target_i, source_j, result, search, voxel, icp_distance, information)


def scored(
    target_i: ScanFeatures,
    source_j: ScanFeatures,
    T: np.ndarray,
    voxel: float,
    icp_distance: float,
    matches: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[PairResult, tuple[np.ndarray, np.ndarray]]:
    """``score_pair`` without the information (None), and the ``icp.nearest_within`` of scan j's points
    moved by ``T`` that it searched (``registration_information`` takes it)."""
    max_distance = icp_distance * voxel
    q = source_j.points
    # As far as any caller looks: the ICP distance (fitness, information) or the inlier distance with the slack that
    # agreeing_matches allows.
    search = nearest_within(
        target_i, q @ T[:3, :3].T + T[:3, 3], max(max_distance, INLIER_DISTANCE * voxel) * (1 + 1e-6)
    )
    if matches is None and source_j.keypoints is q and target_i.keypoints is target_i.points:
        a, b = agreeing_matches(target_i, source_j, T, voxel, search)
    else:
        matches = mutual_matches(target_i, source_j) if matches is None else matches
        a, b = matches
    p_i = target_i.keypoints[a]
    residual = np.linalg.norm(source_j.keypoints[b] @ T[:3, :3].T + T[:3, 3] - p_i, axis=1)
    agree = residual < INLIER_DISTANCE * voxel
    cells = np.floor(p_i[agree] / (COVERAGE_CELL * voxel)).astype(np.int64)
    sq_dist = search[1]
    close = sq_dist < max_distance**2
    n = int(np.count_nonzero(close))
    return PairResult(
        T=T,
        inliers=int(np.count_nonzero(agree)),
        fitness=n / len(q),
        rmse=float(np.sqrt(sq_dist[close].mean())) if n else 0.0,
        information=None,
        seconds=0.0,
        coverage=len(unique_cells(cells)[0]),
        matches=matches,
    ), search


def informed(
    target_i: ScanFeatures,
    source_j: ScanFeatures,
    result: PairResult,
    search: tuple[np.ndarray, np.ndarray],
    voxel: float,
    icp_distance: float,
    information: Information | None = None,
) -> PairResult:
    """``result`` (``scored``, with its ``search``) carrying ``information`` when given and measured, else the
    matching grid's (``registration_information``; None with too few close pairs)."""
    if information is None:
        information = registration_information(target_i, source_j, result.T, icp_distance * voxel, search)
    if information is not None:
        result.information, result.free, result.loose = information.measured, information.free, information.loose
        result.bounded = information.matrix if information.free else None
    return result
