"""Loop evidence: judge an edge by the loops it closes, and place scans outward from the most consistent core.

Residual reweighting (IRLS, GNC) and the weighted consensus judge an edge by its own weight and by how well
it fits poses that the heavy edges made; a wrong placement of a scan repeated on 2-4 heavy edges (look-alike
scans in a symmetric room) or a majority of random outliers then drags a whole group of scans with it.
Here placements are decided by how many edges agree on them — every agreement of two edges is a loop
through the placed scans — and each edge's vote (``credibility``) is 1 plus at most 1 for its weight:

- **Loop support** (``triangle_support``): how many triangles ``a → b → c → a`` whose composed transform
  ``T_ab T_bc T_ca`` is within the agreement tolerances of the identity (those of ``consensus``: ``MAX_DEG``
  and ``translation_tolerance``) an edge is part of. A random outlier closes no consistent triangle; a
  look-alike edge only those it shares with the other edges of its wrong placement. It picks the seed and
  ranks placements that rest on one edge; ``SyncResult.loop_support`` reports it. (As a vote weight it
  favours tightly knit wrong groups over a scan's scattered right edges: measured, not used.)
- **Growing** (``grow``): seed at the edge with the most loop support, then repeatedly place the unplaced
  scan whose placements, proposed by its edges to placed scans (``T_a T_as``), are least ambiguous: first
  scans where two proposals agree, then single edges on a consistent triangle, then lone edges; within a
  tier, the largest *margin* between the votes of the best placement and of the best one disagreeing with
  it. An ambiguous scan waits until its partners are placed; a wrong placement stays the scan's own — its
  edges to the right scans propose their placements moved by the same wrong transform, which the rest of
  their edges outvote.
- **Group moves** (``replace_groups``): after least squares, the blocks of the consistent edges once the
  bridges are cut (groups held by loops but hung on one edge) move as a whole where their other edges
  agree they belong — the failure growing and IRLS share, which no single-scan move repairs.
- **Moves across a minimum cut** (``cut_moves``): a group held in a wrong place by several wrong edges that
  agree with each other is no such block. Its dropped right edges agree on one correction of it; where they
  outvote the minimum cut of the consistent edges between their two ends, the side beyond the cut moves.
- **Learned votes** (``inlier_odds``): counts ignore what a weight says, and what it says depends on how the
  registrations failed. A first answer's consistent edges give each weight class its odds of being right in
  this graph, and the answer is re-placed once with those votes.

Each connected part of the graph is grown from its own seed (identity). Cost: one pass over the triangles
(vectorised) and, per placed scan, one vectorised comparison of the proposals of all its unplaced partners
(scores summed in edge order, so ties between placements do not depend on the BLAS); the cut moves, a radius
search over the dropped edges' corrections and a few maximum flows (scipy's) over the consistent edges.
"""

from __future__ import annotations

import heapq

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, maximum_flow
from scipy.spatial import cKDTree
from scipy.special import chdtri

from sghr_gtsam.se3 import inv_T, rotation_angle
from sghr_gtsam.sync.bridges import blocks as block_labels
from sghr_gtsam.sync.consensus import (
    MARGIN,
    MAX_DEG,
    consistent_edges,
    edge_residuals,
    mahalanobis,
    shown_variance_factor,
    translation_tolerance,
    within_noise,
)
from sghr_gtsam.types import PoseGraph


