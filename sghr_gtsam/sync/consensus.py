"""Consensus re-placement: move a scan to where the heaviest group of its edges puts it.

Residual-based reweighting (IRLS, GNC) is local: when a scan's wrong placement is repeated on two or more
of its edges — a repetitive or symmetric room, the paper's Fig. 2 — those edges agree with each other and
with the scan once it sits there, so their residuals are small and they keep their weight; a 90° or 1 m
jump back is out of reach of any descent. This step compares placements instead of residuals. Every edge
``e = (a, s)`` proposes a pose for scan ``s`` from its partner's current pose (``T_a T_as``); proposals within
``max_deg`` and ``max_trans`` of each other agree, and a proposal's support is the initial weight ``w⁰`` of
the edges that agree with it. A scan whose best-supported proposal outweighs its current placement's moves
there (``MARGIN`` more support needed, so near-ties do not pull a scan a descent placed right, and at least
``MIN_AGREEING`` edges must propose the new placement, so one heavy failed registration cannot), most
outweighed first, sweep after sweep until no scan moves or ``MAX_SWEEPS``. Each move raises the total
``w⁰`` of the edges consistent with the poses (a weighted consensus). That consensus is what this step
maximises, not the truth: where a wrong placement outweighs a scan's right edges, the scan goes wrong.

Only scans whose inconsistent edges outweigh their consistent ones can gain by a move; only those are
examined, so a sweep costs a few vectorised passes over the edges plus small per-scan work.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import chdtri

from sghr_gtsam.se3 import inv_T, rotation_angle
from sghr_gtsam.types import PoseGraph

MAX_DEG = 10.0
"""Rotation tolerance (degrees) for an edge to agree with the poses: several times the ~2° error of a good
pairwise registration plus synchronization error, far below the 90° of a symmetric confusion."""
TRANS_FACTOR = 1.0
"""Translation tolerance: the displacement a ``MAX_DEG`` rotation error causes at this many times the median
edge length ‖t_ij‖, so the test needs no scene units (3DMatch: 0.27-0.58 m; wrong placements along a
repeated wall are ~1 m off)."""
MAX_SWEEPS = 10
MARGIN = 0.25
"""A scan moves only when the new placement's support exceeds the current one's by this fraction."""
MIN_AGREEING = 2
"""Edges that must propose a placement (agree on it) before a scan may move there."""


def translation_tolerance(graph: PoseGraph, max_deg: float = MAX_DEG) -> float:
    """``TRANS_FACTOR · radians(max_deg) ·`` median ‖t_ij‖ of the edges with positive weight."""
    used = graph.weight > 0
    length = float(np.median(np.linalg.norm(graph.T[used, :3, 3], axis=1))) if used.any() else 1.0
    return TRANS_FACTOR * np.radians(max_deg) * (length if length > 0 else 1.0)


def edge_residuals(graph: PoseGraph, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each edge's residual transform ``T_ij⁻¹ T_i⁻¹ T_j`` under ``poses`` (E, 4, 4), its rotation angle in
    degrees and its translation's length (E,)."""
    E = inv_T(graph.T) @ inv_T(poses[graph.i]) @ poses[graph.j]
    return E, np.degrees(rotation_angle(E[:, :3, :3])), np.linalg.norm(E[:, :3, 3], axis=1)


def consistent_edges(
    graph: PoseGraph, poses: np.ndarray, max_deg: float = MAX_DEG, max_trans: float | None = None
) -> np.ndarray:
    """(E,) bool: edges with positive weight whose ``T_ij⁻¹ T_i⁻¹ T_j`` is within ``max_deg`` and
    ``max_trans`` (default ``translation_tolerance``) of the identity, or, with ``graph.information``, within
    the edge's own noise (``within_noise``): the fixed tolerances suit registrations good to a few degrees, and
    alone they dropped 55-80 % of the edges of gtsam's clean but noisy grid graphs (σ ≈ 15°), every one of
    them within its own noise at the least-squares optimum."""
    max_trans = translation_tolerance(graph, max_deg) if max_trans is None else max_trans
    E, rot, trans = edge_residuals(graph, poses)
    close = (rot <= max_deg) & (trans <= max_trans)
    if graph.information is not None:
        close |= within_noise(E, graph.information)
    return (graph.weight > 0) & close


NOISE_QUANTILE = 0.999
"""An edge is within its own noise when ``ξᵀ Ω ξ`` is below this quantile of χ²₆ (``ξ`` its residual)."""


