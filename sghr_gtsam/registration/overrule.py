"""Groups of scans placed where their own free space says they cannot be, and the registrations that put them there.

Synchronization weighs registrations; look-alike places (repeated desks, symmetric rooms) give wrong ones that agree
with each other and outweigh the right ones. It cannot tell them apart, but the placed scans can: a scan seen from
one place says where there is nothing, and a group placed on a look-alike cuts through the free space of the scans
around it. So each group that synchronization's kept edges hold together (``sync.disputes.linkage_groups``) is
tried at the move its dropped registrations agree on, and when that move leaves far fewer of its scans in conflict
with the other scans (``CONFLICT``, registered or not), the kept registrations that hold the group where it is are
overruled: synchronization runs again without them. Fewer conflicts alone are no evidence where fewer scan pairs are
judged (a place that few scans see): the conflict rate must fall by more than the pairs' binomial noise explains
(``_clearer``). A group that one kept registration holds is tried at the move
of each family of its dropped registrations, the cleanest taken; the families whose move the free space rules out
are overruled with the held edge, or the next synchronization would hang the group on the heaviest of them.
Repeated furniture (a row of identical desks) holds a group of fused RGB-D fragments metres off in conflict with
more than half the scan pairs judged; at the move its dropped registrations propose, with a quarter of them
(docs/benchmarks.md, free space).

Fused RGB-D fragments are seen from their first camera but fused over many: their free space is noisier than one
range image's, so the range image here is coarser (``COARSE_BIN_DEG``, ``COARSE_MARGIN_VOXELS``) than the per-pair
check's
(``visibility``), and only a clear majority of conflicts decides (``RATIO``, ``MIN_GAIN``).

Identical rooms give no conflict at either placement: nothing in the scans says which placement is right, and such
a group is reported apart (``look_alikes``, read by ``verify``) rather than trusted where it is.

The same coarse range images judge single registrations that the per-pair check cannot (fused fragments), once the
first synchronization's loop-checked registrations vouch for the scans' frames (``Viewpoints.vouch``): a frame whose
origin is no viewpoint (an object's centre) reads right registrations as conflicts."""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri  # norm.isf(q) is -ndtri(q); scipy.stats costs ~0.5 s to import

from sghr_gtsam.registration.visibility import (
    CONFLICT,
    MAX_PARTNERS,
    MIN_IN_VIEW,
    range_image,
    seen_from_origin,
    seen_in_front_of,
)
from sghr_gtsam.se3 import transform_points
from sghr_gtsam.store import Attribute, Stored
from sghr_gtsam.sync.bridges import bridge_edges
from sghr_gtsam.sync.consensus import NOISE_QUANTILE, translation_tolerance
from sghr_gtsam.sync.disputes import agreeing_edges, elsewhere, linkage_groups
from sghr_gtsam.types import PoseGraph, SyncResult

