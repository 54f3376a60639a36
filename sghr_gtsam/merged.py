"""The merged cloud a run writes (merged.ply): every registered scan under its pose, one point per occupied cell of
the voxel grid, streamed so that no more than one scan and the merged grid are held at once."""

from __future__ import annotations

import numpy as np

from sghr_gtsam.result import RunResult


def merged_cloud(result: RunResult) -> np.ndarray:
    """All registered scans under their poses, voxel-downsampled once more where they overlap: one point per
    occupied cell of the voxel grid, the mean of the scans' points in it. Reads one scan at a time and holds the
    merged grid (the scene's size, not the scans' count)."""
    merged = _VoxelMeans(result.voxel)
    for k in result.registered:
        merged.add(result.world_points(k))
    return merged.points()


class _VoxelMeans:
    """Points gathered batch by batch into the cells of a voxel grid: per occupied cell the mean of its points."""

    _BATCH = 250_000  # points gathered before they are merged into the cells: a few MB at a time

    def __init__(self, voxel: float) -> None:
        self.voxel = voxel
        self._cells = np.zeros((0, 3), dtype=np.int64)
        self._sums = np.zeros((0, 3))
        self._counts = np.zeros(0)
        self._pending: list[np.ndarray] = []

    def add(self, points: np.ndarray) -> None:
        self._pending.append(points)
        if sum(map(len, self._pending)) >= self._BATCH:
            self._merge()

    def points(self) -> np.ndarray:
        self._merge()
        return self._sums / self._counts[:, None]

    def _merge(self) -> None:
        if not self._pending:
            return
        new = np.concatenate(self._pending)
        self._pending = []
        cells = np.concatenate([self._cells, np.floor(new / self.voxel).astype(np.int64)])
        sums = np.concatenate([self._sums, new])
        counts = np.concatenate([self._counts, np.ones(len(new))])
        order = np.lexsort(cells.T[::-1])
        cells = cells[order]
        starts = np.concatenate([[0], np.flatnonzero(np.any(cells[1:] != cells[:-1], axis=1)) + 1])
        self._cells = cells[starts]
        self._sums = np.add.reduceat(sums[order], starts)
        self._counts = np.add.reduceat(counts[order], starts)
