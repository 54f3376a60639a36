"""The synchronization methods SGHR is compared with, on the same ``PoseGraph`` and returning a ``SyncResult``.

Every method starts from the graph's initial weights ``w0`` and multiplies its robust weights into them, so
all of them see the same overlap × inlier-count prior as SGHR; the gtsam and open3d ones get each edge's noise
from ``factor_graph.edge_information`` (the project's polish: ``w0`` / median ``w0`` times a 2° rotation
sigma and the translation sigma it implies). As in ``synchronize``, the result's parts are the connected
parts over the edges a method kept (final weight > 0), each anchored at its first node.

- ``eigse3``: EIGSE3 (Arrigoni et al., SIAM J. Imaging Sci. 2016): the 4 leading eigenvectors of the
  degree-normalised 4N×4N matrix of relative transforms, with IRLS on Cauchy weights of the residuals
  ``‖T_ij − T_i⁻¹T_j‖_F`` (the robust variant of the paper; scale 2.385 × 1.4826 × median residual).
- ``l1_irls``: rotation IRLS for the ℓ1 cost (Chatterjee & Govindu), weights ``1/max(δ, ε)``.
- ``rotavg``: rotation IRLS for the ℓ½ cost (Chatterjee & Govindu, TPAMI 2018), weights ``max(δ, ε)^(-3/2)``.
  Both use the project's spectral rotation solver and finish with weighted least-squares translations.
- ``gnc_tls``: gtsam's graduated non-convexity with the truncated-least-squares loss over
  ``BetweenFactorPose3``, from the spectral estimate (spectral rotations, least-squares translations, ``w0``).
- ``shonan``: gtsam's Shonan averaging of the relative rotations (isotropic, from the rotation block of
  ``edge_information``) from the spectral rotations, then least-squares translations. Not robust: it shows
  what plain certifiable rotation averaging does with outliers.
- ``open3d``: open3d's ``global_optimization`` with its line process (Choi et al. 2015), Levenberg–Marquardt,
  ``edge_prune_threshold`` 0.25, from the spectral estimate; consecutive nodes as certain odometry and every
  other edge uncertain, as open3d's reconstruction system does. ``open3d_all_uncertain``: every edge uncertain
  (SGHR's graphs have no odometry: any edge can be a failed registration).
- ``oracle``: gtsam Levenberg–Marquardt on the true inlier edges only (told by the caller), the reference row.

HARA (Lee & Civera) and LITS (Yew & Lee) have no public code and are not reproduced.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import numpy as np
import scipy.sparse as sp

from sghr_gtsam.errors import InputError
from sghr_gtsam.se3 import inv_T, make_T, project_to_so3
from sghr_gtsam.sync.irls import solve_poses
from sghr_gtsam.sync.rotation import connected_components, rotation_residuals, spectral_rotations, split_components
from sghr_gtsam.sync.translation import solve_translations
from sghr_gtsam.types import PoseGraph, SyncResult

IRLS_ITERS = 50
"""Iteration cap of the IRLS baselines (SGHR's M)."""
IRLS_TOL = 1e-6
"""IRLS stops once no weight moves by more than this fraction of the largest weight."""
EPS = 1e-3
"""Residual floor (radians, 0.06°) of the ℓ1 and ℓ½ weights, which are unbounded at zero residual."""
CAUCHY_C = 2.385
"""Cauchy tuning constant (95 % efficiency under Gaussian noise), in units of the robust residual scale."""
MAD_SCALE = 1.4826
"""Median absolute residual → standard deviation under Gaussian noise."""
RESIDUAL_FLOOR = 1e-9
"""Smallest Cauchy scale: below it the residuals are rounding noise, and weights drawn from them would not
settle."""
OPEN3D_MAX_CORRESPONDENCE = 0.07
"""open3d's reconstruction system, fragment pose graph: 1.4 × its 5 cm voxel (metres)."""
OPEN3D_PREFERENCE = 5.0
"""open3d's reconstruction system: ``preference_loop_closure_registration`` of the fragment pose graph."""
OPEN3D_PRUNE = 0.25
EIGSE3_MAX_NODES = 250
"""Largest connected part EIGSE3 takes: a dense eigendecomposition of 4N×4N an IRLS iteration, up to ``iters`` of
them (about 1 s each at 250 poses; a chain of 500 took 256 s, deaf to SIGTERM inside LAPACK, and 10,000 asked
for 24 GB)."""

# factor_graph (gtsam) and open3d are imported inside the functions that need them: factor_graph imports
# the sync package, which may import this module, and the numpy baselines need neither library.


def l1_irls(graph: PoseGraph, iters: int = IRLS_ITERS) -> SyncResult:
    return _rotation_irls(graph, lambda d: 1.0 / np.maximum(d, EPS), iters)


def rotavg(graph: PoseGraph, iters: int = IRLS_ITERS) -> SyncResult:
    return _rotation_irls(graph, lambda d: np.maximum(d, EPS) ** -1.5, iters)


def eigse3(graph: PoseGraph, iters: int = IRLS_ITERS) -> SyncResult:
    largest = np.bincount(connected_components(graph.n, graph.i, graph.j, graph.weight > 0)).max()
    if largest > EIGSE3_MAX_NODES:
        raise InputError(
            f"eigse3 solves a dense eigenproblem of 4N x 4N: at most {EIGSE3_MAX_NODES:,} poses in a "
            f"connected part, got {largest:,} (use another method)"
        )
    w0 = graph.weight
    w = w0.copy()
    for _ in range(iters):
        poses = _eig_se3(graph, w)
        r = np.linalg.norm(graph.T - inv_T(poses[graph.i]) @ poses[graph.j], axis=(1, 2))
        scale = max(MAD_SCALE * np.median(r[w0 > 0]), RESIDUAL_FLOOR)
        w, previous = w0 / (1.0 + (r / (CAUCHY_C * scale)) ** 2), w
        if _converged(w, previous):
            break
    return _result(graph, _eig_se3(graph, w), w)


def gnc_tls(graph: PoseGraph, iters: int = 100) -> SyncResult:
    from sghr_gtsam.factor_graph import edge_information, gnc_tls_poses

    poses, gnc_weights = gnc_tls_poses(
        graph, solve_poses(graph, graph.weight), edge_information(graph, graph.weight), iters
    )
    return _result(graph, poses, graph.weight * gnc_weights)


def shonan(graph: PoseGraph, iters: int = 10) -> SyncResult:
    """``iters``: the highest rank p of the Riemannian staircase (gtsam's default ``max_p``)."""
    from sghr_gtsam.factor_graph import edge_information, shonan_rotations

    init = spectral_rotations(graph.n, graph.i, graph.j, graph.T[:, :3, :3], graph.weight)
    R = shonan_rotations(graph, init, edge_information(graph, graph.weight), iters)
    t = solve_translations(graph.n, graph.i, graph.j, R, graph.T[:, :3, 3], graph.weight)
    return _result(graph, make_T(R, t), graph.weight.copy())


def oracle(graph: PoseGraph, inliers: np.ndarray, iters: int = 100) -> SyncResult:
    """Levenberg–Marquardt on the edges ``inliers`` marks (the project's polish), from their spectral estimate."""
    from sghr_gtsam.factor_graph import edge_information, polish

    w = np.where(inliers, graph.weight, 0.0)
    component = connected_components(graph.n, graph.i, graph.j, w > 0)
    poses = polish(graph, solve_poses(graph, w), edge_information(graph, w), component, max_iters=iters).poses
    return _result(graph, poses, w)


def open3d_line_process(graph: PoseGraph, iters: int = 100, odometry: bool = True) -> SyncResult:
    """open3d's global optimization from the spectral estimate; each edge's information is the project's
    (``factor_graph.edge_information``), whose translation block sets open3d's line-process scale.
    ``odometry``: edges between consecutive nodes are certain (never pruned); otherwise all are uncertain."""
    import open3d as o3d
    import psutil

    from sghr_gtsam.factor_graph import edge_information

    needed, available = 2 * (6 * graph.n) ** 2 * 8, psutil.virtual_memory().available  # its dense 6N x 6N system
    if needed > available:  # open3d's own std::bad_alloc names no cause
        raise InputError(
            f"open3d's global optimization holds a dense system of 6N x 6N: {graph.n:,} poses need about "
            f"{needed / 2**30:.1f} GB, {available / 2**30:.1f} GB are available (use another method)"
        )
    reg = o3d.pipelines.registration
    information = edge_information(graph, graph.weight)  # gtsam's order [rotation, translation] is open3d's too
    pose_graph = reg.PoseGraph()
    for T in solve_poses(graph, graph.weight):
        pose_graph.nodes.append(reg.PoseGraphNode(T))
    for e in np.flatnonzero(graph.weight > 0):
        a, b = int(graph.i[e]), int(graph.j[e])
        # open3d's edge maps its source into its target: T_ij takes scan j (source) into scan i (target).
        uncertain = not (odometry and abs(a - b) == 1)
        pose_graph.edges.append(reg.PoseGraphEdge(b, a, graph.T[e], information[e], uncertain=uncertain))
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=OPEN3D_MAX_CORRESPONDENCE,
        edge_prune_threshold=OPEN3D_PRUNE,
        preference_loop_closure=OPEN3D_PREFERENCE,
        reference_node=0,
    )
    criteria = reg.GlobalOptimizationConvergenceCriteria()
    criteria.max_iteration = iters
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(pose_graph, reg.GlobalOptimizationLevenbergMarquardt(), criteria, option)
    poses = np.stack([np.asarray(node.pose) for node in pose_graph.nodes])
    # Pruned edges are gone from the optimised graph; the kept ones carry their line-process value.
    confidence = {(e.target_node_id, e.source_node_id): e.confidence for e in pose_graph.edges}
    factor = np.array([confidence.get((int(a), int(b)), 0.0) for a, b in zip(graph.i, graph.j)])
    return _result(graph, poses, graph.weight * factor)


