"""Weak groups registered whole: a group of scans that hangs on the rest of the model by
registrations no loop checks (``sync.unverified``), or apart from it, is held together by its own kept edges but
may be placed wrong as a block, e.g. turned 90° in a square room behind one look-alike registration. Loop
closures cannot move it (they start from its place) and retries register its scans one at a time, each as
ambiguous as before. Merged, the group and the rest are far larger than any scan, and one global registration
of the one onto the other (``pairwise.register_pair`` on ``merged`` features) says where the
group belongs. That placement is only a guess: the pairs of scans it makes overlap are registered by ICP from
it (as loop closures are, ``densify``) and enter the graph when they confirm it; synchronization decides."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sghr_gtsam.cells import unique_cells
from sghr_gtsam.config import Config
from sghr_gtsam.features.local import ScanFeatures, grid_features
from sghr_gtsam.registration.pairwise import PairResult, register_pair
from sghr_gtsam.sync.rotation import connected_components
from sghr_gtsam.types import PoseGraph, SyncResult

MIN_SCANS = 2
"""A single weak scan is the retries' business (``retry``); a group has geometry of its own to register."""
GRID = 2.0
"""The merged sides' grid, in voxels: on the run's own grid a merged side of 20-70 thousand points left the right
correspondences few and rarely mutual among the look-alike parts of a whole room (rows of alike desks: 1-9 inliers,
all wrong, 11-89 s a group); at twice the voxel, with FPFH's radius twice as wide in metres, two of its groups
came out within 4.3° / 0.19 m of the truth, in 0.2-3 s."""
MAX_POINTS = 2_000_000
"""Grid points of a merged side above which the group is not tried: FPFH and the descriptor search on the merged
points grow with them (a 500-scan building's whole model), and a group is a refinement, not a stage to wait on."""


def weak_groups(graph: PoseGraph, result: SyncResult, flagged: np.ndarray) -> list[np.ndarray]:
    """The groups to try, largest first: scans of the largest part that are ``flagged`` ((N,) bool, unverified)
    or outside it, joined by the edges ``result`` kept, at least ``MIN_SCANS`` a group."""
    weak = flagged | (result.component != 0)
    kept = (result.weights > 0) & weak[graph.i] & weak[graph.j]
    label = connected_components(graph.n, graph.i, graph.j, kept)
    groups = [np.flatnonzero(weak & (label == g)) for g in np.unique(label[weak])]
    return sorted((g for g in groups if len(g) >= MIN_SCANS), key=lambda g: (-len(g), g[0]))


def merged(
    features: Sequence[ScanFeatures], poses: np.ndarray, members: np.ndarray, voxel: float, config: Config
) -> ScanFeatures | None:
    """The features (``features.local.grid_features``) of the ``members``' grids under ``poses`` (their centred
    frames into the world), merged on one grid of ``GRID`` voxels: each cell's centroid and mean normal, as open3d's
    ``voxel_down_sample`` of all their points would give, but summed one scan at a time, so that only the cells are
    held, not every member's grid points at once. None when they hold more than ``MAX_POINTS`` grid points."""
    cell = GRID * voxel
    total, low = 0, np.full(3, np.inf)
    for k in members:  # open3d's grid starts half a cell below the lowest moved point: a first pass finds it
        points = features[k].points
        total += len(points)
        if total > MAX_POINTS:
            return None
        low = np.minimum(low, (points @ poses[k][:3, :3].T + poses[k][:3, 3]).min(axis=0))
    origin = low - cell / 2
    keys, sums = [], []
    for k in members:
        R, t = poses[k][:3, :3], poses[k][:3, 3]
        points, normals = features[k].points @ R.T + t, features[k].normals @ R.T
        key, inverse = unique_cells(np.floor((points - origin) / cell).astype(np.int64))
        keys.append(key)
        sums.append(_summed(inverse, len(key), np.hstack([points, normals, np.ones((len(points), 1))])))
    _, inverse = unique_cells(np.concatenate(keys))
    total = np.concatenate(sums)
    total = _summed(inverse, int(inverse.max()) + 1, total)
    grid, normal = total[:, :3] / total[:, 6:], total[:, 3:6]
    length = np.linalg.norm(normal, axis=1)
    keep = length > 1e-6  # normals that cancel (two sides of a thin wall) leave no direction
    return grid_features(grid[keep], normal[keep] / length[keep, None], cell, config.fpfh_radius, config.descriptor)


def _summed(index: np.ndarray, n: int, values: np.ndarray) -> np.ndarray:
    """(n, c): the rows of ``values`` (m, c) summed by ``index`` (m,)."""
    out = np.zeros((n, values.shape[1]))
    np.add.at(out, index, values)
    return out


def register_group(
    target: ScanFeatures | None,
    features: Sequence[ScanFeatures],
    poses: np.ndarray,
    group: np.ndarray,
    voxel: float,
    config: Config,
) -> PairResult | None:
    """The global registration of the merged ``group`` (under ``poses``) onto ``target``, the rest's ``merged``
    features: its ``T`` maps the group's world frame into the rest's, so the group's scans belong at
    ``T @ poses[group]``. None when a side is too large (``MAX_POINTS``)."""
    source = merged(features, poses, group, voxel, config)
    if target is None or source is None:
        return None
    return register_pair(
        target, source, GRID * voxel, config.matcher, config.icp_distance, config.seed, config.inlier_bar
    )
