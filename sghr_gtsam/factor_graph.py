"""Everything gtsam: the Levenberg–Marquardt polish of synchronized poses (SGHR step 4).

Every kept edge becomes ``BetweenFactorPose3(i, j, Pose3(T_ij), Gaussian.Information(Ω'_e))``; its error is
``½ r_eᵀ Ω'_e r_e`` with ``r_e = Log(T_ij⁻¹ T_i⁻¹ T_j)`` in gtsam's tangent order [rotation, translation].

Weight → noise (``edge_information``): an edge with its own information (``PoseGraph.information``: calibrated
from the registration's residuals, or a g2o file's) enters with exactly that, ``Ω'_e = Ω_e``, so the polished
poses are the maximum-likelihood ones under it and the graph written to graph.g2o is the one they optimize
(scaling it by ``w⁰`` as well counted the registration's support twice, and moved the optimum 0.05-0.15° from
what ``gtsam.readG2o`` + LM on the exported graph gives on object scans and 3DMatch fragments). Without one,
``Ω'_e = (w_e / ŵ) · diag(σ_r⁻² I₃, σ_t⁻² I₃)``, ``w_e`` the weight the caller gives the edge and ``ŵ`` the
median of the nonzero ones (so a typical edge keeps the base information and the scale of the problem does not
depend on the weights' units). Edges with ``w_e = 0`` get no factor.

``synchronize`` passes the initial weight ``w⁰`` (overlap × inliers) of the edges it kept — those
consistent with the poses after the robust stages (default polish ``"robust"``), or those the history
reweighting kept (``"lm"``) — and 0 for the others: on synthetic graphs with 20-30 % outliers this lands
within 0.1-0.5° (worst scan) of least squares on the true inliers, while the history weights themselves as
precisions (they span e^(−2 × residual in degrees)) leave it 0.8-1.4° further off. The history weights
decide which edges enter; the noise model of an edge that enters is its own information (``w⁰``-scaled
default without one). GNC
(``gnc_tls_poses``, the robust polish's middle stage) gets every edge with this same mapping.

Each connected part gets a prior on its anchor (its first node), which pins the gauge without moving the
optimum: the between factors are invariant to a common transform, so at the optimum the prior's residual
is zero.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np

from sghr_gtsam.errors import InputError, one_line
from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.sync.rotation import connected_components, rotation_residuals
from sghr_gtsam.types import IterationRecord, PoseGraph

ROT_SIGMA_DEG = 2.0
"""Base rotation sigma of an edge without information: a typical pairwise-registration error."""
_PRIOR_SCALE = 1e4
"""Anchor prior precision relative to the largest edge precision: stiff, yet well conditioned."""
_METIS_NODES = 500
"""From this many poses, a connected graph is eliminated in METIS order: 1.2-2× faster LM iterations than
COLAMD at 5000 scans (measured). gtsam's METIS ordering crashes on some disconnected graphs, hence only
connected ones."""
_PCG_ITERS = 1000
_PCG_TOL = 1e-10
"""Conjugate gradients (``iterative``) stop at this residual relative to the right-hand side: LM's own stopping
rule (``relative_tol`` of the error, 1e-9 for method "lm") needs steps at least that exact."""
_ABSOLUTE_TOL = 1e-12
"""LM also stops when the error decreases by less than this per factor (an error is ~3 per edge at the
noise level), so that noise-free graphs, whose error is ~1e-26, do not iterate on rounding noise."""


DIRECT_FLOPS = 3e9
"""Above this estimated cost of one direct solve of LM's linear system (``sync.fill.direct_cost``), ``polish``
solves it by conjugate gradients, block-Jacobi preconditioned, instead. Loop closures between far-apart poses leave an
elimination no small separators (the fill of uniformly random ones grows as N³): 1,000 poses with 4,000 random
closures (1.3e10 flops) took 7-19 s per LM iteration by Cholesky on a busy 2-core machine, 0.1 s by PCG, to the
same error (benchmarks/bench_sync_scaling.py). Where separators stay small, as along a trajectory, the direct solve
is fast and exact: the pose-graph benchmarks need at most 6e8 (sphere_bignoise_vertex3), bench_sync_speed's scenes
1.2e9 (5,000 scans over a floor), and keep it; its 5,000 scans filling a cube (2.3e10) do not."""


def edge_information(
    graph: PoseGraph, weights: np.ndarray, *, rot_sigma_deg: float = ROT_SIGMA_DEG, trans_sigma: float | None = None
) -> np.ndarray:
    """(E, 6, 6) information of every edge for the polish: ``Ω_e`` where ``w_e > 0`` with the graph's own
    information, else ``(w_e / ŵ) · diag(σ_r⁻², σ_t⁻²)`` (module doc).

    Without ``graph.information``: ``σ_r = rot_sigma_deg`` and ``σ_t`` defaults to ``σ_r`` (radians) times the
    median ‖t_ij‖ of the kept edges — the displacement a rotation error of ``σ_r`` causes at a typical
    partner — so the default is free of the scene's units.
    """
    kept = weights > 0
    if not kept.any():
        return np.zeros((graph.num_edges, 6, 6))
    scale = np.where(kept, weights / np.median(weights[kept]), 0.0)
    if graph.information is not None:
        return np.where(kept[:, None, None], graph.information, 0.0)
    sigma_r = np.radians(rot_sigma_deg)
    if trans_sigma is None:
        length = float(np.median(np.linalg.norm(graph.T[kept, :3, 3], axis=1)))
        trans_sigma = sigma_r * (length if length > 0 else 1.0)
    base = np.diag(np.r_[np.full(3, sigma_r**-2), np.full(3, trans_sigma**-2)])
    return scale[:, None, None] * base


def _values(poses: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    for k, T in enumerate(poses):
        values.insert(k, gtsam.Pose3(T))
    return values


def _poses(values: gtsam.Values) -> np.ndarray:
    flat = gtsam.utilities.extractPose3(values)  # rows sorted by key: R row-major, then t
    return make_T(flat[:, :9].reshape(-1, 3, 3), flat[:, 9:])


def _between_factors(graph: PoseGraph, information: np.ndarray) -> gtsam.NonlinearFactorGraph:
    factors = gtsam.NonlinearFactorGraph()
    for e in np.flatnonzero(np.any(information != 0, axis=(1, 2))):
        noise = gtsam.noiseModel.Gaussian.Information(information[e])
        factors.add(gtsam.BetweenFactorPose3(int(graph.i[e]), int(graph.j[e]), gtsam.Pose3(graph.T[e]), noise))
    return factors


def graph_error(graph: PoseGraph, poses: np.ndarray, information: np.ndarray) -> float:
    """gtsam's error ``Σ_e ½ r_eᵀ Ω_e r_e`` of the between factors at ``poses`` (edges with Ω_e = 0 skipped).

    With ``Ω_e = diag(2κ, 2κ, 2κ, τ, τ, τ)`` this is half the SE-Sync objective to second order in the
    residuals (gtsam measures rotation residuals along the manifold, SE-Sync by chords).
    """
    return float(_between_factors(graph, information).error(_values(poses)))


@dataclass
class PolishResult:
    """The polished poses, gtsam's error before and after, and one record per LM iteration."""

    poses: np.ndarray  # (N, 4, 4), every part re-anchored so its first node is the identity
    initial_error: float
    final_error: float
    converged: bool
    history: list[IterationRecord] = field(default_factory=list)


