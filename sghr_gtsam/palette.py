"""Colours shared by the recording and the summary picture, so that a scan and a flag look the same in both."""

from __future__ import annotations

import colorsys
from collections.abc import Mapping, Sequence

import numpy as np

_TABLEAU10 = ("1f77b4", "ff7f0e", "2ca02c", "d62728", "9467bd", "8c564b", "e377c2", "7f7f7f", "bcbd22", "17becf")
FLAG_COLOURS = {
    "unplaced": (255, 40, 40),
    "single registration": (255, 170, 0),
    "loop error": (230, 60, 230),
    "competing placement": (255, 120, 160),
    "free space": (150, 90, 255),
    "loose": (0, 200, 200),
}
"""8-bit colour of each scan flag (``result.FLAGS``: a box in the recording, a ring in summary.png)."""
REJECTED = (255, 70, 40)
"""Edges synchronization rejected: red-orange, apart from the kept edges' colour for red-green colour blindness
too (kept edges are light blue on the viewer's dark background and near-black on the picture's white)."""
EDGE_COLOURS = {
    "rejected": REJECTED,
    "failed": (150, 150, 150),
    "contradicted": FLAG_COLOURS["free space"],
    "overruled": (255, 215, 0),
    "unplaced": (110, 200, 80),
}
"""8-bit colour of each ``registration.edges.EDGE_STATUS`` but "kept" (whose colour depends on the background:
``recording.KEPT``, ``plots.KEPT_COLOUR``): a failed registration grey (no measurement), a contradicted one in the
violet of scans doubted for free space (the same evidence), an overruled one yellow, one between unplaced scans
green."""


def first_flags(names: Sequence[str], flags: Mapping[str, Sequence[str]]) -> list[str]:
    """Per scan of ``names``: the first of ``flags`` (flag -> the scans it marks, in report order) that marks it, ""
    for none: the per-scan label that ``label_colours`` colours."""
    label = {}
    for flag, marked in reversed(list(flags.items())):
        label.update(dict.fromkeys(marked, flag))
    return [label.get(name, "") for name in names]


def label_colours(
    labels: Sequence[str],
    table: Mapping[str, tuple[int, int, int]] = FLAG_COLOURS,
    other: tuple[int, int, int] = (255, 255, 255),
) -> np.ndarray:
    """(N, 3) uint8: each scan's colour for its label in ``table`` (a flag's, by default), ``other`` for a label the
    table lacks: how the recording and summary.png colour scans by any per-scan label."""
    return np.array([table.get(label, other) for label in labels], dtype=np.uint8).reshape(-1, 3)


def scan_colours(n: int) -> np.ndarray:
    """(n, 3) uint8, one categorical colour per scan, the same on every run: Tableau's 10 hues, then each next
    colour the one farthest (in RGB) from all chosen so far among a grid of saturated, mid-light colours, so
    that no two scans look alike: the smallest distance between two of them (0-255 units) is 67 up to 30 scans,
    59 at 60, 43 at 100; past the grid's 576 colours they repeat."""
    chosen = [np.array([int(c[k : k + 2], 16) for k in (0, 2, 4)]) / 255.0 for c in _TABLEAU10[: min(n, 10)]]
    if n > 10:
        grid = np.array(
            [
                colorsys.hsv_to_rgb(h, s, v)
                for s in (0.35, 0.6, 0.85, 1.0)
                for h in np.linspace(0, 1, 48, endpoint=False)
                for v in (0.45, 0.7, 0.95)
            ]
        )
        nearest = np.min(np.linalg.norm(grid[:, None] - np.array(chosen)[None], axis=2), axis=1)
        for _ in range(min(n - 10, len(grid))):
            best = int(np.argmax(nearest))  # ties: the first
            chosen.append(grid[best])
            nearest = np.minimum(nearest, np.linalg.norm(grid - grid[best], axis=1))
    return np.round(np.resize(np.array(chosen), (n, 3)) * 255).astype(np.uint8)
