"""Colours shared by the recording and the summary picture, so that a scan and a flag look the same in both."""

from __future__ import annotations

import colorsys

import numpy as np

_TABLEAU10 = ("1f77b4", "ff7f0e", "2ca02c", "d62728", "9467bd", "8c564b", "e377c2", "7f7f7f", "bcbd22", "17becf")
FLAG_COLOURS = {"unplaced": (255, 40, 40), "single registration": (255, 170, 0), "loop error": (230, 60, 230),
                "competing placement": (255, 120, 160), "free space": (150, 90, 255), "loose": (0, 200, 200)}
"""8-bit colour of each scan flag (``result.FLAGS``: a box in the recording, a ring in summary.png)."""
REJECTED = (255, 70, 40)
"""Edges synchronization rejected: red-orange, apart from the kept edges' colour for red-green colour blindness
too (kept edges are light blue on the viewer's dark background and near-black on the picture's white)."""


def scan_colours(n: int) -> np.ndarray:
    """(n, 3) uint8, one categorical colour per scan, the same on every run: Tableau's 10 hues, then each next
    colour the one farthest (in RGB) from all chosen so far among a grid of saturated, mid-light colours, so
    that no two scans look alike: the smallest distance between two of them (0-255 units) is 67 up to 30 scans,
    59 at 60, 43 at 100; past the grid's 576 colours they repeat."""
    chosen = [np.array([int(c[k:k + 2], 16) for k in (0, 2, 4)]) / 255.0 for c in _TABLEAU10[: min(n, 10)]]
    if n > 10:
        grid = np.array([colorsys.hsv_to_rgb(h, s, v) for s in (0.35, 0.6, 0.85, 1.0)
                         for h in np.linspace(0, 1, 48, endpoint=False) for v in (0.45, 0.7, 0.95)])
        nearest = np.min(np.linalg.norm(grid[:, None] - np.array(chosen)[None], axis=2), axis=1)
        for _ in range(min(n - 10, len(grid))):
            best = int(np.argmax(nearest))  # ties: the first
            chosen.append(grid[best])
            nearest = np.minimum(nearest, np.linalg.norm(grid - grid[best], axis=1))
    return np.round(np.resize(np.array(chosen), (n, 3)) * 255).astype(np.uint8)