def triangles(graph: PoseGraph) -> np.ndarray:
    """(K, 3) edge indices of every triangle of the graph's edges with positive weight: rows ``(e_ab, e_bc,
    e_ca)`` for nodes ``a < b < c``. Of parallel edges only the heaviest takes part."""
    used = np.flatnonzero(graph.weight > 0)
    n = graph.n
    a, b = np.minimum(graph.i[used], graph.j[used]), np.maximum(graph.i[used], graph.j[used])
    key = a * n + b
    order = np.lexsort((-graph.weight[used], key))
    keys, first = np.unique(key[order], return_index=True)
    eid = used[order[first]]
    a, b = keys // n, keys % n
    # Sorted by (a, b): the edges (u, c) with c > v follow edge (u, v) up to the end of u's run.
    end = np.searchsorted(a, np.arange(n) + 1)[a]
    count = end - np.arange(len(a)) - 1
    p = np.repeat(np.arange(len(a)), count)
    q = p + 1 + (np.arange(len(p)) - np.repeat(np.cumsum(count) - count, count))
    wanted = b[p] * n + b[q]  # the closing edge (v, c)
    r = np.minimum(np.searchsorted(keys, wanted), len(keys) - 1)
    found = keys[r] == wanted
    return np.stack([eid[p[found]], eid[r[found]], eid[q[found]]], axis=1).astype(np.int64).reshape(-1, 3)


def _directed(graph: PoseGraph, e: np.ndarray, frm: np.ndarray) -> np.ndarray:
    """``T`` of edges ``e`` read from node ``frm`` to their other node (``T_ij`` or its inverse)."""
    T = graph.T[e]
    return np.where((graph.i[e] == frm)[:, None, None], T, inv_T(T))


def triangle_support(
    graph: PoseGraph, max_deg: float = MAX_DEG, max_trans: float | None = None, tri: np.ndarray | None = None
) -> np.ndarray:
    """(E,) number of consistent triangles (module doc) each edge is part of."""
    max_trans = translation_tolerance(graph, max_deg) if max_trans is None else max_trans
    tri = triangles(graph) if tri is None else tri
    support = np.zeros(graph.num_edges)
    if len(tri) == 0:
        return support
    e_ab, e_bc, e_ca = tri.T
    # Nodes a < b < c: e_ab joins a-b, e_bc joins b-c, e_ca joins a-c.
    a = np.minimum(graph.i[e_ab], graph.j[e_ab])
    b = np.maximum(graph.i[e_ab], graph.j[e_ab])
    c = np.maximum(graph.i[e_ca], graph.j[e_ca])
    C = _directed(graph, e_ab, a) @ _directed(graph, e_bc, b) @ _directed(graph, e_ca, c)
    ok = (np.degrees(rotation_angle(C[:, :3, :3])) <= max_deg) & (np.linalg.norm(C[:, :3, 3], axis=1) <= max_trans)
    for col in tri.T:
        support += np.bincount(col[ok], minlength=graph.num_edges)
    return support


def credibility(graph: PoseGraph) -> np.ndarray:
    """(E,) an edge's vote: ``1 + w⁰ / max w⁰`` for an edge with positive weight, else 0 — between 1 and 2,
    so a placement more edges agree on wins unless the fewer are much heavier (measured against pure
    counts and against ``w⁰`` alone on the development draws:
    the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""
    top = graph.weight.max(initial=0.0)
    return np.where(graph.weight > 0, 1.0 + graph.weight / (top if top > 0 else 1.0), 0.0)


ODDS_BINS = 8
"""Weight classes of ``inlier_odds``: octiles of log w⁰, so that each class holds an eighth of the edges (about 40
on a 60-scan graph) and its rate is measured on enough of them."""


def inlier_odds(weight: np.ndarray, kept: np.ndarray, bins: int = ODDS_BINS) -> np.ndarray:
    """(E,) an edge's vote learned from a first answer: the odds ``(k + 1) / (n − k + 1)`` that an edge of its
    weight class (``bins`` quantiles of log w⁰) is among the ``kept`` edges, ``k`` of the class's ``n``; 0 for
    an edge without weight.

    What a weight says depends on how registrations fail. Failed random registrations are light, so a heavy
    edge is likely right; a look-alike placement carries the weight of a true registration or more, so weight
    says little or speaks against. A first answer placed by counts (``credibility``) has most edges right,
    and the share of each class it keeps says what that class's weight is worth in this graph."""
    used = weight > 0
    if not used.any():
        return np.zeros(len(weight))
    log_w = np.log(np.where(used, weight, 1.0))
    cuts = np.quantile(log_w[used], np.linspace(0.0, 1.0, bins + 1))
    label = np.clip(np.searchsorted(cuts, log_w, side="right") - 1, 0, bins - 1)
    n = np.bincount(label[used], minlength=bins)
    k = np.bincount(label[used & kept], minlength=bins)
    odds = (k + 1.0) / (n - k + 1.0)
    return np.where(used, odds[label], 0.0)


