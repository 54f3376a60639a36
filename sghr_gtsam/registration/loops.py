"""Loop proposals: pairs never registered that overlap under the synchronized poses.

The cheap test is a shared occupancy grid: each placed scan marks the cells (of ``CELL`` voxels) its
points fall in, in the world frame; a pair's predicted overlap is the number of cells both mark over the
smaller scan's count (one sparse product for all pairs). Pairs above ``MIN_OVERLAP`` are then registered by
multi-scale ICP from the synchronized guess (``refine.register_from_guesses``) and enter the graph when the
result passes the bar of a registration (``refine.confirms``)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import sparse

from sghr_gtsam.cells import unique_cells
from sghr_gtsam.se3 import transform_points

CELL = 2.0
"""Occupancy cell, in voxels: coarse enough that the synchronized poses' drift (a voxel or two) keeps a
true overlap visible, fine enough that two walls a metre apart do not overlap."""
MIN_OVERLAP = 0.3
"""Predicted overlap above which a pair is worth an ICP: 3DMatch's own threshold for a benchmark pair."""


def predicted_overlap(points: Sequence[np.ndarray], poses: np.ndarray, placed: np.ndarray, voxel: float) -> np.ndarray:
    """(N, N) overlap of every pair of placed scans (``placed``: (N,) bool) under ``poses``: cells shared over
    the smaller scan's cells; 0 for pairs with an unplaced scan and on the diagonal. ``points[k]`` is read once,
    one scan at a time."""
    n = len(points)
    rows, keys = [], []
    for k in np.flatnonzero(placed):
        cells = unique_cells(np.floor(transform_points(poses[k], points[k]) / (CELL * voxel)).astype(np.int64))[0]
        rows.append(np.full(len(cells), k))
        keys.append(cells)
    overlap = np.zeros((n, n))
    if not rows:
        return overlap
    _, col = unique_cells(np.concatenate(keys))
    A = sparse.csr_matrix((np.ones(len(col)), (np.concatenate(rows), col)), shape=(n, col.max() + 1))
    shared = (A @ A.T).toarray()
    size = np.diag(shared)
    smaller = np.minimum(size[:, None], size[None, :])
    overlap = np.divide(shared, smaller, out=np.zeros((n, n)), where=smaller > 0)
    np.fill_diagonal(overlap, 0.0)
    return overlap


def propose_loops(overlap: np.ndarray, registered: np.ndarray, per_scan: int) -> np.ndarray:
    """(L, 2) pairs i < j not yet ``registered`` ((N, N) bool) with overlap above ``MIN_OVERLAP``, at most
    ``per_scan`` new pairs a scan, highest overlap first."""
    i, j = np.nonzero(np.triu(overlap >= MIN_OVERLAP, 1) & ~registered)
    order = np.argsort(-overlap[i, j], kind="stable")
    count = np.zeros(len(overlap), dtype=int)
    chosen = []
    for e in order:
        a, b = i[e], j[e]
        if count[a] < per_scan and count[b] < per_scan:
            count[a] += 1
            count[b] += 1
            chosen.append((a, b))
    return np.array(chosen, dtype=np.int64).reshape(-1, 2)
