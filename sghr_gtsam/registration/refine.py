"""Multi-scale ICP of a pair from a pose guess: the refinement of kept edges and the registration of loop
closures.

A scan's ``Pyramid`` holds its points on grids of voxel v and v/2 (never finer than the scan's own spacing).
``refine_pair`` runs GICP coarse to fine from ``T_init`` (in the synchronized poses: ``T_i⁻¹ T_j``),
each level starting where the coarser one ended, as Open3D's reconstruction system refines its fragments; the
final transform is then scored on the matching grid like a global registration (``score_pair``), so that a
refined edge and a loop closure carry the same kind of weight as the edges they join. Its information comes
from the finest level instead, the grid the transform was aligned on: on the matching grid the same transform
gets σ 2-3× what its error spread is (calibrated covariances in the journal at 18b90a6: git show
18b90a6:docs/BENCHMARKS.md). What that information cannot see is how the estimate depends on the grid itself
(which points average into a cell, which neighbours a normal is fitted on): the same for every draw of noise, so no
spread of residuals shows it. The move from the
next coarser level's transform to the finest one's measures it, if that error shrinks in proportion to the grid
(half the cell, half the error: the move then equals the finest level's own error); it is kept as
``PairResult.grid`` and added to the reported covariance (``gtsam_api.pose_covariances``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import gtsam
import numpy as np
import open3d as o3d
import small_gicp
from scipy.spatial import cKDTree

from sghr_gtsam.cache import Cache, Kind, refined_key
from sghr_gtsam.config import Config
from sghr_gtsam.features.local import GICP_BYTES, ScanFeatures, search_structures
from sghr_gtsam.registration.icp import gicp
from sghr_gtsam.registration.information import registration_information
from sghr_gtsam.registration.pairwise import PAIRS, PairResult, informed, scored
from sghr_gtsam.se3 import inv_T, rotation_angle
from sghr_gtsam.store import Stored, pair_map
from sghr_gtsam.types import Scan

LEVELS = (1.0,)
"""Grid of each level, in voxels v. Open3D's refine_registration adds v/4; on six object pairs started a voxel
off GT, v/4 landed within 0.03° of what v/2 gives (0.03-0.38° from GT) at 3× the time (0.24 s a pair against
0.08 s), and on dense 3DMatch fragments its 100k-point grids cost 0.7-2.5 s a pair."""
LEVEL_DISTANCE = (2.0, 1.5)
"""GICP correspondence distance of each level, in that level's voxels: the coarse level admits the
synchronized guess's drift (a few centimetres on 3DMatch), the fine ones only close neighbours."""
LEVEL_ITERATIONS = (10, 10)
"""From a guess 1° / v/2 off GT GICP converges within these on 36-38 of 40 3DMatch pairs; 20, small_gicp's default,
converges on all and turned two 3DMatch scenes' models both ways, no clear gain
(the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""
STEP_VOXELS = 0.025
"""GICP has converged when a step moves the scan less than this (voxels v) and turns it less than 0.1°. In voxels,
as every other length here, so that a scene registers alike in any unit (small_gicp's default, 1e-3 in scene units,
was 0.0004 v in millimetres: settled ICPs ran out of iterations and their edges were lost). v/40 is that default
at the 3DMatch scenes' 4 cm voxel; on a scene of repeated desks a 2 % change of it turns the run's path
(the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""
MAX_MOVE_DEG = 5.0
MAX_MOVE_VOXELS = 3.0
"""ICP's reach: a registration of a weak group that moves it less than this leaves it where loop closure from its
current place finds it (``densify.register_weak_groups``)."""
MIN_FITNESS = 0.2
"""Fraction of the source's grid points within the ICP distance of the target after the loop's ICP."""


@dataclass
class Level:
    """One pyramid grid ready for GICP and ``registration_information`` (an ``information.Grid``)."""

    points: np.ndarray
    normals: np.ndarray
    cloud: small_gicp.PointCloud
    cloud_tree: small_gicp.KdTree
    point_tree: cKDTree


@dataclass
class Pyramid:
    """One scan's points on the grids ``voxels`` (coarse to fine), in the scan's own frame. Pickles as
    arrays; each level's GICP cloud is built on first use in whichever process uses it."""

    voxels: tuple[float, ...]
    grids: tuple[np.ndarray, ...]

    def __post_init__(self) -> None:
        self._levels: dict[int, Level] = {}

    def __getstate__(self) -> dict:
        return {"voxels": self.voxels, "grids": self.grids}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._levels = {}

    @property
    def nbytes(self) -> int:
        """Memory it holds: its grids and the levels built so far (``features.local.GICP_BYTES`` a point)."""
        return sum(g.nbytes for g in self.grids) + sum(len(self.grids[k]) * GICP_BYTES for k in self._levels)

    def level(self, k: int) -> Level:
        if k not in self._levels:
            # The same covariances as the matching grid's, and the normals from the same neighbourhoods.
            cloud, tree, point_tree = search_structures(self.grids[k], with_normals=True)
            self._levels[k] = Level(self.grids[k], np.asarray(cloud.normals())[:, :3], cloud, tree, point_tree)
        return self._levels[k]


def _encode_pyramid(p: Pyramid) -> dict[str, np.ndarray]:
    return {"voxels": np.array(p.voxels), **{f"grid{k}": g for k, g in enumerate(p.grids)}}


def _decode_pyramid(a: dict[str, np.ndarray]) -> Pyramid:
    voxels = tuple(float(v) for v in a["voxels"])
    grids = tuple(a[f"grid{k}"] for k in range(len(voxels)))
    if any(g.ndim != 2 or g.shape[1] != 3 or not np.isfinite(g).all() for g in grids):
        raise ValueError("pyramid entry of (n, 3) grids with non-finite values or another shape")
    return Pyramid(voxels, grids)


def _encode_refined(result: tuple[PairResult, bool]) -> dict[str, np.ndarray]:
    pair, converged = result
    return {**PAIRS.encode(pair), "converged": np.bool_(converged)}


def _decode_refined(a: dict[str, np.ndarray]) -> tuple[PairResult, bool]:
    return PAIRS.decode(a), bool(a["converged"])


PYRAMIDS = Kind("pyramids", _encode_pyramid, _decode_pyramid)
"""A scan's refinement grids in the cache and the store (``cache.Kind``)."""
REFINED = Kind("refined", _encode_refined, _decode_refined)
"""A pair's re-registration from a synchronized guess, and whether its ICP converged (``refine_pair``), in the cache
(``cache.Kind``)."""


def build_pyramid(points: np.ndarray, voxel: float) -> Pyramid:
    """The grids of ``LEVELS`` for a scan's raw ``points``; a level that would not thin the points any
    more than the previous one (the scan's own spacing reached) ends the pyramid."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    voxels, grids = [], []
    for scale in LEVELS:
        grid = np.asarray(pcd.voxel_down_sample(scale * voxel).points)
        if grids and len(grid) < 1.5 * len(grids[-1]):
            break
        voxels.append(scale * voxel)
        grids.append(grid)
    return Pyramid(tuple(voxels), tuple(grids))


def scan_pyramid(voxel: float, scan: Scan) -> Pyramid:
    """An executor task: ``build_pyramid`` of ``scan``, read where the task runs."""
    return build_pyramid(scan.read()[0], voxel)


def _levels(target_i: Pyramid, source_j: Pyramid) -> int:
    return min(len(target_i.voxels), len(source_j.voxels))


def _distance(target_i: Pyramid, k: int) -> float:
    return LEVEL_DISTANCE[k] * target_i.voxels[k]


def multiscale_icp(target_i: Pyramid, source_j: Pyramid, T_init: np.ndarray) -> tuple[np.ndarray, bool, np.ndarray]:
    """GICP of scan j onto scan i, coarse to fine from ``T_init``; the final ``T_ij``, whether the finest
    level converged, and the ``T_ij`` of the level before the finest (``T_init`` when there is one level)."""
    T, converged = np.asarray(T_init, dtype=float), False
    for k in range(_levels(target_i, source_j)):
        coarser = T
        result = gicp(
            target_i.level(k),
            source_j.level(k),
            T,
            _distance(target_i, k),
            max_iterations=LEVEL_ITERATIONS[k],
            translation_epsilon=STEP_VOXELS * target_i.voxels[0],
        )
        T, converged = result.T_target_source, bool(result.converged)
    return T, converged, coarser


def stays_near(T: np.ndarray, guess: np.ndarray, voxel: float) -> bool:
    """Whether ``T`` lies within ``MAX_MOVE_DEG`` and ``MAX_MOVE_VOXELS`` voxels of ``guess``."""
    move = inv_T(guess) @ T
    return bool(
        rotation_angle(move[:3, :3]) <= np.radians(MAX_MOVE_DEG)
        and np.linalg.norm(move[:3, 3]) <= MAX_MOVE_VOXELS * voxel
    )


def refine_pair(
    target_i: ScanFeatures,
    source_j: ScanFeatures,
    pyramid_i: Pyramid,
    pyramid_j: Pyramid,
    T_init: np.ndarray,
    voxel: float,
    icp_distance: float,
    min_inliers: int,
    matches: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[PairResult, bool]:
    """Multi-scale ICP from ``T_init``, and whether its finest level converged. Only then is the pair scored at the
    result (``score_pair``, on the pair's earlier ``matches`` when given), and only a result that ``confirms`` at
    ``min_inliers`` gets the information of the finest level's alignment (the matching grid's when that level has
    too few close pairs): one that enters no graph needs none. Otherwise the result has no inliers and no
    information."""
    start = time.perf_counter()
    T, converged, coarser = multiscale_icp(pyramid_i, pyramid_j, T_init)
    if not converged:
        # ICP still moving is no registration, whatever its score: skipping the scoring saves the descriptor
        # matching and the information (40 % of a pair on 3DMatch).
        return PairResult(T, 0, 0.0, 0.0, None, time.perf_counter() - start, matches=matches), False
    result, search = scored(target_i, source_j, T, voxel, icp_distance, matches)
    if confirms(result, True, min_inliers):
        finest = _levels(pyramid_i, pyramid_j) - 1
        information = registration_information(
            pyramid_i.level(finest), pyramid_j.level(finest), T, _distance(pyramid_i, finest)
        )
        result = informed(target_i, source_j, result, search, voxel, icp_distance, information)
        if finest > 0:
            result.grid = gtsam.Pose3.Logmap(gtsam.Pose3(T).between(gtsam.Pose3(coarser)))
    result.seconds = time.perf_counter() - start
    return result, True


def confirms(result: PairResult, converged: bool, min_inliers: int) -> bool:
    """A refined edge or a loop closure enters the graph when its ICP converged (from ``refine_pair``) with enough
    overlap and at least ``min_inliers`` descriptor matches agree with it: the bar a global registration must pass.
    How far ICP moved from its guess does not matter: a re-registration that passes is evidence on the same terms
    as a global registration, and synchronization weighs it against the rest. (A bound of 5° / 3 voxels on that
    move refused the loop closures that would straighten a model bent by a few degrees.)"""
    return bool(converged and result.inliers >= min_inliers and result.fitness >= MIN_FITNESS)


def _refine_task(shared: tuple[Stored, Stored, float, float, int], task: tuple) -> tuple[PairResult, bool]:
    features, pyramids, voxel, icp_distance, min_inliers = shared
    a, b, T_init, matches = task
    return refine_pair(
        features[a], features[b], pyramids[a], pyramids[b], T_init, voxel, icp_distance, min_inliers, matches
    )


def register_from_guesses(
    features: Stored,
    pyramids: Stored,
    ij: np.ndarray,
    guesses: np.ndarray,
    voxel: float,
    config: Config,
    matches: list | None = None,
    on_result: Callable[[int, object], None] | None = None,
    cache: Cache | None = None,
) -> tuple[list[PairResult], np.ndarray]:
    """``refine_pair`` of every (i, j) row of ``ij`` from its guess ``T_ij`` (E, 4, 4), on the scans' stored
    ``features`` and ``pyramids``, over the executor's processes (``config.workers``, ``config.ray``), with each
    pair's earlier descriptor ``matches`` where known (None: found anew): the results and whether each converged.
    ``on_result`` as in ``parallel_map`` (progress); ``cache``: results stored and reused (``cache.Cache``)."""
    matches = matches or [None] * len(ij)
    tasks = [(int(a), int(b), T, m) for (a, b), T, m in zip(ij, guesses, matches)]
    keys = [
        refined_key(features.keys[a], features.keys[b], T, config.icp_distance, config.inlier_bar)
        for a, b, T, _ in tasks
    ]
    shared = (features, pyramids, voxel, config.icp_distance, config.inlier_bar)
    out = pair_map(cache, REFINED, _refine_task, shared, ij, tasks, keys, config.workers, on_result, config.ray)
    return [p for p, _ in out], np.array([c for _, c in out], dtype=bool)
