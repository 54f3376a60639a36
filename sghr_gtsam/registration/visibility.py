"""Free-space check of a registered pair: a scan seen from one viewpoint (a TLS station, a LiDAR or depth frame,
each in its own sensor frame) also tells where there is nothing: the space between its sensor and the first
surface in each direction. A transform that puts the other scan's surfaces there contradicts what the scan saw,
whatever the descriptors agreed on: look-alike rooms and corridors register with many inliers to the wrong place
(a generated 100-scan building: 21 such edges among 222 kept, which joined its halves wrongly).

Only scans whose frame origin is their viewpoint can say it. A scan seen from its origin hides almost none of
its own points behind others (``SELF_HIDDEN``); a fused RGB-D fragment, an object scan in its object's frame or a
georeferenced scan hides more of them (generated fragments whose camera walked a few decimetres: mostly 2.2-7.9 %; an
object's range scan: 18 %), and its pairs are not checked here; fused fragments' are by the overrule's coarser range
images, once the graph's loops vouch for the scene's frames (``overrule.Viewpoints.vouch``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from sghr_gtsam.store import Attribute, Stored

BIN_DEG = 1.0
"""Angular size of the range image's cells (azimuth x elevation); a cell keeps its nearest point."""
MARGIN_VOXELS = 3.0
"""A point counts as in front of a surface when nearer than it along the ray by more than this many voxels
(range noise, the grid's rounding and a right registration's error stay inside)."""
SELF_HIDDEN = 0.026
"""A scan is seen from its origin when at most this fraction of its points lie behind its own nearest point in
their cell by more than the margin: 99 % of generated stations (rooms, buildings, hotels) hide no more, a few points
at depth edges. An RGB-D fragment fused from a walking camera's frames mostly hides more (generated: 2.2-7.9 %,
1-99 %), and its origin, the first frame's camera, is one viewpoint of many: seen from there, surfaces that later
frames saw around an object lie where the first frame saw nothing, so where many fragments pass, the free space
blames right ones at their true poses (under a bar of 5 %, 10 of 96; under this one 4 pass and none is blamed:
``benchmarks/bench_free_space.py --viewpoints``). A station the bar loses is not judged by the free space at all,
which let wrong joins through on a generated 500-scan building under a bar that kept only the stations under the
fragments' 1 % (2.2 %: 10 misplaced scans verified instead of 6)."""
CONFLICT = 0.15
"""A pair is contradicted when, in either direction, more than this fraction of one scan's points that fall in
cells the other scan observed lie in front of that scan's surface: they would be where it saw nothing.
Measured on a generated 100-scan building (benchmarks, "Free space"): right edges at most 0.09, wrong ones 0.29
at the median."""
MIN_IN_VIEW = 100
"""Points of one scan in cells the other observed below which a pair of placed scans is not judged: the fraction
in front then has a standard error of at most 0.5 / √100 = 0.05, a third of ``CONFLICT`` (scans whose boxes merely
meet may share a handful of cells: 2 points of 6 read 0.33). Registered pairs share far more."""
MAX_PARTNERS = 40
"""Scans each placed scan is tested against at most, the nearest first: a scan placed wrong conflicts with the
scans around it, and a folded model, whose boxes all meet, would otherwise cost N² tests (a generated 500-scan
building: 117 s without this bound)."""
MIN_CONFLICTS = 2
"""A placed scan is blamed for its placement (``contradicted_scans``) when in conflict with at least this many
others."""


def _cells(P: np.ndarray, bin_deg: float = BIN_DEG) -> tuple[np.ndarray, np.ndarray, int]:
    """Ranges (n,) and range-image cells (n,) of points ``P`` (n, 3) seen from the origin, and the cell count."""
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    r = np.sqrt(x * x + y * y + z * z)  # np.linalg.norm's sum in its order, 4x faster on (n, 3): same ranges
    step = np.radians(bin_deg)
    rows, cols = int(np.ceil(np.pi / step)), int(np.ceil(2 * np.pi / step))
    elevation = np.arcsin(np.clip(z / np.maximum(r, 1e-300), -1.0, 1.0))
    azimuth = np.arctan2(y, x)
    row = np.clip(((elevation + np.pi / 2) / step).astype(np.int64), 0, rows - 1)
    col = np.clip(((azimuth + np.pi) / step).astype(np.int64), 0, cols - 1)
    return r, row * cols + col, rows * cols


def _nearest(r: np.ndarray, cell: np.ndarray, count: int) -> np.ndarray:
    """The range image of points at ranges ``r`` in cells ``cell`` (``_cells``): per cell the nearest point's
    range, inf where the scan saw nothing."""
    image = np.full(count, np.inf)
    np.minimum.at(image, cell, r)
    return image


def hidden_fraction(P: np.ndarray, voxel: float) -> float:
    """The fraction of scan points ``P`` (n, 3) that lie behind the scan's own nearest point in their cell, seen
    from the origin, by more than the margin (1 for no points)."""
    if len(P) == 0:
        return 1.0
    r, cell, count = _cells(P)
    return float(np.mean(r > _nearest(r, cell, count)[cell] + MARGIN_VOXELS * voxel))