def grow(
    graph: PoseGraph, cred: np.ndarray, support: np.ndarray, max_deg: float = MAX_DEG, max_trans: float | None = None
) -> np.ndarray:
    """(N, 4, 4) poses grown outward from the most credible edge (module doc); edges with ``cred <= 0`` are
    ignored, and a scan without such edges stays at the identity."""
    max_trans = translation_tolerance(graph, max_deg) if max_trans is None else max_trans
    cos_tol = np.cos(np.radians(max_deg))
    n = graph.n
    used = np.flatnonzero(cred > 0)
    # Per scan: its partners and the placement each edge proposes relative to the partner (T_as).
    ends = np.concatenate([graph.i[used], graph.j[used]])
    others = np.concatenate([graph.j[used], graph.i[used]])
    edges = np.concatenate([used, used])
    order = np.argsort(ends, kind="stable")
    ends, others, edges = ends[order], others[order], edges[order]
    rel = _directed(graph, edges, others)  # from partner to scan: T_as
    start = np.searchsorted(ends, np.arange(n + 1))
    c_inc = cred[edges]
    looped = support[edges] > 0

    poses = np.tile(np.eye(4), (n, 1, 1))
    placed = np.zeros(n, dtype=bool)
    version = np.zeros(n, dtype=np.int64)
    heap: list[tuple[int, float, int, int]] = []

    max_trans2 = max_trans**2

    def evaluate(scans: np.ndarray) -> None:
        """Push each scan of ``scans`` (unplaced, each with a placed partner) with its best placement."""
        # Every scan's incidence rows to placed partners, one segment a scan, then every pair of rows
        # within a segment: all the scans' proposals compared at once.
        counts = start[scans + 1] - start[scans]
        rows = np.repeat(start[scans] - (np.cumsum(counts) - counts), counts) + np.arange(counts.sum())
        seg = np.repeat(np.arange(len(scans)), counts)
        to_placed = placed[others[rows]]
        rows, seg = rows[to_placed], seg[to_placed]
        size = np.bincount(seg, minlength=len(scans))
        first = np.cumsum(size) - size
        P = poses[others[rows]] @ rel[rows]
        R = P[:, :3, :3].reshape(len(rows), 9)
        t = P[:, :3, 3]
        span = size[seg]
        p = np.repeat(np.arange(len(rows)), span)
        q = np.repeat(first[seg] - (np.cumsum(span) - span), span) + np.arange(len(p))
        # cos of the angle between two proposals: (trace(R_aᵀ R_b) − 1) / 2, the trace as a flat dot product.
        agree = ((np.einsum("ij,ij->i", R[p], R[q]) - 1.0) / 2.0 >= cos_tol) & (
            ((t[p] - t[q]) ** 2).sum(axis=-1) <= max_trans2
        )
        score = np.bincount(p, agree * c_inc[rows][q], len(rows))
        top = np.flatnonzero(score == np.maximum.reduceat(score, first)[seg])
        best = top[np.unique(seg[top], return_index=True)[1]]  # the first best row of each scan
        with_best = p == best[seg[p]]
        rival = np.zeros(len(scans))
        np.maximum.at(rival, seg[p[with_best & ~agree]], score[q[with_best & ~agree]])
        agreeing = np.bincount(seg[p[with_best]], agree[with_best], len(scans))
        # Tiers: a placement two placed partners agree on (a loop through the placed scans), then one
        # edge on a consistent triangle, then a lone edge; within a tier, the least ambiguous first.
        tier = np.where(agreeing >= 2, 0, np.where(looped[rows[best]], 1, 2))
        margin = score[best] - rival
        version[scans] += 1
        best_pose[scans] = P[best]
        for s, k, m, v in zip(scans.tolist(), tier.tolist(), margin.tolist(), version[scans].tolist()):
            heapq.heappush(heap, (k, -m, v, s))

    best_pose = np.tile(np.eye(4), (n, 1, 1))

    def place(s: int, pose: np.ndarray) -> None:
        poses[s] = pose
        placed[s] = True
        partners = np.unique(others[start[s] : start[s + 1]])
        partners = partners[~placed[partners]]
        if len(partners):
            evaluate(partners)

    node_cred = np.bincount(ends, c_inc, n)
    while not placed.all():
        # Seed a part: the unplaced end of the most credible edge between unplaced scans, else any scan.
        free = (~placed[graph.i[used]]) & (~placed[graph.j[used]])
        if free.any():
            e = used[free][np.lexsort((cred[used][free], support[used][free]))[-1]]
            seed = max(graph.i[e], graph.j[e], key=lambda x: node_cred[x])
        else:
            seed = int(np.flatnonzero(~placed)[0])
        place(int(seed), np.eye(4))
        while heap:
            _, _, v, s = heapq.heappop(heap)
            if placed[s] or v != version[s]:
                continue
            place(s, best_pose[s].copy())
    return poses