# --- shared ------------------------------------------------------------------------------------------------


def _rotation_irls(graph: PoseGraph, robust: Callable[[np.ndarray], np.ndarray], iters: int) -> SyncResult:
    """Spectral rotations re-solved with ``w0 · robust(δ)``, then least-squares translations."""
    n, i, j, R_ij = graph.n, graph.i, graph.j, graph.T[:, :3, :3]
    w0 = graph.weight
    w, R = w0.copy(), None
    for _ in range(iters):
        R = spectral_rotations(n, i, j, R_ij, w, init=R)
        w, previous = w0 * robust(rotation_residuals(R, i, j, R_ij)), w
        if _converged(w, previous):
            break
    return _result(graph, solve_poses(graph, w, init=R), w)


def _converged(w: np.ndarray, previous: np.ndarray) -> bool:
    return bool(np.abs(w - previous).max() <= IRLS_TOL * max(w.max(), np.finfo(float).tiny))


def _eig_se3(graph: PoseGraph, w: np.ndarray) -> np.ndarray:
    """EIGSE3: ``M_i = T_i⁻¹`` satisfies ``M_i M_j⁻¹ = T_ij``, so the stacked ``M`` (4N×4) spans the eigenvalue-1
    eigenspace of ``D⁻¹Z`` (Z: blocks ``w T_ij`` at (i, j) and ``w T_ij⁻¹`` at (j, i)). Per connected part;
    a dense eigendecomposition, O((4N)³): parts of up to ``EIGSE3_MAX_NODES``."""
    poses = np.tile(np.eye(4), (graph.n, 1, 1))
    keep = w > 0
    labels = connected_components(graph.n, graph.i, graph.j, keep)
    for nodes, edges, li, lj in split_components(labels, graph.i, graph.j, keep):
        n = len(nodes)
        we = w[edges][:, None, None]
        Z = _block_matrix(n, li, lj, we * graph.T[edges], we * inv_T(graph.T[edges]))
        degree = np.bincount(li, w[edges], n) + np.bincount(lj, w[edges], n)
        # Dense: Krylov solvers (ARPACK) miss vectors of the 4-fold eigenvalue, and the benchmark's parts
        # have at most a few hundred nodes.
        values, vectors = np.linalg.eig((sp.diags(np.repeat(1.0 / degree, 4)) @ Z).toarray())
        vectors = vectors[:, np.argsort(-values.real)[:4]]
        # A real basis of the (real) eigenspace, whatever complex combination the solver returned.
        U = np.linalg.svd(np.hstack([vectors.real, vectors.imag]), full_matrices=False)[0][:, :4]
        M = (U @ np.linalg.inv(U[:4])).reshape(n, 4, 4)  # gauge: the part's first node at the identity
        M = M / M[:, 3:, 3:]
        poses[nodes] = inv_T(make_T(project_to_so3(M[:, :3, :3]), M[:, :3, 3]))
    return poses