def seen_from_origin(P: np.ndarray, voxel: float) -> bool:
    """Whether scan points ``P`` (n, 3) look like one viewpoint's at the origin (``SELF_HIDDEN``)."""
    return hidden_fraction(P, voxel) <= SELF_HIDDEN


def contradicted(conflict: np.ndarray) -> np.ndarray:
    """Which ``free_space_conflict`` values (NaN: not checked) rule their registration out (``CONFLICT``)."""
    return np.nan_to_num(conflict, nan=0.0) > CONFLICT


def range_image(P: np.ndarray, bin_deg: float = BIN_DEG) -> np.ndarray:
    """The range image of scan points ``P`` (n, 3) seen from the origin, in cells of ``bin_deg`` (``_nearest``)."""
    return _nearest(*_cells(P, bin_deg))


def in_front_of(
    image: np.ndarray,
    P: np.ndarray,
    voxel: float,
    margin: float = MARGIN_VOXELS,
    bin_deg: float = BIN_DEG,
    min_seen: int = 1,
    turn: tuple[float, np.ndarray] | None = None,
) -> float:
    """Fraction of points ``P`` (in the frame of the scan whose range image of ``bin_deg`` cells is ``image``) that
    lie in front of its surface by more than ``margin`` voxels, among those in cells it observed (0 with fewer than
    ``min_seen``). ``turn``: (degrees, (n,) each point's range from its own scan's viewpoint): a point must also lie
    in front by more than that turn about either viewpoint moves it (``placement_conflicts``)."""
    seen, fraction = seen_in_front_of(image, P, voxel, margin, bin_deg, turn)
    return fraction if seen >= min_seen else 0.0


def seen_in_front_of(
    image: np.ndarray,
    P: np.ndarray,
    voxel: float,
    margin: float = MARGIN_VOXELS,
    bin_deg: float = BIN_DEG,
    turn: tuple[float, np.ndarray] | None = None,
) -> tuple[int, float]:
    """``in_front_of``'s count of points in observed cells, and the fraction (NaN for none)."""
    r, cell, _ = _cells(P, bin_deg)
    surface = image[cell]
    seen = np.isfinite(surface)
    count = int(seen.sum())
    if not count:
        return 0, float("nan")
    r, surface = r[seen], surface[seen]
    allowed = surface - margin * voxel
    if turn is not None:
        degrees, own_range = turn
        allowed = allowed - 2 * np.sin(np.radians(degrees) / 2) * np.maximum(surface, own_range[seen])
    return count, float(np.mean(r < allowed))


def _in_front(P_i: np.ndarray, P_j: np.ndarray, T_ij: np.ndarray, voxel: float) -> float:
    """Fraction of scan j's points, moved into scan i's frame by ``T_ij``, that lie in front of scan i's surface
    among those in cells scan i observed (0 with none)."""
    return in_front_of(range_image(P_i), P_j @ T_ij[:3, :3].T + T_ij[:3, 3], voxel)


def free_space_conflict(P_i: np.ndarray, P_j: np.ndarray, T_ij: np.ndarray, voxel: float) -> float:
    """How much ``T_ij`` contradicts what scans i and j saw: the larger of the fractions of each scan's points
    that it puts in the other's free space (``_in_front``); both scans seen from their origins."""
    return max(_in_front(P_i, P_j, T_ij, voxel), _in_front(P_j, P_i, np.linalg.inv(T_ij), voxel))


def viewpoints(points: Sequence[np.ndarray], voxel: float, centres: np.ndarray) -> np.ndarray:
    """(N,) bool: which scans (``points[k]`` in scan k's frame, read once each) can say where there is nothing:
    seen from their frame's origin (``seen_from_origin``) and not centred by the pipeline (``centres`` (N, 3),
    ``local_frame.centres``: a centred scan lies far from its input frame's origin, which is no viewpoint)."""
    return np.array([_viewpoint(P, c, voxel) for P, c in zip(points, centres)], dtype=bool)


def _viewpoint(P: np.ndarray, centre: np.ndarray, voxel: float) -> bool:
    """``viewpoints`` of one scan (points ``P``, centred by ``centre``)."""
    return not np.any(centre) and seen_from_origin(P, voxel)


def conflicts(features: Stored, ij: np.ndarray, T: np.ndarray, voxel: float, centres: np.ndarray) -> np.ndarray:
    """(E,) ``free_space_conflict`` of each pair ``ij[e]`` at ``T[e]`` on the scans' feature grids, NaN where a
    scan is not seen from its origin (nothing to check; ``viewpoints``)."""
    viewpoint: dict[int, bool] = {}

    def seen(k: int) -> bool:
        if k not in viewpoint:
            viewpoint[k] = _viewpoint(features[k].points, centres[k], voxel)
        return viewpoint[k]

    out = np.full(len(ij), np.nan)
    for e, (a, b) in enumerate(np.asarray(ij, dtype=np.int64).reshape(-1, 2)):
        if seen(a) and seen(b):
            out[e] = free_space_conflict(features[a].points, features[b].points, T[e], voxel)
    return out


