"""Pose synchronization: absolute poses from a graph of relative ones (SGHR step 3, then the gtsam polish).

``synchronize(graph, method=...)`` is the public entry point; ``METHODS`` lists the methods, ``POLISHES``
what follows them. The maths lives in ``rotation`` (spectral rotations), ``translation`` (least-squares
translations) and ``irls`` (history reweighting, the warm start); the default polish, ``loops``, decides which
edges to trust by loop evidence (``cycles``: triangle support, growing from the most consistent core, group
moves) and by placement consensus (``consensus``); ``robust`` uses consensus and gtsam GNC instead. Either
ends with gtsam Levenberg–Marquardt (``sghr_gtsam.factor_graph``) on the edges it trusts, each with its own
information when the graph has it, else its initial weight.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from functools import lru_cache

import numpy as np
from threadpoolctl import ThreadpoolController

from sghr_gtsam.io.g2o import sesync_precisions
from sghr_gtsam.se3 import inv_T, non_rigid, project_to_so3
from sghr_gtsam.sync.bridges import biconnected_core, blocks
from sghr_gtsam.sync.consensus import (
    MAX_DEG,
    consensus_placement,
    consistent_edges,
    edge_residuals,
    translation_tolerance,
)
from sghr_gtsam.sync.cycles import (
    credibility,
    cut_moves,
    grow,
    inlier_odds,
    kept_edges_at,
    replace_groups,
    triangle_support,
    within_shown_noise,
)
from sghr_gtsam.sync.irls import REWEIGHTS, irls, solve_poses, usable_edges
from sghr_gtsam.sync.rotation import connected_components, rotation_residuals
from sghr_gtsam.types import InputError, IterationRecord, PoseGraph, SyncResult

POLISHES: dict[str, str] = {
    "loops": "loop evidence (sync.cycles): the IRLS poses and scans grown outward from the most consistent "
    "core, each polished by gtsam Levenberg-Marquardt on its consistent edges and re-placed by groups "
    "and by scans where most edges agree; the one with more consistent edges wins (unless the other fits "
    "more of the edges they place far apart), its groups held by several wrong edges move across a "
    "minimum cut, and it is re-placed once more with the votes its consistent edges teach each weight "
    "class; then LM",
    "robust": "consensus re-placement of scans, gtsam GNC (TLS) over every edge, consensus again, then "
    "gtsam Levenberg-Marquardt on the edges consistent with the poses",
    "lm": "gtsam Levenberg-Marquardt on the edges IRLS kept",
    "none": "the IRLS poses as they are",
}

MAX_ITERS = 10_000
"""The most IRLS iterations M: SGHR uses 50; history reweighting's g(m) = 2m / (M(M+1)) spreads its weight thinner
with M, and each iteration is an eigen-solve (1e9 ended in MemoryError, 2^63 in IndexError)."""

FAR = 2.0
"""The loop polish's answers are also compared on the edges one fits and the other puts this many times the
consistency tolerances off (``_overturns``)."""

REFIT_ROUNDS = 3
"""With ``"loops"``: final least-squares solves at most, the kept edges re-judged at each optimum (``_readmit``)."""

GNC_ITERS = 10
"""Cap of each inner Levenberg-Marquardt run of the robust polish's GNC: 10 and 100 give the same
robustness-benchmark recall (2 seeds), and 10 halves the time at 50 scans."""

LM_START_FLOOR = 1e-3
"""Method ``lm``'s chordal start weighs each edge by its isotropic precisions raised to at least this fraction of
the largest. The spectral solve does not resolve a wider span where the light edges alone hold a group (two
triangles joined by edges of 1e-6 of the others' information: a start 27° off, which LM repairs), and LM cannot
move what edges far below its tolerance hold (1e-9: 14-22° off at the end; 1e-20: 100-170°; in a loop, gtsam's
"Factor is exactly singular"). Raised, they place it as the other methods' starts do; the parking garage (κ spans
1e-9) ends at the same optimum."""

_SQUARABLE = (float(np.sqrt(np.finfo(float).tiny)), float(np.sqrt(np.finfo(float).max)))
"""The range of an edge's information eigenvalues whose squares are normal doubles (1.5e-154 to 1.3e154). Shonan's
eigen-solver fails below it (1e-200: "TridiagEigen: eigen decomposition failed") where the other methods answer,
so every method refuses such information: one answer for a graph, whatever the method."""

METHODS: dict[str, str] = {
    "history": "SGHR: IRLS with history reweighting (g(m) = 2m/(M(M+1))), then the polish",
    "constant": "ablation of 'history': constant history schedule g(m) = 1/M",
    "current": "ablation of 'history': no history, weights from the current residual only",
    "spectral": "one weighted spectral solve and least-squares translations, no reweighting",
    "lm": "spectral estimate, then gtsam Levenberg-Marquardt on the edges' information (pose-graph benchmarks)",
}


@lru_cache(maxsize=1)
def _blas() -> ThreadpoolController:
    return ThreadpoolController()  # finds the loaded BLAS libraries once (~30 ms)


def synchronize(
    graph: PoseGraph,
    *,
    method: str = "history",
    iters: int = 50,
    reweight: str = "authors",
    polish: str = "loops",
    min_weight: float = 1e-3,
    on_iteration: Callable[[IterationRecord], None] | None = None,
) -> SyncResult:
    """Absolute poses ``T_i`` (``T_ij = T_i⁻¹ T_j``) of every node of ``graph``.

    ``method``: a key of ``METHODS``. ``iters``: IRLS iterations M. ``reweight``: ``"authors"`` (δ in degrees,
    factor 2, as the authors' code) or ``"paper"`` (δ in radians, as the paper writes it); see ``irls``.
    ``polish``: a key of ``POLISHES`` (method ``"lm"`` always ends with Levenberg-Marquardt). An edge that
    enters a gtsam solve does so with its own information if the graph has it, else with its initial weight
    as precision scale (``factor_graph.edge_information``). Every edge with a positive initial weight is used
    (above ``irls.NEGLIGIBLE`` of the largest). With ``"none"`` and ``"lm"`` the kept edges are those whose
    reweighted weight is not below ``min_weight`` times their initial weight; with ``"robust"`` those consistent
    with the final poses (``consensus.consistent_edges``); with ``"loops"`` (default; ``_loop_placement``,
    ``_readmit``) those consistent with the least-squares optimum over them, at tolerances widened to the
    residual spread or within their own noise (``cycles.kept_edges_at``). Dropped edges have weight 0 in
    the result; kept ones their last IRLS weight (``"robust"``, ``"loops"``: ``w⁰``). ``"loops"`` also
    fills ``SyncResult.loop_support``.

    The nodes split into connected parts over the kept edges; ``SyncResult.component`` labels them (0 =
    the largest) and every part is anchored at its own first node (the identity). A node without kept
    edges is a part of its own. The result does not depend on the order of the edges (they are solved sorted
    by (i, j, weight, T)); it can depend on the nodes' labels, which break ties between near-equal placements
    ("Still near-ties, now deterministic" in the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md).
    Raises ``InputError`` for unusable input.
    """
    # The dense blocks are small (3N×3N below DENSE_NODES, 3N×3 beyond): a multithreaded BLAS spends its
    # time synchronising threads, 10-30× slower on a busy 2-core machine (a 180×180 Cholesky: 0.8 ms on one
    # thread, 3 ms on two; a warm eigen-solve 12 ms against 165 ms).
    with _blas().limit(limits=1, user_api="blas"):
        return _synchronize(
            graph,
            method=method,
            iters=iters,
            reweight=reweight,
            polish=polish,
            min_weight=min_weight,
            on_iteration=on_iteration,
        )


def _synchronize(
    graph: PoseGraph,
    *,
    method: str,
    iters: int,
    reweight: str,
    polish: str,
    min_weight: float,
    on_iteration: Callable[[IterationRecord], None] | None,
) -> SyncResult:
    if polish not in POLISHES:
        raise InputError(f"unknown polish {polish!r}; choose from {', '.join(POLISHES)}")
    if method not in METHODS:
        raise InputError(f"unknown synchronization method {method!r}; choose from {', '.join(METHODS)}")
    if reweight not in REWEIGHTS:
        raise InputError(f"unknown reweighting {reweight!r}; choose from {', '.join(REWEIGHTS)}")
    if not 1 <= iters <= MAX_ITERS:
        raise InputError(f"iters must be an integer from 1 to {MAX_ITERS:,}; got {iters:,}")
    # Growing and consensus break ties in edge order: the edges are solved in one canonical order, so that the
    # result does not depend on the order they come in (a g2o file's lines, the pipeline's stages).
    graph, order = _canonical(checked_graph(graph))
    back = np.argsort(order)
    history: list[IterationRecord] = []

    def keep_history(record: IterationRecord) -> None:
        record = replace(record, weights=record.weights[back], residual_deg=record.residual_deg[back])
        history.append(record)
        if on_iteration is not None:
            on_iteration(record)

    if method in ("history", "constant", "current"):
        # The IRLS methods are named after their history schedule.
        result = irls(
            graph, iters=iters, reweight=reweight, schedule=method, min_weight=min_weight, on_iteration=keep_history
        )
        weights, kept, poses = result.weights, result.kept, result.poses
    else:
        weights = graph.weight
        kept = usable_edges(weights)  # initial weights: nothing reweighted them yet
        used = np.where(kept, weights, 0.0)
        if method == "lm" and graph.information is not None:
            poses = _chordal(replace(graph, weight=used))
        else:
            poses = solve_poses(graph, used)
    support = held = None
    iterative = (polish != "none" or method == "lm") and _iterative(graph)
    if polish == "robust" and method != "lm":
        poses, kept = _robust_placement(graph, poses, keep_history)
        weights = graph.weight
    elif polish == "loops" and method != "lm":
        poses, kept, support = _loop_placement(graph, poses, keep_history, iterative)
        weights = graph.weight
    if polish != "none" or method == "lm":
        from sghr_gtsam.factor_graph import edge_information
        from sghr_gtsam.factor_graph import polish as lm_polish

        # The history weights decide which edges are kept; as precisions they are miscalibrated (an inlier
        # 3° off has e⁻⁶ of the weight of a perfect one), which measurably costs accuracy, so the kept edges
        # enter least squares with their initial weights, or their own information (see factor_graph).
        def solve(P: np.ndarray, kept: np.ndarray, record: bool = True) -> np.ndarray:
            component = connected_components(graph.n, graph.i, graph.j, kept)
            information = edge_information(graph, np.where(kept, graph.weight, 0.0))
            return lm_polish(
                graph,
                P,
                information,
                component,
                weights=np.where(kept, weights, 0.0),
                iterative=iterative,
                relative_tol=1e-9 if method == "lm" else 1e-6,
                on_iteration=keep_history if record else None,
            ).poses

        poses = solve(poses, kept)
        if polish == "loops" and method != "lm":
            poses, kept, held = _readmit(graph, poses, kept, solve)
    weights = np.where(kept, weights, 0.0)
    component = connected_components(graph.n, graph.i, graph.j, kept)
    poses = _anchored(poses, component)  # a part re-judged apart is anchored at its own first node
    residual = rotation_residuals(poses[:, :3, :3], graph.i, graph.j, graph.T[:, :3, :3])
    return SyncResult(
        poses=poses,
        weights=weights[back],
        residual_deg=np.degrees(residual)[back],
        component=component,
        history=history,
        loop_support=None if support is None else support[back],
        held=None if held is None else held[back],
    )


def _chordal(graph: PoseGraph) -> np.ndarray:
    """The chordal initial estimate of ``graph`` with information: each edge weighted by its weight times its
    isotropic precisions (SE-Sync's κ, τ, raised to ``LM_START_FLOOR`` of the largest)."""
    kappa, tau = (np.maximum(p, LM_START_FLOOR * p.max()) for p in sesync_precisions(graph.information))
    return solve_poses(graph, graph.weight * kappa, w_trans=graph.weight * tau)


def _iterative(graph: PoseGraph) -> bool:
    """Whether the LM polishes of ``graph`` solve by conjugate gradients (``factor_graph.DIRECT_FLOPS``): judged
    on its usable edges, a superset of those any polish uses."""
    from sghr_gtsam.factor_graph import DIRECT_FLOPS
    from sghr_gtsam.sync.fill import direct_cost

    usable = usable_edges(graph.weight)
    return direct_cost(graph.n, graph.i[usable], graph.j[usable]) > DIRECT_FLOPS


def _canonical(graph: PoseGraph) -> tuple[PoseGraph, np.ndarray]:
    """``graph`` with its edges sorted by (i, j, weight, T), and that order."""
    keys = [*graph.T[:, :3].reshape(graph.num_edges, 12).T[::-1], graph.weight, graph.j, graph.i]
    order = np.lexsort(keys)
    info = None if graph.information is None else graph.information[order]
    return replace(
        graph, i=graph.i[order], j=graph.j[order], T=graph.T[order], weight=graph.weight[order], information=info
    ), order


def _usable(graph: PoseGraph) -> PoseGraph:
    """``graph`` without its negligible edges (initial weight below ``irls.NEGLIGIBLE`` of the largest: weight 0)."""
    return replace(graph, weight=np.where(usable_edges(graph.weight), graph.weight, 0.0))


def _anchored(poses: np.ndarray, component: np.ndarray) -> np.ndarray:
    """``poses`` with every part (``component`` label) moved so that its first node is the identity."""
    first = np.unique(component, return_index=True)[1]
    return inv_T(poses[first[component]]) @ poses


def _readmit(
    graph: PoseGraph, poses: np.ndarray, kept: np.ndarray, solve: Callable[..., np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The loop polish's kept edges re-judged at least-squares optima (``kept_edges_at``), at most
    ``REFIT_ROUNDS`` solves: the placement steps judge edges at poses before least squares and with tolerances
    for registrations good to a few degrees, so on a clean graph with large noise (gtsam's grids: σ ≈ 11°
    on every edge) they leave edges out that the optimum over all of them fits within their noise. With
    the edges' own information (the only noise model an edge can be re-admitted by), every usable edge is
    tried from the current poses too, and in the first round from the chordal start of method ``"lm"``: a graph
    whose noise exceeds the placement's tolerances falls apart there into parts, each anchored at its own first
    node, a start from which least squares over every edge finds a local minimum only (a benchmark graph with
    15° residuals: 8 parts left). The larger consistent set wins, widened to the noise the graph shows at its
    poses (``within_shown_noise``), and that set is solved again. Edges that
    alone join two parts stay kept (``_holding``); the last mask is returned with the poses and the kept edges."""
    usable_graph = _usable(graph)
    usable = usable_graph.weight > 0
    held = np.zeros(graph.num_edges, dtype=bool)
    for k in range(REFIT_ROUNDS - 1):
        refit = kept_edges_at(usable_graph, poses)
        if graph.information is not None and not np.array_equal(refit, usable):
            starts = [poses, _chordal(usable_graph)] if k == 0 else [poses]
            for start in starts:
                trial = solve(start, usable, record=False)
                widest = kept_edges_at(usable_graph, trial)
                if widest.sum() > refit.sum():
                    poses, refit = trial, widest
        refit = within_shown_noise(usable_graph, poses, refit)
        held = _holding(usable_graph, poses, kept, refit)
        refit |= held
        if np.array_equal(refit, kept):
            break
        kept = refit
        poses = solve(poses, kept)
    return poses, kept, held


def _holding(graph: PoseGraph, poses: np.ndarray, kept: np.ndarray, refit: np.ndarray) -> np.ndarray:
    """(E,) bool: edges of ``kept`` that ``refit`` drops although they join two of its parts, and that ``poses``
    fit within ``FAR`` times the consistency tolerances.

    Such edges are all that place one part against the other, and least squares has already placed the parts by
    them: their residuals are the share of a loop's error they took (a lone edge takes none), not a vote
    against a placement that other edges support. Dropping them loses the part instead (five right scans held by
    two loop-checked registrations 2.7° / 0.10 m off after least squares spread a corridor's error, against a
    tolerance of 0.08 m)."""
    part = connected_components(graph.n, graph.i, graph.j, refit)
    return kept & ~refit & (part[graph.i] != part[graph.j]) & ~_far(graph, poses)


def _loop_placement(
    graph: PoseGraph, poses: np.ndarray, keep_history: Callable[[IterationRecord], None], iterative: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The loop polish before its last LM (``sync.cycles``): the poses, the (E,) mask of the edges
    consistent with them and every edge's loop support.

    Two starts: ``poses`` (the IRLS warm start) and the scans grown from the most consistent core. Each is
    polished by LM on its consistent edges (growing chains registration errors, which the consistency test
    would read as disagreement), then whole groups and single scans move where most of their edges agree
    (``replace_groups``, ``consensus_placement`` with the ``credibility`` votes). Growing is what keeps a
    look-alike from dragging a group; the IRLS poses hold better where 70 % of the edges are wrong and the
    core's evidence runs thin (the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md).
    The grown start replaces the IRLS one if it has more
    consistent edges, and not fewer among those the other answer puts far off (``_overturns``); in the answer
    kept, groups held in place by several wrong edges move across a minimum cut (``cut_moves``). The kept
    answer's consistent edges then say what each weight class is worth in this graph (``inlier_odds``);
    re-placed with those votes, the answer changes by the same rule with those votes (a look-alike placement
    that more, lighter edges propose loses where light edges are mostly wrong). The final answer's kept edges
    are those consistent at tolerances widened to the residual spread (``kept_edges_at``), so that without
    outliers every edge stays and the final LM is plain least squares. Edges negligible from
    the start (below ``irls.NEGLIGIBLE``) stay out, as in IRLS.
    """
    from sghr_gtsam.factor_graph import edge_information
    from sghr_gtsam.factor_graph import polish as lm_polish

    usable = _usable(graph)
    support = triangle_support(usable)
    cred = credibility(usable)

    def record(stage: str, k: int, P: np.ndarray, kept: np.ndarray) -> None:
        keep_history(_record(graph, stage, k, P, kept))

    def place(P: np.ndarray, votes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kept = consistent_edges(usable, P)
        component = connected_components(graph.n, graph.i, graph.j, kept)
        P = lm_polish(
            graph, P, edge_information(graph, np.where(kept, graph.weight, 0.0)), component, iterative=iterative
        ).poses
        P = consensus_placement(replace(usable, weight=votes), replace_groups(usable, P, votes))
        return P, consistent_edges(usable, P)

    P, kept = place(poses, cred)
    record("loops/irls", 1, P, kept)
    Q, kept_q = place(grow(usable, cred, support), cred)
    record("loops/grow", 2, Q, kept_q)
    # Ties go to the IRLS start: near-ties are where it is right (tests).
    if _overturns(usable, np.ones(graph.num_edges), (Q, kept_q), (P, kept)):
        P, kept = Q, kept_q
    # Groups held by several wrong edges move in the answer kept, not within each start: moved within the grown
    # start, a real scene's first graph gave an answer that won a near-tie (183 against 181 consistent edges) with
    # 13 scans still turned 86°, where the IRLS start was right.
    P = cut_moves(usable, P, cred)
    kept = consistent_edges(usable, P)
    # A second opinion with the votes the first answer learned.
    odds = inlier_odds(usable.weight, kept)
    Q, kept_q = place(P, odds)
    record("loops/odds", 3, Q, kept_q)
    if _overturns(usable, odds, (Q, kept_q), (P, kept)):
        P, kept = Q, kept_q
    kept = kept_edges_at(usable, P)
    # Every part is anchored at its own first node (the grown poses are anchored at the seed).
    return _anchored(P, connected_components(graph.n, graph.i, graph.j, kept)), kept, support


def _overturns(
    graph: PoseGraph,
    votes: np.ndarray,
    challenger: tuple[np.ndarray, np.ndarray],
    incumbent: tuple[np.ndarray, np.ndarray],
) -> bool:
    """Whether the ``challenger`` answer (poses, consistent edges) replaces the ``incumbent``: its consistent edges
    carry more ``votes``, and of the edges one answer fits and the other puts far off (beyond ``FAR`` times the
    consistency tolerances) its share carries at least as many.

    Votes alone are decided by edges just inside the tolerances in one answer and just outside in the other:
    on a real scene's final graph, 204 consistent edges against 203, in some orders of the edges, for an answer
    that turns 24 scans 91° and that 4 edges to them support against 6.
    Far-off edges alone would let a drifted answer win: one whose scans sit 10-20° off puts few edges
    far."""
    (Q, kept_q), (P, kept) = challenger, incumbent
    if votes[kept_q].sum() <= votes[kept].sum():
        return False
    return bool(votes[kept_q & _far(graph, P)].sum() >= votes[kept & _far(graph, Q)].sum())


def _far(graph: PoseGraph, poses: np.ndarray) -> np.ndarray:
    """(E,) bool: edges ``poses`` put beyond ``FAR`` times the consistency tolerances."""
    _, rot, trans = edge_residuals(graph, poses)
    return (rot > FAR * MAX_DEG) | (trans > FAR * translation_tolerance(graph))


def _robust_placement(
    graph: PoseGraph, poses: np.ndarray, keep_history: Callable[[IterationRecord], None]
) -> tuple[np.ndarray, np.ndarray]:
    """The robust polish before its LM: consensus re-placement, GNC, consensus; the poses and the (E,)
    mask of edges consistent with them.

    Residual reweighting keeps a wrong placement repeated on several edges of a scan and ignores
    translations (the authors' units). The consensus step can move a scan back by 90° or a metre, which
    no descent does; GNC over all edges then weighs translations too, and a second consensus pass catches
    what GNC moved (robustness in the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md).
    Edges negligible from the start (below
    ``irls.NEGLIGIBLE``) stay out, as in IRLS.
    """
    from sghr_gtsam.factor_graph import edge_information, gnc_tls_poses

    usable = _usable(graph)
    steps = (
        ("consensus", lambda P: consensus_placement(usable, P)),
        ("gnc", lambda P: gnc_tls_poses(usable, P, edge_information(usable, usable.weight), GNC_ITERS)[0]),
        ("consensus", lambda P: consensus_placement(usable, P)),
    )
    for k, (stage, step) in enumerate(steps, 1):
        poses = step(poses)
        kept = consistent_edges(usable, poses)
        keep_history(_record(graph, stage, k, poses, kept))
    return poses, kept


def _record(graph: PoseGraph, stage: str, k: int, poses: np.ndarray, kept: np.ndarray) -> IterationRecord:
    """A polish step's record: its poses, the weights of the edges it keeps, every edge's rotation residual."""
    residual = rotation_residuals(poses[:, :3, :3], graph.i, graph.j, graph.T[:, :3, :3])
    return IterationRecord(
        stage=stage,
        iteration=k,
        poses=poses,
        weights=np.where(kept, graph.weight, 0.0),
        residual_deg=np.degrees(residual),
    )


def unverified(graph: PoseGraph, result: SyncResult, one_scan: bool = True) -> np.ndarray:
    """(N,) bool: nodes of the largest part (``component == 0``) whose place in it rests on one registration, or on
    one scan's registrations, that no independent loop checks.

    Among the edges the result kept (weight > 0), a bridge is an edge on no cycle. Without the bridges the
    largest part falls into blocks in which every edge is cross-checked by another path; nodes outside the
    block with the most nodes are reached from it only across a bridge. A wrong registration on a bridge cannot
    be outvoted by anything — the nodes beyond it go wherever it says — so their placement is unverified (it
    may well be right: a chain of scans is all bridges). The same holds beyond one scan (an articulation point):
    its registrations to the rest can all be wrong in the same way, as a square room's scan registered 90°
    turned to four of its partners, and the scans that hang on it follow (a simulated 50-scan room, seed 3: 21
    scans turned 89° behind one scan, 17 of them flagged by nothing else). So a node outside the largest
    biconnected component (``bridges.biconnected_core``) is unverified too; ``one_scan=False`` leaves that out.
    Edges kept past the tolerances only because they alone join two parts (``SyncResult.held``) check nothing: the
    nodes they join to the rest are unverified.
    """
    main = result.component == 0
    kept = (result.weights > 0) & main[graph.i] & main[graph.j]
    if result.held is not None:
        kept &= ~result.held  # past the tolerances, kept only to join two parts: they check nothing
    label = blocks(graph.n, graph.i, graph.j, kept)
    # The largest block of the main part (ties: the one with the smallest node), as labels are ordered.
    core = label[np.flatnonzero(main)].min()
    beyond_one_scan = main & ~biconnected_core(graph.n, graph.i, graph.j, kept) if one_scan and kept.any() else False
    return main & (label != core) | beyond_one_scan


def checked_graph(graph: PoseGraph) -> PoseGraph:
    """``graph`` with its checks passed: integer indices, float arrays, rotations projected onto SO(3).

    Raises ``InputError`` (one line) for fewer than 2 nodes, no edges, inconsistent shapes, indices out
    of range or self-loops, non-finite values, negative weights, a ``T`` that is not a rigid transform or whose
    translation leaves ``_SQUARABLE``, or information that is not positive definite or whose eigenvalues leave it.
    """
    n = int(graph.n)
    if n < 2:
        raise InputError(f"pose graph needs at least 2 nodes, got {n}")
    i, j = np.asarray(graph.i), np.asarray(graph.j)
    T, w = np.asarray(graph.T, dtype=float), np.asarray(graph.weight, dtype=float)
    E = len(i)
    if E == 0:
        raise InputError("pose graph has no edges")
    if i.shape != (E,) or j.shape != (E,) or T.shape != (E, 4, 4) or w.shape != (E,):
        raise InputError(f"pose graph arrays disagree: i {i.shape}, j {j.shape}, T {T.shape}, weight {w.shape}")
    if not (np.issubdtype(i.dtype, np.integer) and np.issubdtype(j.dtype, np.integer)):
        raise InputError("pose graph node indices must be integers")
    bad = np.flatnonzero((i < 0) | (i >= n) | (j < 0) | (j >= n))
    if len(bad):
        raise InputError(f"edge {bad[0]}: node index ({i[bad[0]]}, {j[bad[0]]}) out of range [0, {n})")
    if np.any(i == j):
        raise InputError(f"edge {np.flatnonzero(i == j)[0]}: connects node {i[i == j][0]} to itself")
    if not np.all(np.isfinite(T)):
        raise InputError(f"edge {np.flatnonzero(~np.isfinite(T).all(axis=(1, 2)))[0]}: T is not finite")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise InputError(f"edge {np.flatnonzero(~(np.isfinite(w) & (w >= 0)))[0]}: weight is not finite and >= 0")
    R = T[:, :3, :3]
    bad = non_rigid(T)
    if bad.any():
        raise InputError(f"edge {np.flatnonzero(bad)[0]}: T is not a rigid transform")
    far = np.flatnonzero(np.abs(T[:, :3, 3]).max(axis=1) > _SQUARABLE[1])
    if len(far):  # the objective squares them: overflow warnings, then poses of 1e199
        raise InputError(
            f"edge {far[0]}: translation {np.abs(T[far[0], :3, 3]).max():.3g} beyond what double "
            f"precision can square ({_SQUARABLE[1]:.2g})"
        )
    info = graph.information
    if info is not None:
        info = np.asarray(info, dtype=float)
        if info.shape != (E, 6, 6) or not np.all(np.isfinite(info)):
            raise InputError(f"information must be finite with shape ({E}, 6, 6), got {info.shape}")
        eigenvalues = np.linalg.eigvalsh(0.5 * (info + np.swapaxes(info, 1, 2)))
        bad = eigenvalues[:, 0] <= 0
        if bad.any():
            raise InputError(f"edge {np.flatnonzero(bad)[0]}: information is not positive definite")
        low, high = _SQUARABLE
        bad = np.flatnonzero((eigenvalues[:, 0] < low) | (eigenvalues[:, -1] > high))
        if len(bad):
            e = bad[0]
            raise InputError(
                f"edge {e}: information's eigenvalues {eigenvalues[e, 0]:.3g} to {eigenvalues[e, -1]:.3g} "
                f"leave the range double precision can square ({low:.2g} to {high:.2g}); scale the "
                "graph's information"
            )
    T = T.copy()
    T[:, :3, :3] = project_to_so3(R)  # measured rotations can be off-orthonormal by ~1e-4 (3DMatch)
    return replace(graph, n=n, i=i.astype(np.int64), j=j.astype(np.int64), T=T, weight=w, information=info)


__all__ = ["METHODS", "POLISHES", "synchronize", "checked_graph", "unverified"]