def anchor_prior(peak: float) -> gtsam.noiseModel.Isotropic:
    """The noise model of a part's anchor prior, for edges whose largest information entry is ``peak`` (0: no
    edge): ``_PRIOR_SCALE`` times it, at least 1."""
    return gtsam.noiseModel.Isotropic.Precision(6, _PRIOR_SCALE * max(peak, 1.0))


def polish(
    graph: PoseGraph,
    poses: np.ndarray,
    information: np.ndarray,
    component: np.ndarray,
    *,
    weights: np.ndarray | None = None,
    max_iters: int = 100,
    relative_tol: float = 1e-6,
    iterative: bool = False,
    on_iteration: Callable[[IterationRecord], None] | None = None,
) -> PolishResult:
    """Levenberg–Marquardt from ``poses`` over the edges with nonzero ``information`` (see module doc).

    ``component``: (N,) part labels; the first node of each part gets the anchor prior. One
    ``IterationRecord`` (stage ``"lm"``, ``cost`` = gtsam error) per LM iteration; ``weights`` is only copied
    into the records. Stops when an iteration decreases the error by less than ``relative_tol`` of it (or by
    a negligible absolute amount). ``iterative``: LM's linear systems solved by conjugate gradients
    (``DIRECT_FLOPS``), not by Cholesky.
    """
    # gtsam's LM damps by an absolute λ (1e-5 to start) and stops on an absolute change of the error: information
    # far below 1 (other units: all of it 1e-12 of a metre graph's) left it at its start. Scaled by a power of two
    # (exact) the optimum is the same; the errors are reported at the graph's own scale.
    peak = float(np.abs(information).max())
    scale = 2.0 ** -np.floor(np.log2(peak)) if 0.0 < peak < 1.0 else 1.0
    factors = _between_factors(graph, information if scale == 1.0 else scale * information)
    anchors = np.unique(component, return_index=True)[1]
    prior = anchor_prior(scale * peak)
    for a in anchors:
        factors.add(gtsam.PriorFactorPose3(int(a), gtsam.Pose3(poses[a]), prior))
    params = gtsam.LevenbergMarquardtParams()
    if iterative:
        params.setLinearSolverType("ITERATIVE")
        pcg = gtsam.PCGSolverParameters()
        pcg.preconditioner = gtsam.BlockJacobiPreconditionerParameters()
        pcg.maxIterations, pcg.epsilon_rel, pcg.epsilon_abs = _PCG_ITERS, _PCG_TOL, 0.0
        params.setIterativeParams(pcg)
    elif len(anchors) == 1 and graph.n >= _METIS_NODES:
        params.setOrderingType("METIS")
    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, _values(poses), params)
    record_weights = np.zeros(graph.num_edges) if weights is None else weights
    initial = previous = error = optimizer.error() / scale
    history: list[IterationRecord] = []
    converged = False
    current = poses
    for k in range(1, max_iters + 1):
        optimizer.iterate()
        error = optimizer.error() / scale
        current = _poses(optimizer.values())
        record = IterationRecord(
            stage="lm",
            iteration=k,
            poses=current,
            weights=record_weights.copy(),
            residual_deg=np.degrees(rotation_residuals(current[:, :3, :3], graph.i, graph.j, graph.T[:, :3, :3])),
            cost=error,
        )
        history.append(record)
        if on_iteration is not None:
            on_iteration(record)
        if gtsam.checkConvergence(relative_tol, _ABSOLUTE_TOL * factors.size(), 0.0, scale * previous, scale * error):
            converged = True
            break
        previous = error
    # The stiff but finite priors leave the anchors a hair off their start: re-anchor every part exactly.
    # (one product for every node: a loop over the parts took minutes where 100,000 poses had no edge)
    a = anchors[component]
    current = poses[a] @ inv_T(current[a]) @ current
    return PolishResult(
        poses=current, initial_error=float(initial), final_error=float(error), converged=converged, history=history
    )


