"""Pictures of a run with matplotlib (imported when a picture is drawn, never at import time): the summary
written to ``OUT/summary.png`` and the weight history the notebook shows.

``summary_figure``: left, the registered scans seen along their common axis of least extent (a floor plan for a
room: the axis of least extent is the vertical one) coloured by scan with a categorical palette (by part when the
verification left more than one, ``verify``), the pose graph
over them (scan centres; kept edges solid, as wide as their weight; rejected, contradicted and overruled edges dashed
in their status's colour, ``palette.EDGE_COLOURS``; failed registrations and edges between unplaced scans not drawn,
and every status counted in the legend; each doubtful scan ringed in its reason's colour, ``palette.FLAG_COLOURS``);
right, the histogram of the edges' rotation residuals, kept and rejected apart. The title wraps onto more lines
rather than run past the figure's edge.
Figures are built on ``matplotlib.figure.Figure`` with the Agg canvas, so drawing them never opens a window
and never touches pyplot's global state; they show inline in Jupyter as PNG (``_repr_png_``), which a bare
``Figure`` does not do unless pyplot's inline backend is active.
"""

from __future__ import annotations

import io
from collections.abc import Iterable
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sghr_gtsam.io.atomic import atomic_path
from sghr_gtsam.palette import EDGE_COLOURS, FLAG_COLOURS, REJECTED, first_flags, label_colours, scan_colours
from sghr_gtsam.result import DOUBTS

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from sghr_gtsam.result import RunResult
    from sghr_gtsam.types import SyncResult

RASTER_WIDTH = 400
"""The top view is drawn as an image this many pixels wide (``_Raster``): every point of the voxelised scans
at the cost of one image, where a scatter of 60,000 points took 0.8 s to draw."""

KEPT_COLOUR = "#1a1a1a"
DRAWN = ("rejected", "contradicted", "overruled")
"""The statuses besides "kept" drawn as dashed lines; the others (a failed registration: no measurement; an edge
between unplaced scans: no pose to draw it at) are only counted in the legend."""
TITLE_CHARS = 70
"""The top view's title wraps at this many characters (at its font size, about the view's width)."""


def _hex(rgb: tuple[int, int, int]) -> str:
    return "#" + "".join(f"{c:02x}" for c in rgb)


REJECTED_COLOUR = _hex(REJECTED)


@cache
def _figure_class() -> type:
    from matplotlib.figure import Figure

    class InlineFigure(Figure):
        def _repr_png_(self) -> bytes:
            buffer = io.BytesIO()
            self.savefig(buffer, format="png")
            return buffer.getvalue()

    return InlineFigure


def _view_axes(clouds: Iterable[np.ndarray]) -> np.ndarray:
    """(3, 2): the two principal axes of largest extent of the points of ``clouds`` (each read once), the top
    view's x and y."""
    count, total, scatter, origin = 0, np.zeros(3), np.zeros((3, 3)), None
    for P in clouds:
        origin = P[0] if origin is None else origin  # sums about a point of the scene keep their digits
        Q = P - origin
        count, total, scatter = count + len(Q), total + Q.sum(0), scatter + Q.T @ Q
    mean = total / count
    _, vectors = np.linalg.eigh(scatter / count - np.outer(mean, mean))
    return vectors[:, ::-1][:, :2]


