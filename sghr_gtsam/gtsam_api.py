"""The public gtsam API: a registration as a ``gtsam.NonlinearFactorGraph`` and ``gtsam.Values`` a SLAM stack
can extend, re-optimize and query for covariances.

- ``to_gtsam(result)`` (or ``to_gtsam(graph, poses)``): one ``BetweenFactorPose3`` per edge the result rests
  on, keys of the caller's choosing (default ``gtsam.symbol('x', k)`` for scan ``k`` of ``result.names``),
  the edges' own information (``"information"``, from each registration's residuals, see
  ``registration.information``) or SE-Sync's isotropic precisions (``"isotropic"``), and a robust kernel
  (``KERNELS``); a run's information scaled by its ``calibration`` to what its errors bear out, so that factors
  of one's own with honest σ stand beside it. No prior: the caller anchors the graph (a prior, GNSS, odometry).
- ``optimize(factors, values, kernel=...)``: the project's polish (Levenberg–Marquardt with the same
  stopping rule and ordering), or gtsam GNC with a truncated-least-squares loss for ``kernel="tls"``.
- ``marginal_covariances(factors, values, keys)``: 6×6 covariances from ``gtsam.Marginals``, in gtsam's
  tangent order [rotation, translation] at each pose (right perturbation ``T exp(ξ)``).
- ``pose_covariances(result)``: the same for a run, with the world scan (the first of the largest part) held
  fixed and the run's ``calibration`` applied (the ``variance_factor`` of the graph's loops and the edges a scan
  shares its errors with); what the results folder and the recording show.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import gtsam
import networkx as nx
import numpy as np
from scipy.special import chdtri  # chi2.ppf(q, df) is chdtri(df, 1 - q); scipy.stats costs ~1 s to import

from sghr_gtsam.config import KERNELS, NOISE_MODELS
from sghr_gtsam.factor_graph import _ABSOLUTE_TOL, _METIS_NODES, anchor_prior, edge_information
from sghr_gtsam.io.g2o import check_information, isotropic_information
from sghr_gtsam.io.poses import check_rigid
from sghr_gtsam.se3 import project_to_so3
from sghr_gtsam.sync import checked_graph
from sghr_gtsam.types import InputError, PoseGraph

if TYPE_CHECKING:
    from sghr_gtsam.registration.pairwise import PairResult
    from sghr_gtsam.result import RunResult

KERNEL_THRESHOLD = float(np.sqrt(chdtri(6, 1 - 0.99)))
"""Whitened residual norm where Huber turns linear and Cauchy halves a factor's weight: the 99 % point of a
6-dof residual under the edge's own noise model, the inlier threshold gtsam's GNC uses by default for TLS."""
RELATIVE_TOL = 1e-6
"""LM stops when an iteration decreases the error by less than this fraction (the pipeline polish's rule)."""

Keys = Callable[[int], int] | Sequence[int] | None


def _key_table(keys: Keys, nodes: Sequence[int], n: int) -> dict[int, int]:
    """Node → gtsam key for ``nodes`` of an ``n``-node graph; ``InputError`` unless the keys are distinct integers
    in gtsam's range (a sequence: one per node)."""
    if keys is None:
        return {k: gtsam.symbol("x", k) for k in nodes}
    if not callable(keys):
        keys = list(keys)
        if len(keys) != n:
            raise InputError(f"keys: {len(keys)} given for {n} nodes")
    table = {k: keys(k) if callable(keys) else keys[k] for k in nodes}
    odd = [
        v
        for v in table.values()
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not 0 <= v < 2**64
    ]
    if odd:
        raise InputError(f"keys must be integers in [0, 2^64), got {odd[0]!r}")
    if len(set(table.values())) != len(table):
        raise InputError("keys: two nodes have the same key")
    return {k: int(v) for k, v in table.items()}


def _mask(edges: np.ndarray, count: int) -> np.ndarray:
    """``edges`` as a boolean mask over ``count`` edges; an index array or a mask of another length is refused
    (numpy would read the one as a mask, or fail deep inside on the other)."""
    mask = np.asarray(edges)
    if mask.dtype != bool or mask.shape != (count,):
        raise InputError(f"edges must be a boolean mask of shape ({count},), got {mask.dtype} {mask.shape}")
    return mask


def _selected(graph: PoseGraph, edges: np.ndarray | None) -> tuple[PoseGraph, np.ndarray, list[int]]:
    """``graph`` checked, the mask of its ``edges`` (default: weight > 0) and the nodes they join. The pose graph
    check (``sync.checked_graph``) asks positive definite information; gtsam takes semi-definite (zero: no
    measurement), so the information is checked apart."""
    checked = checked_graph(replace(graph, information=None))
    if graph.information is not None:
        checked = replace(checked, information=check_information(graph.information, checked.num_edges))
    chosen = checked.weight > 0 if edges is None else _mask(edges, checked.num_edges)
    return checked, chosen, sorted(set(checked.i[chosen].tolist()) | set(checked.j[chosen].tolist()))


def _poses(poses: np.ndarray | None, n: int, nodes: Sequence[int]) -> np.ndarray:
    """``poses`` (n, 4, 4) with those of ``nodes`` rigid (projected onto SO(3), as ``checked_graph`` does the
    edges'); the others may be anything (NaN: an unregistered scan)."""
    if poses is None or np.shape(poses) != (n, 4, 4):
        raise InputError(f"needs poses of shape ({n}, 4, 4), got {np.shape(poses)}")
    poses = np.array(poses, dtype=float)
    check_rigid(poses[nodes], "pose", labels=nodes)
    poses[nodes, :3, :3] = project_to_so3(poses[nodes, :3, :3])
    return poses


def check_choice(name: str, value: str, allowed: Sequence[str]) -> None:
    """One-line ``InputError`` unless ``value`` is one of ``allowed``."""
    if value not in allowed:
        raise InputError(f"{name} must be one of {', '.join(allowed)}; got {value!r}")


def noise_model(information: np.ndarray, kernel: str = "none") -> gtsam.noiseModel.Base:
    """Gaussian noise with ``information`` (6, 6), wrapped in the Huber or Cauchy m-estimator (scale
    ``KERNEL_THRESHOLD``) when asked; ``"tls"`` and ``"none"`` give the plain Gaussian (TLS acts in ``optimize``).
    ``InputError`` unless ``information`` is finite, symmetric and positive semi-definite."""
    check_choice("kernel", kernel, KERNELS)
    return _noise_model(check_information(information), kernel)


def _noise_model(information: np.ndarray, kernel: str) -> gtsam.noiseModel.Base:
    """``noise_model`` of a checked ``information`` and ``kernel``."""
    gaussian = gtsam.noiseModel.Gaussian.Information(information)
    if kernel == "huber":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(KERNEL_THRESHOLD), gaussian)
    if kernel == "cauchy":
        return gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Cauchy.Create(KERNEL_THRESHOLD), gaussian)
    return gaussian