COARSE_BIN_DEG = 3.0
"""Angular cells of the range image (degrees). Fused fragments' free space is blurred by their many cameras: on
generated fragments at their true poses, 3° and 6 voxels keep 99 % of the pairs' fractions in front below 0.11 (0.3 %
above ``CONFLICT``) where 1° and 3 voxels (the per-pair check's) reach 0.34 (14 % above); turned 90° or 180°, 87 %
read above it (``benchmarks/bench_free_space.py --viewpoints``)."""
COARSE_MARGIN_VOXELS = 6.0
"""A point is in front of a surface when nearer along the ray by more than this many voxels."""
RATIO = 0.5
"""A move overrules a placement when it leaves at most this fraction of the group's conflicts."""
MIN_GAIN = 10
"""... and at least this many conflicting scan pairs fewer (a pair is one scan of the group and one outside)."""
SUPPORT = 0.25
"""Moves whose agreeing dropped registrations weigh (``w⁰``) less than this fraction of the kept ones leaving the
group are not tried: a stray registration is no alternative."""
MAX_GROUP = 50
"""Groups of more scans are not tried: a folded building's halves would cost |group| x ``MAX_PARTNERS`` tests for
every group the linkage forms on the way (a generated 500-scan building: 152 s against 26 s without the stage)."""
SAMPLE = 2000
"""Points of a scan, about, whose fraction in another's free space is measured (every n-th point of its grid): a
fraction's standard error stays below 0.5 / √2000 ≈ 0.011, a tenth of ``CONFLICT``."""
MIN_LOOK_ALIKE = 3
"""Dropped registrations that must agree on another placement of a group before ``look_alikes`` calls it one where
the free space cannot tell (where it can, two agreeing ones compete by weight: ``verify``): structured look-alikes
come backed by 2-4 (benchmarks/bench_robustness.py, structured outliers), a lone wrong registration by one."""
MIN_LOOPED = 20
"""Loop-checked registrations a scene must have judged before its scans' frames count as seen from their sensors
(``Viewpoints.vouch``): one conflict among them is then at most 5 %."""
MAX_FALSE_ALARMS = 0.05
"""... and the largest fraction of them in conflict: right pairs of generated fragments read 0.3 %
(``benchmarks/bench_free_space.py --viewpoints``); a frame whose origin is no viewpoint reads right registrations
as conflicts by the quarter (an object scan in its object's frame: 28 %, docs/benchmarks.md, free space)."""
CONE_DEG = 80.0
"""A scan takes part when its points lie within this angle of their mean direction from its origin (a camera's or
a scanner's view; the 99th percentile), or it is seen from its origin all around (``visibility.seen_from_origin``)."""