# --- baselines (sghr_gtsam.sync.baselines) ---------------------------------------------------------------


def gnc_tls_poses(
    graph: PoseGraph, init: np.ndarray, information: np.ndarray, iters: int
) -> tuple[np.ndarray, np.ndarray]:
    """gtsam GNC (TLS loss, default inlier threshold: χ²₆ at 0.99) over the edges with nonzero
    ``information``, from ``init``; ``iters`` caps each inner Levenberg–Marquardt run. Returns the poses
    and the (E,) GNC weights (0 for edges left out)."""
    factors = _between_factors(graph, information)
    kept = np.any(information != 0, axis=(1, 2))
    edges = np.flatnonzero(kept)  # the factors' order
    component = connected_components(graph.n, graph.i, graph.j, kept)
    anchors = np.unique(component, return_index=True)[1]
    for a in anchors:  # the gauge: priors GNC is told are inliers
        factors.add(gtsam.PriorFactorPose3(int(a), gtsam.Pose3(init[a]), gtsam.noiseModel.Constrained.All(6)))
    lm = gtsam.LevenbergMarquardtParams()
    lm.setMaxIterations(iters)
    params = gtsam.GncLMParams(lm)  # GNC's own outer-iteration cap stays at its default (100)
    params.setLossType(gtsam.GncLossType.TLS)
    params.setKnownInliers(list(range(len(edges), len(edges) + len(anchors))))
    optimizer = gtsam.GncLMOptimizer(factors, _values(init), params)
    poses = _poses(optimizer.optimize())
    weights = np.zeros(graph.num_edges)
    weights[edges] = np.asarray(optimizer.getWeights())[: len(edges)]
    return poses, weights