def _edges_of(result: RunResult) -> tuple[np.ndarray, list[int]]:
    """(E,) mask of the edges a run's poses rest on (kept by synchronization, both ends registered) and the
    registered scans."""
    nodes = result.registered
    placed = np.zeros(len(result.names), dtype=bool)
    placed[nodes] = True
    g = result.graph
    return (result.sync.weights > 0) & placed[g.i] & placed[g.j], nodes


def graph_information(graph: PoseGraph, edges: np.ndarray, noise: str = "information") -> np.ndarray:
    """(E, 6, 6) information of ``graph``'s edges in ``edges`` (zero elsewhere): their own (``"information"``)
    or SE-Sync's isotropic precisions (``"isotropic"``). A graph without information gets the polish's
    default (``factor_graph.edge_information`` with unit weights: a 2° rotation sigma, not calibrated)."""
    check_choice("noise", noise, NOISE_MODELS)
    edges = _mask(edges, graph.num_edges)
    info = graph.information if graph.information is not None else edge_information(graph, edges.astype(float))
    info = np.where(edges[:, None, None], info, 0.0)
    if noise == "isotropic":  # of the chosen edges alone: the others' may be zero (a failed registration)
        try:
            info[edges] = isotropic_information(info[edges])
        except np.linalg.LinAlgError:
            raise InputError(
                "isotropic noise needs each chosen edge's rotation and translation information invertible"
            ) from None
    return info


