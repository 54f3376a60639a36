"""Verification: which placed scans the evidence holds, as rigid parts with one status per scan.

A pose is *verified* when registrations that can be checked against each other hold it. Three tests, each a
standard one:

1. **Loop-closure error against its noise.** Every kept registration ``T_ij`` is compared with the final poses,
   by the consistency test synchronization itself uses (``sync.consensus.consistent_edges``): it passes when
   ``T_ij⁻¹ T_i⁻¹ T_j`` lies within a good registration's error budget (``consensus.MAX_DEG`` and the translation
   tolerance) or within its own noise (``χ² = rᵀ Ω r ≤ χ²₆(0.999)``, ``r`` the residual in gtsam's order, ``Ω`` the
   edge's information). Real registrations carry systematic errors that point noise does not see (their
   information is overconfident by the factor ``σ̂₀²`` below), so a χ² test alone would break right loops.
2. **Cycle consistency.** The passing registrations form the verified graph. Its biconnected components of three
   or more scans are the *rigid parts*: any two scans of one are joined by two paths that share no scan, so every
   pose in it is checked by a loop of registrations that closes within their noise. What joins two parts is a
   *bridge* (one registration no loop checks) or an *articulation point* (one scan, whose registrations can all be
   wrong the same way, as a symmetric room's can): such a join is reported and not trusted. Scans in no part of
   three hang on one registration or one scan.
3. **Competing placements.** Registrations that synchronization dropped may agree among themselves on another
   placement of a scan or of a group that kept registrations hold together (the linkage groups of
   ``sync.disputes``). When those that agree on one move of it outweigh (``w⁰``) the kept registrations that hold
   it there, one or several, and moving the scans at their far ends instead would cost as much, the evidence
   against the join passes the same test as the evidence for it: the join is disputed and the group is a part of
   its own. (Asking for two or more let a scan turned 180° stand verified on three light look-alike registrations
   whose loops close, against the one right registration that outweighed them: a generated 12-scan building.) A
   dropped registration disputes one of its two ends, not both: one that moved a disputed group does not count
   against another group apart from it (a right scan whose one dropped registration reaches a wrong one). So
   is a group that several dropped registrations place elsewhere where the free space cannot tell the two
   placements apart (identical rooms: ``registration.overrule.look_alikes``), whatever the weights.
4. **Free space.** Where scans are seen from their frame's origin (a laser station, a depth frame), a placement that
   puts one scan's surfaces where another saw empty space, farther than the error the placement of the two may carry
   (``placement_turns``: the run's registration error grown as a random walk along the path that joins them), is
   contradicted (``registration.visibility.placement_conflicts``). Within a part, such conflicts say a registration on
   the path between the two scans is wrong. The join is found as the minimum cut of the part's verified graph between
   the scan in most conflicts and the scans it conflicts with; when the pairs of scans in conflict across that cut
   outnumber the registrations that hold it, the free space contradicts the join, its registrations fail, and the two
   sides are parts of their own. (Look-alike rooms: a generated 100-scan building's two wings held 11 m apart by two
   light registrations that close loops, against 288 conflicting pairs across them.) A scan left in conflict with others
   of its part that no cut separates is blamed as a scan (``registration.visibility.contradicted_scans``); a conflict
   between two parts is about their join, which is already unverified.

A scan's pose may also be held but loose: the registrations leave a direction (a plane, a corridor, a cylinder)
that only the bounds of their overlap fix (``registration.information.free_directions``). Its covariance comes
from the passing registrations' measured information scaled by the a posteriori variance factor ``σ̂₀²``
(``sync.consensus.shown_variance_factor``: robust, never below 1), plus the bounds as they are. Its spread is set
by those bounds, not by measurements, when it shrinks by more than ``STIFFEN^¼`` (the geometric middle of no change
and ``√STIFFEN``) with every bound ``STIFFEN`` times stiffer; such a scan is reported loose with the direction and
σ, and doubted only where σ exceeds ``Verification.max_sigma``. Spreads are taken relative to the scan of the part
that most passing registrations hold, a gauge the registrations choose rather than the order of the scans.

Parts are ordered largest first; part 0 holds the world scan when it is the largest. A part whose join failed is
placed where its best join puts it, and marked so (``Part.join``).
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from itertools import chain

import gtsam
import networkx as nx
import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import shortest_path

from sghr_gtsam.registration.visibility import contradicted_scans
from sghr_gtsam.sync.consensus import (
    MAX_DEG,
    consistent_edges,
    edge_residuals,
    mahalanobis,
    shown_variance_factor,
    translation_tolerance,
)
from sghr_gtsam.sync.disputes import agreeing_edges, elsewhere, linkage_groups, move_size
from sghr_gtsam.sync.rotation import connected_components
from sghr_gtsam.types import PoseGraph

RESIDUAL_QUANTILE = 0.9
"""The error a registration of the run carries: the level this share of the kept ones stay within at the final poses
(``placement_turns``)."""
STIFFEN = 100.0
"""How much stiffer the free directions' bounds are made to tell a spread they set from a measured one: one they
set shrinks by √STIFFEN = 10, one the measurements set does not move."""
REASONS = {
    "single registration": "held by one registration, or through one scan, that no loop checks",
    "loop error": "its registrations do not close their loops within their noise",
    "competing placement": "dropped registrations agree on another placement of it and outweigh its own",
    "free space": "placed where other scans saw empty space, or seeing empty space where they are",
    "loose": "its registrations leave a direction free beyond the tolerance (see report.json loose)",
}
"""Why a placed scan is doubtful: one of these, the first that applies in this order."""
STATUSES = ("verified", "doubtful", "unplaced")


@dataclass(frozen=True)
class Verification:
    """Parameters of the verification. ``max_sigma``: the largest σ (scene units) of a loose scan's points along
    its free direction that still counts as placed; None: the translation tolerance of the consistency test
    (``sync.consensus.translation_tolerance``), the error budget within which two registrations count as agreeing:
    a pose looser than that cannot be told from another placement by the registrations themselves."""

    max_sigma: float | None = None


@dataclass
class Join:
    """How a part hangs on another: the kept registrations between them (scan names) and why they do not verify
    the join; where dropped registrations agree on another placement of the part, how far that lies
    (``[degrees, distance]``: the turn, and how far the part's centre moves)."""

    to: int
    edges: list[tuple[str, str]]
    why: str
    elsewhere: list[float] | None = None


ALIKE = "dropped registrations agree on another placement of it that the free space cannot rule out"
OUTWEIGHED = "dropped registrations agree on another placement of it and outweigh these"
SEEN_THROUGH = "scans across it see each other's surfaces in their free space, more pairs than it has registrations"


@dataclass
class Dispute:
    """A group of scans (``group``: (N,) bool) whose place dropped registrations dispute, how far their placement
    lies (``Join.elsewhere``) and why the join fails (``ALIKE``, ``OUTWEIGHED``)."""

    group: np.ndarray
    elsewhere: list[float]
    why: str


@dataclass
class Part:
    id: int
    scans: list[str]
    join: Join | None = None
    """None for part 0 (the world) and for a part that no registration joins to the rest."""

    @property
    def frame(self) -> str:
        return "world" if self.id == 0 else "joined"


@dataclass
class Verdict:
    """The verification's answer: parts (largest first), and per scan name a status (``STATUSES``), the reason
    of each doubt (``REASONS``) and, for a loose pose, its free direction (unit, world frame) and σ."""

    parts: list[Part]
    status: dict[str, str]
    doubts: dict[str, str]
    loose: dict[str, dict[str, object]] = field(default_factory=dict)
    """Scans whose spread the free directions' bounds set: σ (scene units) and the axis it lies along."""
    variance_factor: float = float("nan")

    def part_of(self) -> dict[str, int]:
        return {name: p.id for p in self.parts for name in p.scans}

    def trusted(self) -> list[str]:
        """The verified scans of the world part (part 0): the model a user can take as it is."""
        return [name for name in (self.parts[0].scans if self.parts else []) if self.status[name] == "verified"]

    def as_dict(self) -> dict:
        return {
            "parts": [
                {"id": p.id, "scans": p.scans, "frame": p.frame, "join": None if p.join is None else asdict(p.join)}
                for p in self.parts
            ],
            "status": self.status,
            "doubts": self.doubts,
            "loose": self.loose,
            "robust_variance_factor": None if not np.isfinite(self.variance_factor) else self.variance_factor,
        }

    @classmethod
    def from_dict(cls, data: dict) -> Verdict:
        """The verdict ``as_dict`` wrote (report.json's fields)."""
        parts = [
            Part(
                int(p["id"]),
                list(p["scans"]),
                None
                if p["join"] is None
                else Join(
                    int(p["join"]["to"]),
                    [tuple(e) for e in p["join"]["edges"]],
                    str(p["join"]["why"]),
                    p["join"].get("elsewhere"),
                ),
            )
            for p in data["parts"]
        ]
        factor = data.get("robust_variance_factor")
        return cls(
            parts,
            dict(data["status"]),
            dict(data["doubts"]),
            dict(data.get("loose") or {}),
            float("nan") if factor is None else float(factor),
        )

    def summary(self, max_lines: int = 12) -> list[str]:
        """One line per part of two or more scans, then the single scans in one line: at most ``max_lines`` + 2."""
        lines = []
        many = [p for p in self.parts if len(p.scans) > 1]
        for p in many[:max_lines]:
            doubtful = [s for s in p.scans if self.status[s] == "doubtful"]
            where = (
                "the world"
                if p.join is None and p.id == 0
                else (f"joined to part {p.join.to} by a join that failed: {p.join.why}" if p.join else "not joined")
            )
            if p.join is not None and p.join.elsewhere is not None:
                where += f" ({p.join.elsewhere[0]:.1f}° / {p.join.elsewhere[1]:.3g} away)"
            said = f"part {p.id}: {len(p.scans)} scans, {len(p.scans) - len(doubtful)} verified; {where}"
            if doubtful:
                said += "; doubtful: " + _listed(doubtful, self.doubts)
            lines.append(said)
        if len(many) > max_lines:
            lines.append(f"... {len(many) - max_lines} more parts (report.json parts)")
        single = [p.scans[0] for p in self.parts if len(p.scans) == 1]
        if single:
            lines.append(f"{len(single)} scan(s) on their own, doubtful: " + _listed(single, self.doubts))
        unplaced = [s for s, v in self.status.items() if v == "unplaced"]
        if unplaced:
            lines.append(f"{len(unplaced)} scan(s) unplaced: {_names(unplaced)}")
        return lines


def placement_turns(graph: PoseGraph, kept: np.ndarray, poses: np.ndarray) -> Callable[[int], np.ndarray]:
    """``turns(a)``: (N,) the rotation error (degrees) the placement of scan a and each scan may carry, for the
    free-space test (``registration.visibility.placement_conflicts``): registration errors add up along the path that
    joins two scans as a random walk, so the error ``RESIDUAL_QUANTILE`` of the ``kept`` registrations stay within at
    ``poses`` times √(registrations on the shortest path), at most the loop test's budget (``consensus.MAX_DEG``); 0
    between scans no kept registrations join. One scan's row at a time (one breadth-first search): the test asks for
    a few partners of each scan, and an N × N matrix would not stay bounded (0.8 GB at 10,000 scans)."""
    n = len(poses)
    if not kept.any():
        return lambda a: np.zeros(n)
    _, degrees, _ = edge_residuals(graph, poses)
    step = float(np.quantile(degrees[kept], RESIDUAL_QUANTILE))
    adjacency = csr_matrix((np.ones(int(kept.sum())), (graph.i[kept], graph.j[kept])), shape=(n, n))

    def turns(a: int) -> np.ndarray:
        hops = shortest_path(adjacency, directed=False, unweighted=True, indices=a)
        return np.where(np.isfinite(hops), np.minimum(step * np.sqrt(hops), MAX_DEG), 0.0)

    return turns


def _names(names: list[str], most: int = 6) -> str:
    return ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")


def _listed(names: list[str], doubts: dict[str, str]) -> str:
    by_reason: dict[str, list[str]] = {}
    for name in names:
        by_reason.setdefault(doubts[name], []).append(name)
    return "; ".join(f"{reason}: {_names(found)}" for reason, found in by_reason.items())


def rigid_parts(
    n: int, i: np.ndarray, j: np.ndarray, verified: np.ndarray, placed: np.ndarray, weight: np.ndarray | None = None
) -> np.ndarray:
    """(N,) part label of each scan (−1 unplaced): the biconnected components of three or more scans of the
    ``verified`` edges, largest first (ties: the one with the smallest scan); an articulation point goes to the
    component whose registrations hold it most (``weight``: (E,) w⁰; None: one each), then the largest (so a
    triangle hung on one can leave a part of two): two blocks that share a scan are placed against each other by
    that scan alone, and it belongs where more of the evidence for its own pose lies; every other placed scan is a
    part of its own."""
    weight = np.ones(len(i)) if weight is None else weight
    G = _summed_graph(i[verified], j[verified], weight[verified], "w")
    blocks = [c for c in map(list, nx.biconnected_component_edges(G)) if len({k for e in c for k in e}) >= 3]
    members = [sorted({k for e in c for k in e}) for c in blocks]
    order = sorted(range(len(blocks)), key=lambda x: (-len(members[x]), members[x][0]))
    held: defaultdict[int, defaultdict[int, float]] = defaultdict(lambda: defaultdict(float))
    for x, block in enumerate(blocks):
        for a, b in block:
            held[a][x] += G[a][b]["w"]
            held[b][x] += G[a][b]["w"]
    rank_of = {x: r for r, x in enumerate(order)}
    label = np.full(n, -1)
    for k, by_block in held.items():
        label[k] = min(by_block, key=lambda x: (-by_block[x], rank_of[x]))
    alone = np.flatnonzero(placed & (label < 0))
    label[alone] = len(blocks) + np.arange(len(alone))
    sizes = np.bincount(label[label >= 0], minlength=label.max() + 1)
    order = sorted(range(len(sizes)), key=lambda x: (-sizes[x], int(np.flatnonzero(label == x)[0])))
    rank = np.empty(len(order), dtype=int)
    rank[order] = np.arange(len(order))
    return np.where(label >= 0, rank[np.maximum(label, 0)], -1)


def _summed_graph(i: np.ndarray, j: np.ndarray, values: np.ndarray, key: str) -> nx.Graph:
    """The graph of edges ``i[e]``–``j[e]``, each pair's ``values`` summed into its attribute ``key`` (parallel
    registrations of one pair add up)."""
    G = nx.Graph()
    for a, b, v in zip(i.tolist(), j.tolist(), values.tolist()):
        G.add_edge(a, b, **{key: G.get_edge_data(a, b, {key: 0.0})[key] + v})
    return G


def _join(
    part: int,
    label: np.ndarray,
    i: np.ndarray,
    j: np.ndarray,
    kept: np.ndarray,
    passed: np.ndarray,
    disputes: Sequence[Dispute],
    seen_through: np.ndarray,
    weight: np.ndarray,
    names: Sequence[str],
) -> Join | None:
    """The kept registrations from ``part`` to other parts and why they do not verify its place (None: none);
    ``disputes``: the groups whose place a competing one disputes (the first that holds a scan of the part says
    why); ``seen_through``: (E,) the registrations of joins the free space contradicts."""
    a, b = label[i], label[j]
    out = kept & ((a == part) != (b == part)) & (a >= 0) & (b >= 0)
    if not out.any():
        return None
    e = np.flatnonzero(out)
    best = e[np.argmax(weight[e])]
    to = int(b[best] if a[best] == part else a[best])
    good = e[passed[e]]
    members = label == part
    dispute = next((d for d in disputes if d.group[members].any()), None)
    if dispute is not None:
        why = dispute.why
    elif seen_through[e].any():
        why = SEEN_THROUGH
    elif len(good) == 0:
        why = "its registrations to the rest do not close their loops within their noise"
    elif len(good) == 1:
        why = "one registration that no loop checks (a bridge)"
    else:
        inside = np.where(a[good] == part, i[good], j[good])
        outside = np.where(a[good] == part, j[good], i[good])
        why = (
            "every registration goes through one scan (an articulation point)"
            if (len(set(inside.tolist())) == 1 or len(set(outside.tolist())) == 1)
            else "registrations that close no loop with the part"
        )
    edges = [(names[i[x]], names[j[x]]) for x in e]
    return Join(to=to, edges=edges, why=why, elsewhere=None if dispute is None else dispute.elsewhere)


def verify(
    names: Sequence[str],
    graph: PoseGraph,
    kept: np.ndarray,
    poses: np.ndarray,
    placed: np.ndarray,
    params: Verification,
    points: Sequence[np.ndarray] | None = None,
    information: np.ndarray | None = None,
    free: np.ndarray | None = None,
    conflicts: np.ndarray | None = None,
    dependent: np.ndarray | None = None,
    look_alike: Sequence[tuple[np.ndarray, np.ndarray]] = (),
) -> Verdict:
    """The parts and statuses of a run (module doc). ``kept``: (E,) the registrations synchronization kept; ``poses``:
    (N, 4, 4) in the frames of ``graph``; ``placed``: (N,) the scans with a pose; ``points[k]``: scan k's points in its
    own frame, for its ``pose_spread`` (None: looseness not judged); ``information``: (E, 6, 6) each edge's information
    with its free directions bounded by the overlap alone (``PairResult.bounded``; default: the graph's) and ``free``
    its part along them (``PairResult.loose``; None: no direction is free); ``conflicts``: (N, N) symmetric bool, the
    pairs of scans the poses place in each other's free space (``registration.visibility.placement_conflicts``; None: no
    free-space test); ``dependent``: (E,) the kept registrations that are no independent evidence for a loop (they
    started from the poses they would check): they count in what holds a group against a competing placement, not in the
    loops that verify it; ``look_alike``: groups ((N,) bool) with the move (4, 4, left-multiplying their poses) that
    dropped registrations agree on, where the free space cannot tell the two placements apart
    (``registration.overrule.look_alikes``): their joins to the rest are disputed."""
    n = len(names)
    kept = kept & placed[graph.i] & placed[graph.j]
    kept_graph = replace(graph, weight=kept.astype(float))
    consistent = consistent_edges(kept_graph, poses)
    passed = consistent.copy()
    alike = [Dispute(g, _distance(poses, g, move), ALIKE) for g, move in look_alike]
    disputes = alike + _disputed(graph, kept, placed, poses)
    contested = np.any([d.group for d in disputes], axis=0) if disputes else np.zeros(n, dtype=bool)
    disputed = np.zeros(graph.num_edges, dtype=bool)
    for d in disputes:
        disputed |= kept & (d.group[graph.i] != d.group[graph.j])
    passed &= ~disputed
    if dependent is not None:
        passed &= ~dependent
    conflicts = np.zeros((n, n), dtype=bool) if conflicts is None else conflicts
    seen_through, label = _seen_through(graph, passed, placed, conflicts)
    passed &= ~seen_through
    factor = 1.0
    if graph.information is not None:  # the a posteriori variance factor of the passing registrations
        factor = shown_variance_factor(mahalanobis(edge_residuals(graph, poses)[0][passed], graph.information[passed]))
    parts = [Part(id=x, scans=[names[k] for k in np.flatnonzero(label == x)]) for x in range(label.max() + 1)]
    for p in parts[1:]:
        p.join = _join(p.id, label, graph.i, graph.j, kept, passed, disputes, seen_through, graph.weight, names)
    sizes = np.bincount(label[label >= 0], minlength=len(parts))
    alone = placed & (label >= 0) & (sizes[np.maximum(label, 0)] == 1)
    contradicted = contradicted_scans(conflicts, label, _held(graph, passed))
    max_sigma = translation_tolerance(kept_graph) if params.max_sigma is None else params.max_sigma
    spreads, stiff, axes = np.full(n, np.nan), np.full(n, np.nan), np.full((n, 3), np.nan)
    information = graph.information if information is None else information
    if points is not None and information is not None and free is not None:
        measured = (information - free) / factor  # the bounds are the overlap's extent, not a noise to rescale
        # Each part with the single scans that hang on it: a pose is judged in its own part, not across a join.
        single = alone[graph.i] | alone[graph.j]
        within = passed & ((label[graph.i] == label[graph.j]) | single)
        held = connected_components(n, graph.i, graph.j, within)
        has_free = np.abs(free).sum(axis=(1, 2)) > 0
        for x in np.unique(held[placed]):
            members = held == x
            if members.sum() >= 2 and (has_free & within & members[graph.i] & members[graph.j]).any():
                _part_spreads(members, graph, within, measured + free, poses, points, spreads, axes)
                _part_spreads(
                    members, graph, within, measured + STIFFEN * free, poses, points, stiff, np.full((n, 3), np.nan)
                )
    bound = placed & (np.nan_to_num(spreads, nan=0.0) > STIFFEN**0.25 * np.nan_to_num(stiff, nan=np.inf))
    loose = bound & (spreads > max_sigma)
    status, doubts, loose_said = {}, {}, {}
    for k, name in enumerate(names):
        if not placed[k]:
            status[name] = "unplaced"
            continue
        reason = (
            _alone_reason(k, graph, kept & ~consistent, passed, contested, seen_through)
            if alone[k]
            else "free space"
            if contradicted[k]
            else "loose"
            if loose[k]
            else None
        )
        status[name] = "verified" if reason is None else "doubtful"
        if reason:
            doubts[name] = reason
        if bound[k]:
            loose_said[name] = {"sigma": float(spreads[k]), "axis": np.round(axes[k], 4).tolist()}
    return Verdict(parts=parts, status=status, doubts=doubts, loose=loose_said, variance_factor=factor)


def _part_spreads(
    members: np.ndarray,
    graph: PoseGraph,
    passed: np.ndarray,
    information: np.ndarray,
    poses: np.ndarray,
    points: Sequence[np.ndarray],
    spreads: np.ndarray,
    axes: np.ndarray,
) -> None:
    """Fill ``spreads`` and ``axes`` (``registration.information.loosest``) of the ``members`` scans from the
    marginal covariances of their passing registrations, relative to the scan most of them hold (a stiff prior; ties
    by the registrations' summed w⁰): the gauge follows the registrations, not the scans' names or order, so a pose
    is not loose or firm by which scan happened to be listed first."""
    from sghr_gtsam.factor_graph import anchor_prior
    from sghr_gtsam.registration.information import loosest

    edges = np.flatnonzero(passed & members[graph.i] & members[graph.j])
    factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    nodes = np.flatnonzero(members)
    degree = np.bincount(np.r_[graph.i[edges], graph.j[edges]], minlength=len(poses))[nodes]
    weight = _held(graph, edges)[nodes]
    anchor = int(nodes[np.lexsort((-weight, -degree))[0]])
    for k in nodes:
        values.insert(int(k), gtsam.Pose3(poses[k]))
    for e in edges:
        factors.add(
            gtsam.BetweenFactorPose3(
                int(graph.i[e]),
                int(graph.j[e]),
                gtsam.Pose3(graph.T[e]),
                gtsam.noiseModel.Gaussian.Information(information[e]),
            )
        )
    factors.add(
        gtsam.PriorFactorPose3(
            anchor, gtsam.Pose3(poses[anchor]), anchor_prior(float(np.abs(information[edges]).max()))
        )
    )
    try:
        marginals = gtsam.Marginals(factors, values)
    except RuntimeError:  # indeterminate: some direction nothing fixes
        spreads[nodes] = np.inf
        return
    covariances = np.full((len(poses), 6, 6), np.nan)
    for k in nodes:
        covariances[k] = marginals.marginalCovariance(int(k))
    spreads[nodes], axes[nodes] = (a[nodes] for a in loosest(covariances, points, nodes))


def _held(graph: PoseGraph, edges: np.ndarray) -> np.ndarray:
    """(N,) the summed w⁰ of the registrations ``edges`` (a mask or indices) at each scan."""
    return np.bincount(
        np.r_[graph.i[edges], graph.j[edges]],
        weights=np.r_[graph.weight[edges], graph.weight[edges]],
        minlength=graph.n,
    )


def _alone_reason(
    k: int,
    graph: PoseGraph,
    failing: np.ndarray,
    passed: np.ndarray,
    contested: np.ndarray,
    seen_through: np.ndarray,
) -> str:
    """Why scan k is in no part of three: a competing placement of it (``contested``: (N,) the scans of the disputed
    groups), a join the free space contradicts (``seen_through``: (E,)), its kept registrations ``failing`` the
    consistency test, or too few that pass."""
    own = (graph.i == k) | (graph.j == k)
    if contested[k]:
        return "competing placement"
    if (own & seen_through).any():
        return "free space"
    if (own & failing).any() and int(np.sum(own & passed)) < 2:
        return "loop error"
    return "single registration"


def _seen_through(
    graph: PoseGraph, passed: np.ndarray, placed: np.ndarray, conflicts: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(E,) the ``passed`` registrations of joins the free space contradicts (module doc, test 4), and the rigid
    parts (``rigid_parts``) of the passed registrations without them. Repeatedly, in
    each rigid part the scan in most conflicts with others of it is cut from them (a minimum cut, one unit a
    registration); the cut is a contradicted join when more pairs of scans conflict across it than it has
    registrations. A scan whose cut does not pass is not tried again until a cut changes the parts."""
    cut = np.zeros(graph.num_edges, dtype=bool)
    tried: set[int] = set()
    while True:
        label = rigid_parts(graph.n, graph.i, graph.j, passed & ~cut, placed, graph.weight)
        inside = conflicts & (label[:, None] == label[None]) & (label[:, None] >= 0)
        count = inside.sum(axis=1)
        for k in np.argsort(-count, kind="stable"):
            if count[k] == 0:
                return cut, label
            if k in tried:
                continue
            part = label == label[k]
            edges, side = _min_cut(graph, passed & ~cut & part[graph.i] & part[graph.j], int(k), inside[k])
            if len(edges) and inside[np.ix_(side, part & ~side)].sum() > len(edges):
                cut[edges] = True
                tried.clear()
                break
            tried.add(int(k))
        else:
            return cut, label


def _min_cut(graph: PoseGraph, edges: np.ndarray, k: int, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The registrations (indices) of a minimum cut of the graph of ``edges`` ((E,) bool; one unit each) between
    scan ``k`` and the ``targets`` ((N,) bool), and (N,) bool the side of ``k``."""
    G = _summed_graph(graph.i[edges], graph.j[edges], np.ones(int(edges.sum())), "capacity")
    G.add_edges_from((int(t), -1) for t in np.flatnonzero(targets))  # no capacity: unbounded
    side = np.zeros(graph.n, dtype=bool)
    if k not in G or not nx.has_path(G, k, -1):
        return np.zeros(0, dtype=int), side
    _, (reached, _) = nx.minimum_cut(G, k, -1)
    side[list(reached)] = True
    return np.flatnonzero(edges & (side[graph.i] != side[graph.j])), side


def _disputed(graph: PoseGraph, kept: np.ndarray, placed: np.ndarray, poses: np.ndarray) -> list[Dispute]:
    """The scans, and linkage groups, held where dropped registrations that agree on another placement of them
    outweigh what holds them (module doc, test 3), in the order they were found. A dropped registration says that
    one of its two ends is misplaced, not both: the groups are taken by the weight of the dropped registrations that
    agree on moving them (then the least held first), and a registration that already moved a disputed group counts
    no more against a group disjoint from it (a right scan whose one dropped registration reaches a wrong one is not
    disputed by it). Of nested disputed groups, the largest only: the same dropped registrations move any of its
    subgroups as well, which says nothing of the registrations inside it."""
    i, j, w = graph.i, graph.j, graph.weight
    inside = (w > 0) & placed[i] & placed[j]
    tolerance = translation_tolerance(graph)
    candidates = []  # (order, group, agreeing, their weight, held, move)
    singles = (np.arange(graph.n) == k for k in np.flatnonzero(placed))
    for group in chain(singles, linkage_groups(graph, kept, placed)):
        leaving = inside & (group[i] != group[j])
        held = w[leaving & kept].sum()
        dropped = elsewhere(graph, poses, group, np.flatnonzero(leaving & ~kept), tolerance)
        if w[dropped].sum() <= held:  # also when none is dropped: the weights are not negative
            continue
        agreeing, move = agreeing_edges(graph, poses, group, dropped, tolerance)
        against = w[agreeing].sum()
        if against > held:
            candidates.append((len(candidates), group, agreeing, against, held, move))
    disputed: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
    for order, group, agreeing, _, held, move in sorted(candidates, key=lambda c: (-c[3], c[4])):
        spent = [a for _, g, a, _ in disputed if not (g & group).any()]
        agreeing = np.setdiff1d(agreeing, np.concatenate(spent)) if spent else agreeing
        if w[agreeing].sum() <= held:
            continue
        accused = np.zeros(graph.n, dtype=bool)
        accused[np.where(group[i[agreeing]], j[agreeing], i[agreeing])] = True
        if w[inside & kept & (accused[i] != accused[j])].sum() >= held:  # else they accuse their far ends
            disputed.append((order, group, agreeing, move))
    return [
        Dispute(g, _distance(poses, g, move), OUTWEIGHED)
        for _, g, _, move in sorted(disputed, key=lambda d: d[0])
        if not any(o.sum() > g.sum() and np.all(o[g]) for _, o, _, _ in disputed)
    ]


def _distance(poses: np.ndarray, group: np.ndarray, move: np.ndarray) -> list[float]:
    """``[degrees, distance]`` of ``move`` (4, 4; left-multiplies the group's poses): its turn, and how far it moves
    the group's centre."""
    turn, shift = move_size(poses, group, move)
    return [round(float(turn), 2), round(float(shift), 4)]


__all__ = [
    "Verification",
    "Verdict",
    "Part",
    "Join",
    "REASONS",
    "STATUSES",
    "verify",
    "rigid_parts",
]