class _Raster:
    """An (H, W, 4) RGBA image of points drawn scan by scan over the extent [x0, x1, y0, y1] of ``lo``-``hi``. A pixel
    takes the colour of one of its points (each drawn with a random priority, the highest wins) and an opacity that
    grows with their number, so that walls, which stand across the view, show above floors and ceilings, which
    spread over it."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, rng: np.random.Generator) -> None:
        span = np.maximum(hi - lo, 1e-12)
        self.lo, self.pixel, self.rng = lo, span[0] / RASTER_WIDTH, rng
        self.shape = (int(np.ceil(span[1] / self.pixel)) + 1, RASTER_WIDTH + 1)
        self.extent = [lo[0], lo[0] + self.shape[1] * self.pixel, lo[1], lo[1] + self.shape[0] * self.pixel]
        self._rgb = np.zeros((self.shape[0] * self.shape[1], 3))
        self._priority = np.full(self.shape[0] * self.shape[1], -1.0)
        self._count = np.zeros(self.shape[0] * self.shape[1])

    def add(self, xy: np.ndarray, rgb: np.ndarray) -> None:
        """Points ``xy`` (P, 2) of one colour ``rgb``."""
        col, row = ((xy - self.lo) / self.pixel).astype(int).T  # within the image: lo-hi bound every scan's xy
        cell = row * self.shape[1] + col
        priority = self.rng.random(len(cell))
        top = np.full_like(self._priority, -1.0)
        np.maximum.at(top, cell, priority)
        wins = (priority == top[cell]) & (priority > self._priority[cell])
        self._priority[cell[wins]] = priority[wins]
        self._rgb[cell[wins]] = rgb
        np.add.at(self._count, cell, 1.0)

    def image(self) -> np.ndarray:
        count = self._count.reshape(self.shape)
        image = np.zeros((*self.shape, 4))
        image[..., :3] = self._rgb.reshape(*self.shape, 3)
        full = max(np.percentile(count[count > 0], 90), 1.0)
        image[..., 3] = np.where(count > 0, np.clip(count / full, 0.25, 1.0), 0.0)
        return image


def summary_figure(result: RunResult, status: list[str] | None = None) -> Figure:
    """The run at a glance (module doc). ``status``: each edge's ``registration.edges.EDGE_STATUS`` key (computed when
    not given)."""
    from matplotlib.collections import LineCollection
    from matplotlib.lines import Line2D

    from sghr_gtsam.registration.edges import EDGE_STATUS, edge_status

    if status is None:
        status = edge_status(result)
    placed = result.registered
    n = len(result.names)
    parts = [] if result.verdict is None else result.verdict.parts
    if len(parts) > 1:  # a scene in parts: each part in its colour, so that the parts show apart
        part_of = result.verdict.part_of()
        colours = scan_colours(len(parts))[[part_of.get(name, 0) for name in result.names]] / 255.0
    else:
        colours = scan_colours(n) / 255.0

    def world(k: int) -> np.ndarray:
        """Scan k's points in the world, read anew at each pass (no pass holds every scan's points); a scan without
        points (an incremental session's add_node, a loaded results folder) is its origin."""
        P = result.world_points(k)
        return P if len(P) else result.poses[k, :3, 3][None]

    axes = _view_axes(world(k) for k in placed)
    centres = np.zeros((n, 2))
    lo, hi = np.full(2, np.inf), np.full(2, -np.inf)
    for k in placed:
        xy = world(k) @ axes
        centres[k] = xy.mean(0)
        lo, hi = np.minimum(lo, xy.min(0)), np.maximum(hi, xy.max(0))
    raster = _Raster(lo, hi, np.random.default_rng(0))
    for k in placed:
        raster.add(world(k) @ axes, colours[k])
    image, extent = raster.image(), raster.extent

    fig = _figure_class()(figsize=(11, 5), dpi=90)
    fig.subplots_adjust(left=0.01, right=0.98, bottom=0.11, top=0.93, wspace=0.12)
    top, hist = fig.subplots(1, 2, width_ratios=[1.6, 1])
    top.imshow(image, extent=extent, origin="lower", interpolation="nearest")
    g, weights = result.graph, result.sync.weights
    by_status = {
        key: [e for e in range(g.num_edges) if status[e] == key]
        for key in EDGE_STATUS
        if key == "kept" or key in status
    }
    kept, rejected = by_status["kept"], by_status.get("rejected", [])
    w_max = max((weights[e] for e in kept), default=1.0)
    segments = np.stack([centres[g.i], centres[g.j]], axis=1)
    for key in DRAWN:
        top.add_collection(
            LineCollection(
                segments[by_status.get(key, [])],
                colors=_hex(EDGE_COLOURS[key]),
                linewidths=0.8,
                linestyles=(0, (3, 2)),
                alpha=0.8,
                label=key,
            )
        )
    top.add_collection(
        LineCollection(
            segments[kept], colors=KEPT_COLOUR, alpha=0.85, label="kept", linewidths=0.6 + 2.4 * weights[kept] / w_max
        )
    )
    doubts = {flag: result.flags[flag] for flag in DOUBTS if result.flags[flag]}
    marks = first_flags(result.names, doubts)  # a scan with several flags shows the first, in report order
    ring = {k: _hex(tuple(c)) for k, c in enumerate(label_colours(marks)) if marks[k]}
    top.scatter(
        centres[placed, 0],
        centres[placed, 1],
        s=36,
        c=colours[placed],
        zorder=3,
        edgecolors=[ring.get(k, "black") for k in placed],
        linewidths=[2.5 if k in ring else 0.8 for k in placed],
    )
    if n <= 40:
        for k in placed:
            top.annotate(str(k), centres[k], xytext=(4, 4), textcoords="offset points", fontsize=7, zorder=4)
    top.set_aspect("equal", adjustable="datalim")
    top.set_xticks([])
    top.set_yticks([])
    title = _wrapped(
        [
            f"{len(placed)}/{n} scans placed",
            *([f"{len(parts)} parts (coloured)"] if len(parts) > 1 else []),
            f"{len(result.unregistered)} unregistered",
            *(f"{len(scans)} {flag}" for flag, scans in doubts.items()),
        ]
    )
    top.set_title(title, fontsize=10)
    fig.subplots_adjust(top=0.93 - 0.04 * title.count("\n"))
    legend = [Line2D([], [], color=KEPT_COLOUR, lw=2, label=f"kept edge ({len(kept)}; width = weight)")]
    legend += [
        Line2D(
            [],
            [],
            color=_hex(EDGE_COLOURS[key]),
            lw=1,
            ls=(0, (3, 2)) if key in DRAWN else ":",
            label=f"{key} edge ({len(edges)}{'' if key in DRAWN else ', not drawn'})",
        )
        for key, edges in by_status.items()
        if key != "kept"
    ]
    legend += [
        Line2D([], [], marker="o", ls="", mfc="white", mec=_hex(FLAG_COLOURS[flag]), mew=2.5, label=flag)
        for flag in doubts
    ]
    top.legend(handles=legend, loc="upper right", fontsize=8, framealpha=0.8)

    residual = result.sync.residual_deg
    groups = [(kept, KEPT_COLOUR, "kept"), (rejected, REJECTED_COLOUR, "rejected")]
    values = np.maximum(residual[kept + rejected], 1e-3) if kept + rejected else np.array([1e-3])
    bins = np.geomspace(values.min() / 1.5, max(values.max() * 1.5, 1.0), 30)
    for edges, colour, name in groups:
        if edges:
            hist.hist(
                np.maximum(residual[edges], 1e-3), bins=bins, color=colour, alpha=0.7, label=f"{name} ({len(edges)})"
            )
    hist.set_xscale("log")
    hist.set_xlabel("rotation residual at the final poses [deg]")
    hist.set_ylabel("edges")
    hist.set_title("edge residuals", fontsize=10)
    if kept + rejected:  # no edge, no legend (matplotlib warns of an empty one)
        hist.legend(fontsize=8)
    return fig


def _wrapped(parts: list[str]) -> str:
    """``parts`` joined by " · ", broken between parts into lines of at most ``TITLE_CHARS`` characters."""
    lines = [parts[0]]
    for part in parts[1:]:
        if len(lines[-1]) + 3 + len(part) > TITLE_CHARS:
            lines.append(part)
        else:
            lines[-1] += " · " + part
    return "\n".join(lines)


def write_summary(path: str | Path, result: RunResult, status: list[str] | None = None) -> None:
    """``summary_figure`` as a PNG at ``path``, written atomically."""
    fig = summary_figure(result, status)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")


def weight_history_figure(sync: SyncResult, highlight: list[int] | None = None) -> Figure:
    """Each edge's weight (relative to the largest) over the IRLS iterations of ``sync.history``: history
    reweighting driving the inconsistent edges to zero. ``highlight``: edges drawn in red (e.g. known outliers)."""
    irls = [r for r in sync.history if r.stage == "irls"]
    if not irls:
        raise ValueError("the synchronization recorded no IRLS iteration")
    steps = np.array([r.iteration for r in irls])
    w = np.stack([r.weights / max(float(r.weights.max()), 1e-300) for r in irls])
    marked = set(highlight or [])
    fig = _figure_class()(figsize=(7, 3.2), dpi=90, layout="constrained")  # drawn once, in the notebook
    ax = fig.subplots()
    for e in range(w.shape[1]):
        if e not in marked:
            ax.plot(steps, w[:, e], color="0.55", lw=0.8)
    for e in sorted(marked):
        ax.plot(steps, w[:, e], color=REJECTED_COLOUR, lw=1.8, label=f"edge {e}")
    ax.set_xlabel("IRLS iteration")
    ax.set_ylabel("weight / largest")
    ax.set_yscale("symlog", linthresh=1e-3)
    if marked:
        ax.legend(fontsize=8)
    return fig