def to_gtsam(
    source: RunResult | PoseGraph,
    poses: np.ndarray | None = None,
    *,
    keys: Keys = None,
    noise: str = "information",
    kernel: str = "none",
    edges: np.ndarray | None = None,
    calibrated: bool = True,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The factor graph and initial values of a run (``RunResult``: its kept edges among registered scans, its
    final poses) or of a ``PoseGraph`` with ``poses`` (N, 4, 4) (default ``edges``: those with weight > 0).

    ``keys``: node index → gtsam key, as a function or a sequence; default ``gtsam.symbol('x', k)``. Factor
    ``f`` of the graph is the ``f``-th selected edge in the graph's order. Values hold every node of a selected
    edge (and, for a run, every registered scan). ``edges``: a boolean mask over the graph's edges. A
    ``PoseGraph`` is checked (``sync.checked_graph``; information finite, symmetric, positive semi-definite) and
    the poses of the values must be rigid: ``InputError`` otherwise. (A run's graph is the pipeline's own.)
    A run's factors carry its ``calibrated_information``: the information its poses were solved with, scaled by one
    number to what its errors bear out, so that factors of one's own with honest σ weigh what they should beside
    them and its poses stay the optimum; ``calibrated=False``: the information as measured, the scale
    ``graph.g2o`` holds.
    """
    if isinstance(source, PoseGraph):
        graph, chosen, nodes = _selected(source, edges)
    else:
        graph, poses = source.graph, source.poses if poses is None else poses
        chosen, nodes = _edges_of(source)
        if edges is not None:
            chosen &= _mask(edges, graph.num_edges)
        if calibrated:
            graph, noise = replace(graph, information=calibrated_information(source, noise=noise)), "information"
    return _factor_graph(graph, _poses(poses, graph.n, nodes), chosen, nodes, keys, noise, kernel)


def _factor_graph(
    graph: PoseGraph, poses: np.ndarray, chosen: np.ndarray, nodes: Sequence[int], keys: Keys, noise: str, kernel: str
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """``to_gtsam`` of a checked graph, its poses, the chosen edges and the nodes that get values."""
    check_choice("kernel", kernel, KERNELS)
    key = _key_table(keys, nodes, graph.n)
    information = graph_information(graph, chosen, noise)
    factors = gtsam.NonlinearFactorGraph()
    for e in np.flatnonzero(chosen):
        factors.add(
            gtsam.BetweenFactorPose3(
                key[int(graph.i[e])],
                key[int(graph.j[e])],
                gtsam.Pose3(graph.T[e]),
                _noise_model(information[e], kernel),
            )
        )
    values = gtsam.Values()
    for k in nodes:
        values.insert(key[k], gtsam.Pose3(poses[k]))
    return factors, values


def _lm_params(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> gtsam.LevenbergMarquardtParams:
    """The polish's LM settings: its stopping rule, and METIS ordering on large connected graphs."""
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(RELATIVE_TOL)
    params.setAbsoluteErrorTol(_ABSOLUTE_TOL * factors.size())
    params.setMaxIterations(100)
    if values.size() >= _METIS_NODES:
        G = nx.Graph()
        G.add_nodes_from(values.keys())
        for f in range(factors.size()):
            k = factors.at(f).keys()
            G.add_edges_from(zip(k[:-1], k[1:]))
        if nx.is_connected(G):
            params.setOrderingType("METIS")
    return params


def optimize(
    factors: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    *,
    kernel: str = "none",
    known_inliers: Sequence[int] | None = None,
) -> gtsam.Values:
    """Optimize from ``values``: Levenberg–Marquardt as the pipeline's polish, or with ``kernel="tls"`` gtsam GNC
    (truncated least squares, inlier threshold χ²₆ at 0.99, the polish's LM inside). ``known_inliers``: factor
    indices GNC must not reject; default every factor that is not a ``BetweenFactorPose3`` (priors, GNSS).
    Huber and Cauchy live in the factors' noise models (``to_gtsam(kernel=...)``), so LM handles them."""
    check_choice("kernel", kernel, KERNELS)
    _check_keys(factors, values)
    params = _lm_params(factors, values)
    if kernel != "tls":
        return gtsam.LevenbergMarquardtOptimizer(factors, values, params).optimize()
    if known_inliers is None:
        known_inliers = [f for f in range(factors.size()) if not isinstance(factors.at(f), gtsam.BetweenFactorPose3)]
    outside = [f for f in known_inliers if not (isinstance(f, (int, np.integer)) and 0 <= f < factors.size())]
    if outside:
        raise InputError(f"known_inliers: {outside[0]!r} is not a factor index of [0, {factors.size()})")
    gnc = gtsam.GncLMParams(params)
    gnc.setLossType(gtsam.GncLossType.TLS)
    gnc.setKnownInliers(list(known_inliers))
    return gtsam.GncLMOptimizer(factors, values, gnc).optimize()


def _check_keys(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> None:
    """``InputError`` unless every key of ``factors`` has a value (gtsam would raise deep inside)."""
    missing = {k for f in range(factors.size()) for k in factors.at(f).keys() if not values.exists(k)}
    if missing:
        raise InputError(
            f"{len(missing)} key(s) of the factors have no value, e.g. {gtsam.DefaultKeyFormatter(min(missing))}"
        )


def marginal_covariances(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, keys: Sequence[int]) -> np.ndarray:
    """(K, 6, 6) marginal covariance of each Pose3 key, [rotation (rad), translation] at the pose. The graph must
    be anchored (a prior or another absolute factor), else the covariances are unbounded and gtsam raises."""
    _check_keys(factors, values)
    absent = [k for k in keys if not values.exists(int(k))]
    if absent:
        raise InputError(f"marginal_covariances: key {gtsam.DefaultKeyFormatter(int(absent[0]))} has no value")
    marginals = gtsam.Marginals(factors, values)
    return np.stack([marginals.marginalCovariance(int(k)) for k in keys]) if len(keys) else np.zeros((0, 6, 6))


def variance_factor(result: RunResult, *, noise: str = "information") -> float:
    """The a posteriori variance factor ``σ̂₀² = Σ_e r_eᵀ Ω_e r_e / (6 (E − N + 1))`` of a run's kept edges at its
    poses (E edges among N registered scans; ``r_e`` the edge's residual, ``Ω_e`` the information the poses were
    solved with): 1 when the edges' residuals are as large as their information says, above 1 when the loops of
    the graph show them overconfident. NaN without redundancy (a tree of edges)."""
    return _variance_factor(*to_gtsam(result, noise=noise, calibrated=False), len(result.registered))


def _variance_factor(factors: gtsam.NonlinearFactorGraph, values: gtsam.Values, nodes: int) -> float:
    """``variance_factor`` of the edge factors ``factors`` among ``nodes`` scans at ``values``."""
    dof = 6 * (factors.size() - nodes + 1)
    return 2.0 * factors.error(values) / dof if dof > 0 else float("nan")


def calibrated_information(result: RunResult, *, noise: str = "information", shared: bool = True) -> np.ndarray:
    """(E, 6, 6) information of a run's edges scaled to what its errors bear out (zero on the edges its poses do
    not rest on): what ``to_gtsam(result)`` hands gtsam. The information the poses were solved with (``noise``)
    times ``calibration``'s one number (``shared`` as there), so that its optimum stays the run's poses."""
    chosen = _edges_of(result)[0]
    return graph_information(result.graph, chosen, noise) * calibration(result, noise=noise, shared=shared)


def calibration(result: RunResult, *, noise: str = "information", shared: bool = True) -> float:
    """The one factor, at most 1, that makes a run's edge information (as in its graph, ``noise``) as large as its
    errors: ``1 / (max(1, σ̂₀²) · d)``. Neither number is fitted to any scene:
    - ``σ̂₀²``, the variance factor of the graph's loops (``variance_factor``): the edges' own errors, as large as
      the loops show them;
    - ``d``, the largest number of kept edges at one scan: the edges of a scan share that scan's errors (its
      sampling, its shape) with a correlation nothing measures (a loop passes a scan on two of its edges, where the
      errors they share cancel). Covariance intersection is the fusion that stays consistent whatever that
      correlation: the information of the estimates combined with weights summing to at most one. ``1 / d`` is the
      largest weight, one for all edges (so that the optimum does not move), whose sum is at most one at every scan.
    On simulated scenes (independent range noise) ``d`` makes σ a few times too large; on real scans it is what
    covers their errors (``benchmarks/bench_covariance.py --real``). ``shared=False``: ``d = 1``, the variance
    factor alone. 1 without kept edges."""
    chosen, nodes = _edges_of(result)
    if not chosen.any():
        return 1.0
    factor = _variance_factor(*to_gtsam(result, noise=noise, calibrated=False), len(nodes))
    degree = np.bincount(np.r_[result.graph.i[chosen], result.graph.j[chosen]]).max() if shared else 1
    return 1.0 / (max(factor, 1.0) * degree) if np.isfinite(factor) else 1.0 / degree


def pose_covariances(
    result: RunResult, *, noise: str = "information", grid: bool = True, shared: bool = True
) -> np.ndarray:
    """(N, 6, 6) covariance of each scan's pose relative to the world scan (which gets zeros), from the kept
    edges' information with the directions their geometry leaves free bounded by the overlap alone
    (``PairResult.bounded``) and, with ``grid``, each refined edge's
    dependence on its grid added to its covariance (``PairResult.grid``), scaled by its ``calibration``
    (``shared`` as there); NaN for unregistered scans. Without bounds and grid terms, the marginals of
    ``to_gtsam(result)``."""
    result = _reported(result, grid)
    information = calibrated_information(result, noise=noise, shared=shared)
    factors, values = to_gtsam(replace(result, graph=replace(result.graph, information=information)), calibrated=False)
    nodes = result.registered
    out = np.full((len(result.names), 6, 6), np.nan)
    anchor = int(np.flatnonzero(result.sync.component == 0)[0])
    factors.add(
        gtsam.PriorFactorPose3(gtsam.symbol("x", anchor), gtsam.Pose3(result.poses[anchor]), _anchor_prior(information))
    )
    out[nodes] = marginal_covariances(factors, values, [gtsam.symbol("x", k) for k in nodes])
    out[anchor] = 0.0
    return out


def _reported(result: RunResult, grid: bool) -> RunResult:
    """``result`` with each edge's ``_reported_information`` in its graph."""
    if result.graph.information is not None and any(
        p.bounded is not None or (grid and p.grid is not None) for p in result.pairs
    ):
        information = np.stack(
            [_reported_information(p, info, grid) for p, info in zip(result.pairs, result.graph.information)]
        )
        result = replace(result, graph=replace(result.graph, information=information))
    return result


def _reported_information(pair: PairResult, information: np.ndarray, grid: bool) -> np.ndarray:
    """The information ``pose_covariances`` gives an edge: ``bounded`` (free directions bounded by the overlap)
    or its ``information`` in the graph (a pair without any has a placeholder there), and with ``grid`` the inverse
    of its covariance plus ``grid gridᵀ`` (Sherman-Morrison)."""
    info = information if pair.bounded is None else pair.bounded
    if grid and pair.grid is not None:
        w = info @ pair.grid
        info = info - np.outer(w, w) / (1.0 + pair.grid @ w)
    return info


def _anchor_prior(information: np.ndarray) -> gtsam.noiseModel.Isotropic:
    """``factor_graph.anchor_prior`` of the edges' ``information`` (none: a run of one scan)."""
    return anchor_prior(float(np.abs(information).max(initial=0.0)))


def sigmas(covariances: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scalar summaries of (N, 6, 6) covariances: the rotation σ in degrees and the translation σ in scene
    units, each the root of the largest eigenvalue of its 3×3 block (the longest axis of the ellipsoid); NaN
    where the covariance is."""
    covariances = np.asarray(covariances, dtype=float)
    if covariances.ndim != 3 or covariances.shape[1:] != (6, 6):
        raise InputError(f"sigmas: covariances must be (N, 6, 6), got {covariances.shape} (of one: C[None])")
    rot, trans = np.full(len(covariances), np.nan), np.full(len(covariances), np.nan)
    ok = np.isfinite(covariances).all(axis=(1, 2))
    rot[ok] = np.degrees(np.sqrt(np.maximum(np.linalg.eigvalsh(covariances[ok, :3, :3])[:, -1], 0.0)))
    trans[ok] = np.sqrt(np.maximum(np.linalg.eigvalsh(covariances[ok, 3:, 3:])[:, -1], 0.0))
    return rot, trans


def repolish(
    graph: PoseGraph,
    poses: np.ndarray,
    edges: np.ndarray,
    component: np.ndarray,
    *,
    noise: str = "information",
    kernel: str = "none",
) -> np.ndarray:
    """``poses`` re-optimized over ``graph``'s ``edges`` (a boolean mask) with ``noise`` and ``kernel``
    (``optimize``), every part of ``component`` (N,) held at its first node's pose by a stiff prior; nodes on no
    edge stay as they are. Bad input (``to_gtsam``'s checks, a ``component`` of another shape) is an
    ``InputError``."""
    graph, chosen, nodes = _selected(graph, edges)
    component = np.asarray(component)
    if component.shape != (graph.n,):
        raise InputError(f"repolish: component must have shape ({graph.n},), got {component.shape}")
    poses = _poses(poses, graph.n, nodes)
    factors, values = _factor_graph(graph, poses, chosen, nodes, lambda k: k, noise, kernel)
    information = graph_information(graph, chosen, noise)
    prior = _anchor_prior(information)
    for a in np.unique(component, return_index=True)[1]:
        if values.exists(int(a)):
            factors.add(gtsam.PriorFactorPose3(int(a), gtsam.Pose3(poses[a]), prior))
    solved = optimize(factors, values, kernel=kernel)
    out = poses.copy()
    for k in solved.keys():
        out[k] = solved.atPose3(k).matrix()
    return out