def _block_matrix(n: int, i: np.ndarray, j: np.ndarray, B_ij: np.ndarray, B_ji: np.ndarray) -> sp.csr_matrix:
    """Sparse 4n×4n matrix with the 4×4 blocks ``B_ij`` at (i, j) and ``B_ji`` at (j, i)."""
    r = np.repeat(np.arange(4), 4)
    c = np.tile(np.arange(4), 4)
    rows = np.concatenate([(4 * i)[:, None] + r, (4 * j)[:, None] + r]).ravel()
    cols = np.concatenate([(4 * j)[:, None] + c, (4 * i)[:, None] + c]).ravel()
    vals = np.concatenate([B_ij.reshape(-1, 16), B_ji.reshape(-1, 16)]).ravel()
    return sp.csr_matrix((vals, (rows, cols)), shape=(4 * n, 4 * n))


def _result(graph: PoseGraph, poses: np.ndarray, weights: np.ndarray) -> SyncResult:
    """Anchor every connected part over the edges the method kept (final weight > 0) at its first node, as
    ``synchronize`` does, and score the residuals."""
    component = connected_components(graph.n, graph.i, graph.j, weights > 0)
    poses = poses.copy()
    for c in np.unique(component):
        nodes = np.flatnonzero(component == c)
        poses[nodes] = inv_T(poses[nodes[0]])[None] @ poses[nodes]
    residual = rotation_residuals(poses[:, :3, :3], graph.i, graph.j, graph.T[:, :3, :3])
    return SyncResult(poses=poses, weights=weights, residual_deg=np.degrees(residual), component=component)


BASELINES: dict[str, Callable[..., SyncResult]] = {
    "eigse3": eigse3,
    "l1_irls": l1_irls,
    "rotavg": rotavg,
    "gnc_tls": gnc_tls,
    "shonan": shonan,
    "open3d": open3d_line_process,
    "open3d_all_uncertain": partial(open3d_line_process, odometry=False),
}
"""Every baseline with the signature ``fn(graph, iters=...)`` (``oracle`` also needs the inlier mask)."""