def replace_groups(
    graph: PoseGraph,
    poses: np.ndarray,
    cred: np.ndarray,
    max_deg: float = MAX_DEG,
    max_trans: float | None = None,
    max_rounds: int = 10,
) -> np.ndarray:
    """``poses`` with whole groups of scans moved where their edges to the other scans agree they belong.

    The groups are the blocks of the edges consistent with ``poses`` once the bridges are cut: scans held
    together by loops, but attached to the rest across one edge at most — a group a single wrong edge put
    in the wrong place, which no single-scan move can fix (every scan of it agrees with its neighbours).
    Each edge from a group to the rest proposes a rigid correction of the group; a group moves to the
    correction with the most ``cred`` among the proposals agreeing with it (at least two), if that beats
    the correction it has now (identity). Round after round, all groups at once, until none moves.
    """
    max_trans = translation_tolerance(graph, max_deg) if max_trans is None else max_trans
    cos_tol = np.cos(np.radians(max_deg))
    poses = poses.copy()
    for _ in range(max_rounds):
        kept = consistent_edges(graph, poses, max_deg, max_trans)
        label = block_labels(graph.n, graph.i, graph.j, kept)
        moved = False
        for k in range(1, int(label.max()) + 1):
            inside_i, inside_j = label[graph.i] == k, label[graph.j] == k
            cross = np.flatnonzero((inside_i != inside_j) & (cred > 0))
            if len(cross) < 2:
                continue
            # Correction M with M T_a = T_b T_ba for the scan a inside: edge (a, b) or (b, a).
            a_in = inside_i[cross]
            a = np.where(a_in, graph.i[cross], graph.j[cross])
            b = np.where(a_in, graph.j[cross], graph.i[cross])
            M = poses[b] @ _directed(graph, cross, b) @ inv_T(poses[a])
            M = np.concatenate([M, np.eye(4)[None]])
            nodes = np.flatnonzero(label == k)
            centre = poses[nodes, :3, 3].mean(axis=0)
            moved_centre = M[:, :3, :3] @ centre + M[:, :3, 3]
            R = M[:, :3, :3]
            agree = ((np.einsum("kab,lab->kl", R, R) - 1.0) / 2.0 >= cos_tol) & (
                np.linalg.norm(moved_centre[:, None] - moved_centre[None], axis=-1) <= max_trans
            )
            support = agree[:, :-1] @ cred[cross]
            best = int(np.argmax(support[:-1]))
            if agree[best, :-1].sum() >= 2 and support[best] > support[-1] and not agree[best, -1]:
                poses[nodes] = M[best] @ poses[nodes]
                moved = True
        if not moved:
            break
    return poses