def shonan_rotations(graph: PoseGraph, init: np.ndarray, information: np.ndarray, max_p: int) -> np.ndarray:
    """gtsam Shonan averaging of the relative rotations of the edges with nonzero ``information`` (isotropic
    noise from the mean of its rotation block), from ``init`` (n, 3, 3), climbing the staircase to rank
    ``max_p``; when no rank certifies a global optimum, the rounded rank-``max_p`` solution. Nodes on no such
    edge keep ``init`` (Shonan numbers its unknowns by the measurements: a node without one failed it)."""
    edges = np.flatnonzero(np.any(information != 0, axis=(1, 2)))
    nodes = np.unique(np.concatenate([graph.i[edges], graph.j[edges]]))
    index = np.full(graph.n, -1)
    index[nodes] = np.arange(len(nodes))
    precision = np.trace(information[edges, :3, :3], axis1=1, axis2=2) / 3.0
    measurements = [
        gtsam.BinaryMeasurementRot3(
            int(index[graph.i[e]]),
            int(index[graph.j[e]]),
            gtsam.Rot3(graph.T[e, :3, :3]),
            gtsam.noiseModel.Isotropic.Precision(3, float(p)),
        )
        for e, p in zip(edges, precision)
    ]
    params = gtsam.ShonanAveragingParameters3(gtsam.LevenbergMarquardtParams.CeresDefaults())
    averaging = gtsam.ShonanAveraging3(measurements, params)
    Q = gtsam.Values()
    for k, node in enumerate(nodes):
        Q.insert(k, gtsam.SOn.FromMatrix(init[node]))
    # gtsam's run() throws when max_p is reached uncertified; this is its loop, keeping the last solution.
    try:
        for p in range(3, max_p + 1):
            Q = averaging.tryOptimizingAt(p, Q)
            min_eigenvalue, min_eigenvector = averaging.computeMinEigenVector(Q)
            if min_eigenvalue >= params.getOptimalityThreshold() or p == max_p:
                break
            Q = averaging.initializeWithDescent(p + 1, Q, min_eigenvector, min_eigenvalue)
    except RuntimeError as e:  # its eigensolver, on precisions far apart (measured: 1 and 1e140 in one loop)
        raise InputError(
            f"Shonan averaging failed ({one_line(e)}) on rotation precisions from {precision.min():.3g} "
            f"to {precision.max():.3g}: try another method"
        ) from None
    rounded = averaging.roundSolution(Q)
    R = np.array(init, dtype=float)
    R[nodes] = np.stack([rounded.atRot3(k).matrix() for k in range(len(nodes))])
    return R