def mahalanobis(E: np.ndarray, information: np.ndarray) -> np.ndarray:
    """(E,) ``ξᵀ Ω ξ`` of residual transforms ``E`` (E, 4, 4), ``ξ = [rotation vector, translation]`` (gtsam's
    order, the first-order log): χ²₆-distributed where ``Ω`` states the edge's noise."""
    xi = np.hstack([Rotation.from_matrix(E[:, :3, :3]).as_rotvec(), E[:, :3, 3]])
    return np.einsum("ea,eab,eb->e", xi, information, xi)


def shown_variance_factor(chi2: np.ndarray) -> float:
    """The variance factor ``s² ≥ 1`` that ``ξᵀΩξ`` values (``mahalanobis``) show: their median over χ²₆'s median,
    which a few outliers far off do not move; 1 for none."""
    return max(1.0, float(np.median(chi2)) / _CHI2_6_MEDIAN) if len(chi2) else 1.0


_CHI2_6_MEDIAN = float(chdtri(6, 0.5))


def within_noise(E: np.ndarray, information: np.ndarray) -> np.ndarray:
    """(E,) bool: residual transforms ``E`` (E, 4, 4) with ``ξᵀ Ω ξ ≤ χ²₆(NOISE_QUANTILE)`` (``mahalanobis``)."""
    # χ²₆ quantile from scipy.special: scipy.stats costs about 1 s to import and nothing else on a run needs it.
    return mahalanobis(E, information) <= chdtri(6, 1.0 - NOISE_QUANTILE)


def consensus_placement(
    graph: PoseGraph,
    poses: np.ndarray,
    max_deg: float = MAX_DEG,
    max_trans: float | None = None,
    max_sweeps: int = MAX_SWEEPS,
) -> np.ndarray:
    """``poses`` with every scan moved to its best-supported placement (module doc)."""
    max_trans = translation_tolerance(graph, max_deg) if max_trans is None else max_trans
    poses = poses.copy()
    w, i, j = graph.weight, graph.i, graph.j
    used = np.flatnonzero(w > 0)
    incident = [[] for _ in range(graph.n)]
    for e in used:
        incident[i[e]].append(e)
        incident[j[e]].append(e)
    for _ in range(max_sweeps):
        ok = consistent_edges(graph, poses, max_deg, max_trans)
        signed = np.where(ok, w, -w)
        balance = np.bincount(i, signed, graph.n) + np.bincount(j, signed, graph.n)
        moved = False
        for s in np.flatnonzero(balance < 0)[np.argsort(balance[balance < 0], kind="stable")]:
            moved |= _replace(s, np.array(incident[s]), graph, poses, max_deg, max_trans)
        if not moved:
            break
    return poses


def placement_support(
    graph: PoseGraph, poses: np.ndarray, s: int, edges: np.ndarray, max_deg: float, max_trans: float
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """The placements of scan ``s`` its ``edges`` propose from their partners' ``poses`` (k, 4, 4), the
    support (summed ``w⁰`` of the agreeing proposals) of each, the support of its current pose, which
    proposals agree with the current pose (k,), and how many proposals agree with each (k,)."""
    T = graph.T[edges]
    as_j = graph.j[edges] == s
    partner = np.where(as_j, graph.i[edges], graph.j[edges])
    # T_s = T_a T_as: edge (a, s) carries T_as; edge (s, b) carries T_sb = T_bs⁻¹.
    proposals = poses[partner] @ np.where(as_j[:, None, None], T, inv_T(T))
    candidates = np.concatenate([proposals, poses[s][None]])
    D = inv_T(candidates)[:, None] @ proposals[None]
    agree = (np.degrees(rotation_angle(D[..., :3, :3])) <= max_deg) & (
        np.linalg.norm(candidates[:, None, :3, 3] - proposals[None, :, :3, 3], axis=-1) <= max_trans
    )
    support = agree @ graph.weight[edges]
    return proposals, support[:-1], float(support[-1]), agree[-1], agree[:-1].sum(axis=1)


def _replace(s: int, edges: np.ndarray, graph: PoseGraph, poses: np.ndarray, max_deg: float, max_trans: float) -> bool:
    """Move scan ``s`` (in place) to the proposal of its ``edges`` with the most support, if that beats the
    support of its current pose by ``MARGIN``."""
    proposals, support, current, _, agreeing = placement_support(graph, poses, s, edges, max_deg, max_trans)
    # A placement only one edge proposes is uncorroborated: a lone failed registration with a high weight
    # must not pull a scan away from where the rest of the graph put it.
    support = np.where(agreeing >= MIN_AGREEING, support, 0.0)
    best = int(np.argmax(support))
    if support[best] <= (1.0 + MARGIN) * current:
        return False
    poses[s] = proposals[best]
    return True