CUT_FAMILIES = 5
"""``cut_moves`` tries the moves of this many families of dropped edges a round, the heaviest first."""
CUT_ROUNDS = 3
"""``cut_moves``: moves at most."""
_CAPACITY = 1000
"""Votes become integer capacities (scipy's maximum flow) at this resolution."""


def cut_moves(
    graph: PoseGraph,
    poses: np.ndarray,
    votes: np.ndarray,
    max_deg: float = MAX_DEG,
    max_trans: float | None = None,
    max_rounds: int = CUT_ROUNDS,
    families: int = CUT_FAMILIES,
) -> np.ndarray:
    """``poses`` with one side of a minimum cut moved where the dropped edges across it agree it belongs.

    ``replace_groups`` moves blocks hung on one edge; a group held in a wrong place by several consistent
    wrong edges (a look-alike placement repeated on 2-4 registrations, or a majority of random outliers)
    is no block, and its scans agree with their neighbours, so no single-scan move frees it either. Its
    right edges to the rest are dropped, and they agree on one rigid correction of it. So: the dropped edges
    (``votes > 0``, inconsistent with ``poses``) are read as corrections ``M`` that move one end onto where
    the other end's edge puts it (both ways); corrections agreeing in rotation (``max_deg``) and in where they
    put both moving ends (``max_trans``) form a family, and an edge both of whose readings agree counts for
    none. For the ``families`` heaviest families of two edges or more, the consistent edges (capacities: their
    votes) are cut at minimum between the family's fixed and moving ends; where the family's votes exceed the
    cut's by ``consensus.MARGIN``, the cut is not empty (no two parts are joined) and leaves two scans or more on
    either side, the moving side (the smallest one) moves by the family's correction, if the consistent edges of
    the result carry more votes. At most ``max_rounds`` moves.
    """
    max_trans = translation_tolerance(graph, max_deg) if max_trans is None else max_trans
    poses = poses.copy()
    kept = consistent_edges(graph, poses, max_deg, max_trans)
    for _ in range(max_rounds):
        total = votes[kept].sum()
        for fixed, moving, M, family_votes in _families(graph, poses, votes, kept, max_deg, max_trans, families):
            side = _cut_side(graph, kept, votes, fixed, moving, family_votes)
            if side is None:
                continue
            trial = poses.copy()
            trial[side] = M @ poses[side]
            trial_kept = consistent_edges(graph, trial, max_deg, max_trans)
            if votes[trial_kept].sum() > total:
                poses, kept = trial, trial_kept
                break
        else:
            break
    return poses