def placement_conflicts(
    points: Sequence[np.ndarray],
    poses: np.ndarray,
    checked: np.ndarray,
    voxel: float,
    turns: Callable[[int], np.ndarray] | None = None,
) -> np.ndarray:
    """(N, N) symmetric bool: pairs of ``checked`` scans that the poses (N, 4, 4; ``points[k]`` in scan k's frame) place
    so that one's points lie in the other's free space (``free_space_conflict`` above ``CONFLICT``, judged on at least
    ``MIN_IN_VIEW`` points in view), whether or not they were ever registered. ``turns(a)``: (N,) the error, in
    degrees, the placement of scan a and each scan may carry (``verify.placement_turns``; None: none); a point counts
    only when in front by more than the margin plus what that turn about either scan's viewpoint moves it
    (2 sin(turn / 2) of the larger of its ranges from the two). Each scan is tested against the ``MAX_PARTNERS`` scans
    nearest to it (box centres) among those whose boxes meet its own; each scan's range image is built once."""
    n = len(poses)
    index = np.flatnonzero(checked)
    boxes = np.zeros((len(index), 2, 3))
    for x, k in enumerate(index):  # one scan at a time: no pass holds every scan's points
        world = points[k] @ poses[k][:3, :3].T + poses[k][:3, 3]
        boxes[x] = world.min(axis=0), world.max(axis=0)
    lo, hi = boxes[:, 0], boxes[:, 1]
    meet = np.all((lo[:, None] <= hi[None]) & (lo[None] <= hi[:, None]), axis=2)
    np.fill_diagonal(meet, False)
    centre = boxes.mean(axis=1)
    clash = np.zeros((n, n), dtype=bool)
    for x, a in enumerate(index):
        image = range_image(points[a])
        near = np.flatnonzero(meet[x])
        near = near[np.argsort(np.linalg.norm(centre[near] - centre[x], axis=1), kind="stable")[:MAX_PARTNERS]]
        row = None if turns is None or not len(near) else turns(int(a))
        for b in index[near]:
            T_ab = np.linalg.solve(poses[a], poses[b])
            P = points[b]  # read once: a stored scan's points may come from disk
            moved = P @ T_ab[:3, :3].T + T_ab[:3, 3]
            turn = None if row is None else (row[b], np.linalg.norm(P, axis=1))
            clash[a, b] = in_front_of(image, moved, voxel, min_seen=MIN_IN_VIEW, turn=turn) > CONFLICT
    return clash | clash.T


def contradicted_scans(
    clash: np.ndarray, parts: np.ndarray | None = None, held: np.ndarray | None = None
) -> np.ndarray:
    """(N,) bool: the scans to blame for the conflicts ``clash`` ((N, N) symmetric, ``placement_conflicts``):
    repeatedly the scan in conflict with the most others not blamed yet, while that is at least
    ``MIN_CONFLICTS``. A scan placed wrong cuts through the free space of every scan around it (a 50-scan room: six
    misplaced scans in conflict with 14-31 scans each, the right ones only with those six); a single conflicting
    pair (a depth edge, a handful of points in view) blames no one. Of scans in as many conflicts, the one the
    registrations hold least (``held``: (N,) e.g. the summed w⁰ of its verified registrations; None: no tie is
    broken but by index): a conflict says one of two placements is wrong, and the listing order of the scans must
    not choose which. ``parts``: (N,) labels of rigid parts (None: one part); only conflicts within a part blame. A
    conflict between two parts says their relative placement is wrong, which is a join the parts already leave
    unverified, not which scans are: where a group placed wrong outnumbers the right scans that see it (a corridor
    placed 177° off, 14 of its scans in view of 6 right ones), the most conflicts are the right scans'."""
    left = clash.copy() if parts is None else clash & (parts[:, None] == parts[None])
    held = np.zeros(len(clash)) if held is None else held
    blamed = np.zeros(len(clash), dtype=bool)
    while True:
        degree = left.sum(axis=1)
        k = int(np.lexsort((held, -degree))[0])
        if degree[k] < MIN_CONFLICTS:
            return blamed
        blamed[k] = True
        left[k], left[:, k] = False, False


def viewpoint_conflicts(
    features: Stored,
    poses: np.ndarray,
    placed: np.ndarray,
    voxel: float,
    centres: np.ndarray,
    turns: Callable[[int], np.ndarray] | None = None,
) -> np.ndarray:
    """(N, N) bool: ``placement_conflicts`` under ``poses`` (scan k's feature grid in its centred frame to the
    world) among the ``placed`` scans that can say where there is nothing (``viewpoints``), allowing ``turns``."""
    points = Attribute(features, "points")
    return placement_conflicts(points, poses, placed & viewpoints(points, voxel, centres), voxel, turns)