class Viewpoints:
    """What the free space of the scans that take part needs, read once a run (the poses change, the scans do not):
    per scan k its range image, a sample of its points (``SAMPLE``) and the corners of its box, in its own frame.
    A scan takes part when seen from its origin (``_takes_part``) and not centred by the pipeline (``centres``
    (N, 3), ``local_frame.centres``: a centred scan's input-frame origin lies far away and is no viewpoint)."""

    def __init__(self, features: Stored, voxel: float, centres: np.ndarray) -> None:
        self.voxel = voxel
        self.images: dict[int, np.ndarray] = {}
        self.samples: dict[int, np.ndarray] = {}
        self.corners: dict[int, np.ndarray] = {}
        self._judged: dict[tuple[int, int, bytes], float] = {}
        self._under: np.ndarray | None = None
        self.vouched = False  # ``vouch``'s answer, once it has run
        points = Attribute(features, "points")
        for k in range(len(points)):
            if np.any(centres[k]):
                continue
            P = points[k]  # one scan at a time
            if _takes_part(P, voxel):
                self.images[k] = range_image(P, COARSE_BIN_DEG)
                self.samples[k] = P[:: max(1, len(P) // SAMPLE)]
                lo, hi = P.min(axis=0), P.max(axis=0)
                self.corners[k] = np.array(
                    [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
                )

    def reordered(self, order: np.ndarray) -> Viewpoints:
        """The same viewpoints with scan ``order[k]`` as scan k (the pairs judged so far are judged again)."""
        out = copy.copy(self)
        new = {int(old): k for k, old in enumerate(order)}
        out.images, out.samples, out.corners = (
            {new[k]: v for k, v in d.items()} for d in (self.images, self.samples, self.corners)
        )
        out._judged, out._under = {}, None
        return out

    def box(self, k: int, T: np.ndarray) -> np.ndarray:
        """(2, 3) lower and upper corner of a box that holds scan k under pose ``T``."""
        world = transform_points(T, self.corners[k])
        return np.stack([world.min(axis=0), world.max(axis=0)])

    def judged(self, poses: np.ndarray) -> dict[tuple[int, int, bytes], float]:
        """The ``conflict`` of each scan pair judged so far under ``poses``, keyed by the two scans and the move of
        the first one's group: kept while the poses stay the same (``look_alikes`` after the overrule's last pass
        on the same model judges no pair again), started afresh when they change."""
        if self._under is None or not np.array_equal(self._under, poses):
            self._under, self._judged = poses.copy(), {}
        return self._judged

    def conflict(self, a: int, b: int, T_a: np.ndarray, T_b: np.ndarray) -> float:
        """1 when either scan puts more than ``CONFLICT`` of its points (``SAMPLE`` of them) in the other's free
        space, judged on at least ``MIN_IN_VIEW`` points in view; 0 when neither does; NaN when neither is judged."""
        out = float("nan")
        for fraction in self._fractions(a, b, lambda: np.linalg.solve(T_a, T_b), lambda: np.linalg.solve(T_b, T_a)):
            if fraction > CONFLICT:  # the second direction is not needed
                return 1.0
            out = 0.0
        return out

    def fraction(self, a: int, b: int, T_ab: np.ndarray) -> float:
        """The larger fraction of either scan's points (``SAMPLE``) that the registration ``T_ab`` (scan b's frame
        to scan a's) puts in the other's free space, of the directions judged on at least ``MIN_IN_VIEW`` points in
        view; NaN when neither is, or a scan does not take part."""
        if a not in self.images or b not in self.images:
            return float("nan")
        return max(self._fractions(a, b, lambda: T_ab, lambda: np.linalg.inv(T_ab)), default=float("nan"))

    def _fractions(
        self, a: int, b: int, T_ab: Callable[[], np.ndarray], T_ba: Callable[[], np.ndarray]
    ) -> Iterator[float]:
        """The fraction of scan b's points in scan a's free space, then of a's in b's, each when judged on at least
        ``MIN_IN_VIEW`` points in view; the moves are made only when asked for."""
        for x, y, T_xy in ((a, b, T_ab), (b, a, T_ba)):
            seen, fraction = seen_in_front_of(
                self.images[x],
                transform_points(T_xy(), self.samples[y]),
                self.voxel,
                COARSE_MARGIN_VOXELS,
                COARSE_BIN_DEG,
            )
            if seen >= MIN_IN_VIEW:
                yield fraction

    def vouch(self, graph: PoseGraph, result: SyncResult) -> bool:
        """Whether the scene's frames show themselves seen from their sensors, also kept as ``vouched``: then the
        single registrations between scans that take part may be judged here (``EdgeSet.check_free_space``). The
        edges that ``result`` kept and that are no bridges of the kept graph are each checked by a loop; judged at
        their registrations (``fraction``), at least ``MIN_LOOPED`` of them, at most ``MAX_FALSE_ALARMS`` of them
        may read as conflicts. Where a frame's origin is no viewpoint, right registrations read as conflicts: the
        scans of an object turned on a table are in the object's frame (origin inside it), 7 of its 25 loop-checked
        edges after
        the first synchronization, all right; on fused RGB-D fragments, seen from their first camera, 9 of 802, all
        wrong (docs/benchmarks.md, free space)."""
        kept = result.weights > 0
        looped = np.flatnonzero(kept & ~bridge_edges(graph.n, graph.i, graph.j, kept))
        fractions = np.array([self.fraction(int(graph.i[e]), int(graph.j[e]), graph.T[e]) for e in looped])
        judged = fractions[np.isfinite(fractions)]
        self.vouched = bool(len(judged) >= MIN_LOOPED and np.sum(judged > CONFLICT) <= MAX_FALSE_ALARMS * len(judged))
        return self.vouched


def _takes_part(P: np.ndarray, voxel: float) -> bool:
    """Whether scan points ``P`` look seen from their origin: within ``CONE_DEG`` of their mean direction from it
    (a camera's or a scanner's view), or all around it (``visibility.seen_from_origin``)."""
    u = P / np.maximum(np.linalg.norm(P, axis=1, keepdims=True), 1e-300)
    mean = u.mean(axis=0)
    if np.linalg.norm(mean) > 1e-9:
        angle = np.degrees(np.arccos(np.clip(u @ (mean / np.linalg.norm(mean)), -1.0, 1.0)))
        if np.percentile(angle, 99) <= CONE_DEG:
            return True
    return seen_from_origin(P, voxel)


@dataclass
class _Trial:
    """One group of scans (``linkage_groups``) tried at the move its agreeing dropped registrations propose (for a
    group one kept edge holds, the move of the family of them that leaves the fewest conflicts)."""

    group: np.ndarray  # (N,) bool
    holding: np.ndarray  # (E,) bool: the kept edges leaving it, and the dropped ones ruled out with them
    agreeing: int  # dropped registrations agreeing on the move
    support: float  # their w⁰ over the holding edges'
    before: int  # scan pairs in conflict (one scan of the group, one outside) where it is
    after: int  # ... and at the move (counted up to ``before`` + 1)
    seen_before: int  # scan pairs judged (boxes meet, ``MIN_IN_VIEW`` points in view) where it is
    seen_after: int  # ... and at the move
    move: np.ndarray  # (4, 4): the move tried, left-multiplying the group's poses


def _trials(views: Viewpoints, graph: PoseGraph, result: SyncResult, alike: bool = False) -> list[_Trial]:
    """The groups worth a move: for ``overruled_edges``, those with ``SUPPORT`` and ``MIN_GAIN`` conflicts to
    remove; with ``alike`` (for ``look_alikes``, once a run: a folded building's groups cost up to ``MAX_GROUP`` x
    ``MAX_PARTNERS`` tests each) also those with ``MIN_LOOK_ALIKE`` registrations for the move."""
    main = result.component == 0
    poses = result.poses
    take = np.array([k for k in sorted(views.images) if main[k]], dtype=np.int64)
    boxes = np.array([views.box(k, poses[k]) for k in take]).reshape(-1, 2, 3)
    lo, hi = boxes[:, 0], boxes[:, 1]
    judged = views.judged(poses)  # nested groups share their scans, pairs and often their move

    def partners(box: np.ndarray, outside: np.ndarray) -> np.ndarray:
        """The scans of ``take[outside]`` whose boxes meet ``box``, the ``visibility.MAX_PARTNERS`` nearest."""
        near = np.flatnonzero(outside & np.all(box[0] <= hi, axis=1) & np.all(lo <= box[1], axis=1))
        order = np.argsort(np.linalg.norm((lo[near] + hi[near]) / 2 - box.mean(axis=0), axis=1), kind="stable")
        return take[near[order[:MAX_PARTNERS]]]

    def conflicts(group: np.ndarray, move: np.ndarray, most: float = np.inf) -> tuple[int, int]:
        """Conflicting pairs of one scan of ``group`` (moved by ``move``) and one outside it, and pairs judged;
        counting stops above ``most`` (no move with more conflicts than the group has now is taken)."""
        outside = ~group[take]
        count, seen = 0, 0
        for a in take[group[take]]:
            for b in partners(views.box(a, move @ poses[a]), outside):
                key = (int(a), int(b), move.tobytes())
                if key not in judged:
                    judged[key] = views.conflict(a, b, move @ poses[a], poses[b])
                if np.isfinite(judged[key]):
                    count, seen = count + int(judged[key]), seen + 1
                if count > most:
                    return count, seen
        return count, seen

    kept = result.weights > 0
    i, j, w = graph.i, graph.j, graph.weight
    inside = (w > 0) & main[i] & main[j]
    tolerance = translation_tolerance(graph)
    trials = []
    for group in linkage_groups(graph, kept, main):
        if group.sum() > MAX_GROUP:
            continue
        leaving = inside & (group[i] != group[j])
        held = w[leaving & kept].sum()
        dropped = elsewhere(graph, poses, group, np.flatnonzero(leaving & ~kept), tolerance)
        if not len(dropped):
            continue
        agreeing, move = agreeing_edges(graph, poses, group, dropped, tolerance)
        support = w[agreeing].sum() / held if held > 0 else np.inf
        many = alike and len(agreeing) >= MIN_LOOK_ALIKE
        if support < SUPPORT and not many:
            continue
        before, seen_before = conflicts(group, np.eye(4))
        if before < MIN_GAIN and not many:
            continue
        after, seen_after = conflicts(group, move, most=before)
        holding = leaving & kept
        if not alike and holding.sum() == 1:
            # Hung on one kept edge, the group would go to its heaviest dropped family once that edge is overruled,
            # right or not (measured on real fused fragments): every family with SUPPORT is tried, the cleanest move is
            # kept, and the families the free space rules out as firmly as the group's place go with the edge.
            tried, others = [(agreeing, after)], np.setdiff1d(dropped, agreeing)
            while len(others):
                family, family_move = agreeing_edges(graph, poses, group, others, tolerance)
                others = np.setdiff1d(others, family)
                weight = w[family].sum()
                if weight < SUPPORT * held:
                    continue
                count, seen = conflicts(group, family_move, most=before)
                tried.append((family, count))
                if count < after:
                    agreeing, move, support, after, seen_after = family, family_move, weight / held, count, seen
            for family, count in tried:
                holding[family] |= count > RATIO * before
        trials.append(_Trial(group, holding, len(agreeing), support, before, after, seen_before, seen_after, move))
    return trials


def overruled_edges(views: Viewpoints, graph: PoseGraph, result: SyncResult) -> np.ndarray:
    """(E,) bool: the kept edges of ``graph`` that hold a group of scans where the scans' free space (``views``)
    rules it out, against the move that the group's dropped registrations agree on; for a group one kept edge holds,
    also the dropped registrations whose move it rules out as firmly (module docstring).
    ``result.poses`` in the scans' centred frames, as ``views``. Groups of more than ``MAX_GROUP`` scans are not
    tried. Of groups that share scans or holding edges, the clearest case is taken (fewest conflicts left, then most
    removed)."""
    return _overruled(_trials(views, graph, result), graph)


def _overruled(trials: list[_Trial], graph: PoseGraph) -> np.ndarray:
    """``overruled_edges`` of the groups tried."""
    found = [
        t
        for t in trials
        if t.support >= SUPPORT
        and t.before >= MIN_GAIN
        and t.after <= RATIO * t.before
        and t.before - t.after >= MIN_GAIN
        and _clearer(t)
    ]
    # A conflict is explained once: a group's neighbours, tried as a group, see the same edges from the other side.
    out = np.zeros(graph.num_edges, dtype=bool)
    taken = np.zeros(graph.n, dtype=bool)
    for t in sorted(found, key=lambda t: (t.after / t.before, t.after - t.before)):
        if not np.any(taken & t.group) and not np.any(out & t.holding):
            taken |= t.group
            out |= t.holding
    return out


def _clearer(t: _Trial) -> bool:
    """Whether the group's scan pairs conflict at a lower rate at the move than where it is, beyond the binomial noise
    of the pairs judged: a one-sided two-proportion z-test at synchronization's ``NOISE_QUANTILE``. A move to a place
    that fewer scans see leaves fewer conflicts at the same rate: on fused 3DMatch fragments, where 30 % of the pairs
    a group's scans make read as conflicts wherever it is, moves that halved the count scored z ≤ 2.2, moves off
    repeated furniture z ≥ 5.3 (tests/test_overrule.py holds one of each)."""
    if t.seen_before == 0 or t.seen_after == 0:
        return False
    rate = (t.before + t.after) / (t.seen_before + t.seen_after)
    noise = np.sqrt(rate * (1.0 - rate) * (1.0 / t.seen_before + 1.0 / t.seen_after))
    gap = t.before / t.seen_before - t.after / t.seen_after
    return bool(noise > 0 and gap >= -ndtri(1.0 - NOISE_QUANTILE) * noise)


def look_alikes(views: Viewpoints, graph: PoseGraph, result: SyncResult) -> list[tuple[np.ndarray, np.ndarray]]:
    """The groups ((N,) bool) that ``MIN_LOOK_ALIKE`` or more dropped registrations agree on placing elsewhere, with
    that move (4, 4, left-multiplying their poses), where the scans' free space (``views``) finds no more conflicts
    than where it is, judged on some scan pairs and on at least half as many at the move (a place nobody saw is no
    evidence): two placements that the scans cannot tell apart (identical rooms), of which synchronization took the
    one with more weight. None while ``overruled_edges`` has edges to overrule: that model is not the last."""
    if overruled_edges(views, graph, result).any():  # its conflicts are kept for the trials below (``judged``)
        return []
    return [
        (t.group, t.move)
        for t in _trials(views, graph, result, alike=True)
        if t.agreeing >= MIN_LOOK_ALIKE and t.after <= t.before and 2 * t.seen_after >= t.seen_before > 0
    ]