def _families(
    graph: PoseGraph,
    poses: np.ndarray,
    votes: np.ndarray,
    kept: np.ndarray,
    max_deg: float,
    max_trans: float,
    count: int,
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
    """The ``count`` heaviest families of ``cut_moves`` (two edges or more, no shared members): each its fixed
    ends, its moving ends, its correction (that of its heaviest reading) and its votes."""
    dropped = np.flatnonzero((votes > 0) & ~kept)
    if len(dropped) < 2:
        return []
    edge = np.r_[dropped, dropped]
    fixed = np.r_[graph.i[dropped], graph.j[dropped]]
    moving = np.r_[graph.j[dropped], graph.i[dropped]]
    # M T_moving = T_fixed T_fixed,moving: the correction that puts the moving end where the edge says.
    M = poses[fixed] @ _directed(graph, edge, fixed) @ inv_T(poses[moving])
    R, t = M[:, :3, :3], M[:, :3, 3]
    p = poses[moving, :3, 3]
    # ‖R_a − R_b‖_F = 2√2 sin(θ/2): the rotation test is a radius search, exact up to rounding.
    radius = 2.0 * np.sqrt(2.0) * np.sin(np.radians(max_deg) / 2.0) * (1.0 + 1e-12)
    a, b = cKDTree(R.reshape(-1, 9)).query_pairs(radius, output_type="ndarray").T.astype(np.int64)
    ok = (
        (edge[a] != edge[b])
        & (np.linalg.norm(np.einsum("kab,kb->ka", R[b] - R[a], p[a]) + t[b] - t[a], axis=1) <= max_trans)
        & (np.linalg.norm(np.einsum("kab,kb->ka", R[a] - R[b], p[b]) + t[a] - t[b], axis=1) <= max_trans)
    )
    x, y = np.r_[a[ok], b[ok]], np.r_[b[ok], a[ok]]
    # An edge whose two readings both agree with x says nothing about which side moves.
    key = x * graph.num_edges + edge[y]
    _, inverse, twice = np.unique(key, return_inverse=True, return_counts=True)
    one_way = twice[inverse] == 1
    x, y = x[one_way], y[one_way]
    score = votes[edge] + np.bincount(x, votes[edge[y]], len(edge))
    by_x = np.argsort(x, kind="stable")
    x, y = x[by_x], y[by_x]
    start = np.searchsorted(x, np.arange(len(edge) + 1))
    taken = np.zeros(len(edge), dtype=bool)
    out = []
    heads = np.flatnonzero(start[1:] > start[:-1])  # readings that some other edge agrees with
    for r in heads[np.argsort(-score[heads], kind="stable")]:
        if len(out) == count:
            break
        if taken[r]:
            continue
        members = np.r_[r, y[start[r] : start[r + 1]]]
        members = members[~taken[members]]
        taken[members] = True
        # A scan both fixed and moved by the family: the role with fewer votes loses its edges.
        for c in np.intersect1d(fixed[members], moving[members]):
            as_fixed, as_moving = fixed[members] == c, moving[members] == c
            w = votes[edge[members]]
            members = members[~as_moving] if w[as_fixed].sum() >= w[as_moving].sum() else members[~as_fixed]
        if len(members) < 2:
            continue
        out.append((np.unique(fixed[members]), np.unique(moving[members]), M[r], float(votes[edge[members]].sum())))
    return out


def _cut_side(
    graph: PoseGraph, kept: np.ndarray, votes: np.ndarray, fixed: np.ndarray, moving: np.ndarray, family_votes: float
) -> np.ndarray | None:
    """The scans on ``moving``'s side of a minimum cut of the ``kept`` edges (capacities: ``votes``) between
    ``fixed`` and ``moving`` (disjoint), if the cut is not empty, ``family_votes`` exceed its votes by
    ``consensus.MARGIN`` (as a single scan's move must) and it leaves two scans or more on each side; else None."""
    n = graph.n
    cap = np.rint(votes[kept] * _CAPACITY).astype(np.int64)
    big = int(cap.sum()) * 2 + 1
    if big >= np.iinfo(np.int32).max:
        return None
    source, sink = n, n + 1
    rows = np.r_[graph.i[kept], graph.j[kept], np.full(len(fixed), source), moving]
    cols = np.r_[graph.j[kept], graph.i[kept], fixed, np.full(len(moving), sink)]
    data = np.r_[cap, cap, np.full(len(fixed) + len(moving), big)].astype(np.int32)
    C = sp.csr_matrix((data, (rows, cols)), shape=(n + 2, n + 2))
    flow = maximum_flow(C, source, sink)
    # No consistent edge between the ends: the move would join two parts on dropped edges alone, which is the
    # front end's to verify (a building whose halves only wrong registrations joined:
    # the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md).
    if flow.flow_value == 0 or (1.0 + MARGIN) * flow.flow_value >= family_votes * _CAPACITY:
        return None
    residual = (C - flow.flow).tocsr()  # ≥ 0: the flow is antisymmetric and within the capacities
    residual.eliminate_zeros()
    # The smallest sides: the scans the source still reaches, and those from which the sink is still reachable.
    held = breadth_first_order(residual, source, directed=True, return_predecessors=False)
    side = breadth_first_order(residual.T.tocsr(), sink, directed=True, return_predecessors=False)
    side = np.sort(side[side < n])
    # A cut that isolates one scan is a single scan's move: consensus_placement's, which compares where its
    # edges put that scan.
    return side if min(len(side), int(np.sum(held < n))) >= 2 else None


RESIDUAL_SPREAD = 4.0
"""The kept edges' tolerance is at least this many times the median residual of the edges consistent
at the base tolerances: registration noise larger than those (3DMatch-like: 8 cm at a scan's origin
against a base of ~9 cm, tails to 25 cm) would otherwise drop right edges and cost accuracy at no outliers at all."""


def kept_edges_at(
    graph: PoseGraph, poses: np.ndarray, max_deg: float = MAX_DEG, max_trans: float | None = None
) -> np.ndarray:
    """(E,) bool: edges consistent with ``poses`` at the base tolerances widened to ``RESIDUAL_SPREAD`` times the
    median residual of the edges consistent at the base tolerances, or, with ``graph.information``, within
    their own noise (``consensus.within_noise``; gtsam's grid graphs have σ ≈ 15° on every edge)."""
    max_trans = translation_tolerance(graph, max_deg) if max_trans is None else max_trans
    E, rot, trans = edge_residuals(graph, poses)
    base = (graph.weight > 0) & (rot <= max_deg) & (trans <= max_trans)
    if base.any():
        max_deg = max(max_deg, RESIDUAL_SPREAD * float(np.median(rot[base])))
        max_trans = max(max_trans, RESIDUAL_SPREAD * float(np.median(trans[base])))
    close = (rot <= max_deg) & (trans <= max_trans)
    if graph.information is not None:
        close |= within_noise(E, graph.information)
    return (graph.weight > 0) & close


FAMILY_ALPHA = 0.01
"""``within_shown_noise``: the chance that any one of a graph's edges whose residual is its noise fails the test."""


def within_shown_noise(graph: PoseGraph, poses: np.ndarray, consistent: np.ndarray) -> np.ndarray:
    """(E,) bool: the ``consistent`` edges and, with ``graph.information``, the edges of positive weight whose
    ``ξᵀΩξ`` (``consensus.mahalanobis``) at ``poses`` is below χ²₆ at ``1 − FAMILY_ALPHA / E`` times the variance
    factor ``s² ≥ 1`` the set shows (its median ``ξᵀΩξ`` over χ²₆'s median), judged again at each new factor
    until the set stays.

    An edge's stated information can be overconfident by the same factor on every edge (a benchmark graph whose
    residuals at the least-squares optimum are 15° against a stated 0.9°: ``ξᵀΩξ`` ~270): tested against the
    information as stated, or at fixed tolerances, the tail of its noise reads as outliers. The factor is the
    graph's own, a median of edges already judged consistent, which outliers far off do not move; the quantile
    shrinks with the number of edges, so that the largest of E residuals of pure noise passes. A factor learnt
    from poses is only as good as they are (least squares over outliers spreads their error and inflates it), so
    this widens the kept edges of an answer chosen without it, never the choice between answers."""
    used = graph.weight > 0
    kept = consistent & used
    if graph.information is None or not kept.any():
        return kept
    chi2 = mahalanobis(edge_residuals(graph, poses)[0], graph.information)
    limit = chdtri(6, FAMILY_ALPHA / int(used.sum()))
    factor = None
    for _ in range(_SHOWN_NOISE_ROUNDS):
        previous, factor = factor, shown_variance_factor(chi2[kept])
        if factor == previous:
            break
        kept = consistent & used | used & (chi2 <= factor * limit)
    return kept


_SHOWN_NOISE_ROUNDS = 10  # the factor settles in 2-4 (a truncation at ~6.7× the median barely moves a median)


__all__ = [
    "triangles",
    "triangle_support",
    "credibility",
    "inlier_odds",
    "grow",
    "replace_groups",
    "cut_moves",
    "kept_edges_at",
    "within_shown_noise",
]
