"""Spectral rotation synchronization (SGHR step 3; the eigenvector relaxation of Singer 2011, Arrigoni et al. 2016).

With ``R_ij = R_iᵀ R_j`` the weighted connection Laplacian ``L = D ⊗ I₃ − W`` (blocks ``W_ij = w R_ij``,
``W_ji = w R_ijᵀ``) annihilates the stacked matrix ``X`` with blocks ``X_i = R_iᵀ``; its three eigenvectors of
smallest eigenvalue span ``X Q`` for some 3×3 ``Q``, so each 3×3 block, transposed and projected onto SO(3),
gives ``R_i`` up to one global rotation, fixed by anchoring the first node of each connected part at identity.

Eigen-solver, chosen by measurement on 2 cores. ARPACK ``which='SA'`` needs seconds on chains with loop
closures. Shift-invert is fast on chains, but the sparse LU of the 3n×3n Laplacian fills in on
well-connected graphs (4 s for a 15000×15000 k-nearest-neighbour Laplacian, minutes on random graphs), and
ARPACK needs many solves when the bottom eigenvalues cluster. Used here: LOBPCG started from a rotation
estimate (the previous IRLS iterate, else a maximum-weight spanning tree) and preconditioned with
``D (L_s + σI)⁻¹ Dᵀ`` — ``L_s`` the n×n scalar weighted Laplacian, ``D`` the estimate's rotations — which is
L's inverse when the edges agree with the estimate, so it converges in 3-9 iterations once outliers are
down-weighted. While outliers still carry weight the spectrum is flat and that preconditioner fails; then
the LU of L itself preconditions (and drives the fallback, block inverse iteration). Within IRLS the factorizations are
reused across iterations while they keep working. Parts under ``DENSE_NODES`` use dense ``eigh``.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree
from scipy.sparse.csgraph import connected_components as _cc
from scipy.sparse.linalg import LinearOperator, lobpcg, splu

from sghr_gtsam.se3 import project_to_so3

DENSE_NODES = 128
"""Parts with fewer nodes use a dense eigendecomposition: a 90×90 ``eigh`` takes under a millisecond, while
from ~150×150 a multithreaded BLAS on a busy machine makes it 10-50× slower than warm LOBPCG (measured)."""
_DENSE_STEPS = 4
"""Inverse-iteration steps a dense part gets from a warm start before falling back to ``eigh``."""
_SHIFT = 1e-6
"""Preconditioner / inverse-iteration shift, relative to the mean weighted degree: it only has to make the
singular Laplacian invertible, and a small shift amplifies the wanted bottom eigenspace."""
TOL = 1e-9
"""Default LOBPCG residual tolerance, relative to the largest weighted degree."""
_MAXITER = 20
"""LOBPCG iterations per attempt; a good preconditioner needs 3-9."""
_RESTARTS = 2
"""Attempts with the scalar preconditioner, each from the rotations of the previous attempt."""
_PROBE = 5
"""Iterations the scalar preconditioner gets right after the exact one was needed."""
_SLACK = 1
"""A cached factorization gets the preconditioner applications of its best solve so far (at most ``_PROBE``)
plus this many, and is dropped once it needs more: a fresh factorization costs about 2.5 applications
(5,000 scans), less than a stale one soon loses (measured: a cache kept until it needed 2× its fresh count
took 13 applications an iteration by the end of IRLS, a fresh one 2-3)."""


def connected_components(n: int, i: np.ndarray, j: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Label of each node's connected part over the edges where ``keep`` is true.

    Labels are ordered by part size, largest first (0), ties broken by the smallest node index, so the
    labelling does not depend on the edge order.
    """
    # The CSR arrays built directly: a COO matrix's conversion costs more than the search at IRLS sizes.
    a, b = i[keep], j[keep]
    order = np.argsort(a, kind="stable")
    A = sp.csr_matrix((np.ones(len(a)), b[order], np.searchsorted(a[order], np.arange(n + 1))), shape=(n, n))
    count, raw = _cc(A, directed=False)
    size = np.bincount(raw, minlength=count)
    first = np.full(count, n)
    np.minimum.at(first, raw, np.arange(n))
    order = np.lexsort((first, -size))
    rank = np.empty(count, dtype=int)
    rank[order] = np.arange(count)
    return rank[raw]


def split_components(labels: np.ndarray, i: np.ndarray, j: np.ndarray, keep: np.ndarray):
    """Yield ``(nodes, edges, local_i, local_j)`` for every part with at least one kept edge.

    ``nodes`` is sorted, so ``nodes[0]`` (local index 0) is the part's anchor.
    """
    local = np.empty(len(labels), dtype=int)
    node_order = np.argsort(labels, kind="stable")
    node_bounds = np.searchsorted(labels[node_order], np.arange(labels.max() + 2))
    kept = np.flatnonzero(keep)
    edge_order = kept[np.argsort(labels[i[kept]], kind="stable")]
    edge_bounds = np.searchsorted(labels[i[edge_order]], np.arange(labels.max() + 2))
    for c in range(labels.max() + 1):
        edges = edge_order[edge_bounds[c] : edge_bounds[c + 1]]
        if len(edges) == 0:
            continue
        nodes = node_order[node_bounds[c] : node_bounds[c + 1]]
        local[nodes] = np.arange(len(nodes))
        yield nodes, edges, local[i[edges]], local[j[edges]]


def laplacian_map(n: int, i: np.ndarray, j: np.ndarray, R: np.ndarray, dense: bool = False):
    """The weighted connection Laplacian of edges ``(i, j, R_ij)`` as a linear map of the weights: ``K`` with
    ``K @ w`` its entries (blocks ``−w R_ij`` at (i, j), ``−w R_ijᵀ`` at (j, i), the weighted degree on the
    diagonal). ``dense``: ``K`` gives the 3n×3n array row by row; else ``(K, indices, indptr)``, ``K @ w``
    being the data of the CSR matrix. Within IRLS only the weights change: the map is built once."""
    e = len(i)
    r = np.repeat(np.arange(3), 3)
    c = np.tile(np.arange(3), 3)
    d = np.arange(3)
    rows = np.concatenate(
        [
            ((3 * i)[:, None] + r).ravel(),
            ((3 * j)[:, None] + r).ravel(),
            ((3 * i)[:, None] + d).ravel(),
            ((3 * j)[:, None] + d).ravel(),
        ]
    )
    cols = np.concatenate(
        [
            ((3 * j)[:, None] + c).ravel(),
            ((3 * i)[:, None] + c).ravel(),
            ((3 * i)[:, None] + d).ravel(),
            ((3 * j)[:, None] + d).ravel(),
        ]
    )
    vals = np.concatenate([-R.reshape(-1), -np.swapaxes(R, 1, 2).reshape(-1), np.ones(6 * e)])
    edge = np.concatenate(
        [np.repeat(np.arange(e), 9), np.repeat(np.arange(e), 9), np.repeat(np.arange(e), 3), np.repeat(np.arange(e), 3)]
    )
    flat = rows * (3 * n) + cols
    if dense:
        return sp.csc_matrix((vals, (flat, edge)), shape=(9 * n * n, e))
    keys, position = np.unique(flat, return_inverse=True)
    K = sp.csr_matrix((vals, (position, edge)), shape=(len(keys), e))
    return K, (keys % (3 * n)).astype(np.int32), np.searchsorted(keys // (3 * n), np.arange(3 * n + 1)).astype(np.int32)


def connection_laplacian(
    n: int, i: np.ndarray, j: np.ndarray, R: np.ndarray, w: np.ndarray, laplacian=None
) -> sp.csc_matrix:
    """Sparse 3n×3n weighted connection Laplacian of edges ``(i, j, R_ij, w)``; ``laplacian``: their
    ``laplacian_map`` if already built."""
    K, indices, indptr = laplacian_map(n, i, j, R) if laplacian is None else laplacian
    # The CSR arrays read as CSC give the transpose, L itself: scipy's CSC product with the 3 columns
    # LOBPCG iterates is 1.5× faster than CSR's (15,000 × 15,000: 0.9 against 1.4 ms), and splu takes CSC.
    return sp.csc_matrix((K @ w, indices, indptr), shape=(3 * n, 3 * n))


FACTOR_FLOPS = 1e9
"""``factor_spd`` solves by conjugate gradients where a direct factorization would cost more than this
(``sync.fill.direct_cost``): 4,000 poses with 16,000 random loop closures took 2 s per factorization of their
scalar Laplacian, 20,000 with 80,000 would take minutes each and gigabytes (benchmarks/bench_sync_scaling.py)."""
FILL_CHECK_SIZE = 2000
"""Matrices smaller than this are always factorized: their fill cannot cost much, and the estimate is skipped."""
_CG_TOL = 1e-10
_CG_ITERS = 5000
_judged: dict[int, tuple[int, bool]] = {}  # size -> (stored entries, too costly) of the last matrix of that size judged


def factor_spd(A: sp.spmatrix):
    """A solver of a symmetric positive definite matrix (``.solve(B)``): sparse LU with a symmetric fill-reducing
    order and no pivoting (2-4× faster than SuperLU's defaults on 3-D neighbourhood graphs), or, where its fill
    would be too costly (``FACTOR_FLOPS``), Jacobi-preconditioned conjugate gradients."""
    A = sp.csc_matrix(A)
    if A.shape[0] >= FILL_CHECK_SIZE and _heavy(A):
        return _ConjugateGradients(A)
    return splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


def _heavy(A: sp.csc_matrix) -> bool:
    """Whether a direct factorization of ``A`` costs more than ``FACTOR_FLOPS``. The estimate takes seconds on the
    largest graphs and IRLS factorizes one graph's Laplacian many times, its edges reweighted and some dropped: a
    matrix of the same size with stored entries within ``_SAME_GRAPH`` of the last one of that size judged gets its
    answer. Remembered by size, as the rotations' and the scalar Laplacians (3N and N) alternate."""
    size, entries = A.shape[0], A.nnz
    if size in _judged and abs(entries - _judged[size][0]) <= _SAME_GRAPH * entries:
        return _judged[size][1]
    from sghr_gtsam.sync.fill import direct_cost

    upper = sp.triu(A, 1).tocoo()
    heavy = direct_cost(size, upper.row, upper.col, dof=1) > FACTOR_FLOPS
    if len(_judged) >= _JUDGED_SIZES:
        _judged.clear()
    _judged[size] = (entries, heavy)
    return heavy


_SAME_GRAPH = 0.1
"""``_heavy``: matrices of one size whose stored entries differ by at most this fraction are one graph's."""
_JUDGED_SIZES = 8
"""``_heavy`` remembers the matrices of at most this many sizes (one graph's parts)."""


class _ConjugateGradients:
    """``factor_spd``'s solver where factorizing costs too much: conjugate gradients, column by column."""

    def __init__(self, A: sp.csc_matrix):
        self.A = A.tocsr()
        self.M = sp.diags(1.0 / A.diagonal())

    def solve(self, B: np.ndarray) -> np.ndarray:
        from scipy.sparse.linalg import cg

        columns = B.reshape(B.shape[0], -1)
        out = np.empty_like(columns, dtype=float)
        for c in range(columns.shape[1]):
            out[:, c] = cg(self.A, columns[:, c], M=self.M, rtol=_CG_TOL, atol=0.0, maxiter=_CG_ITERS)[0]
        return out.reshape(B.shape)


def scalar_laplacian(n: int, i: np.ndarray, j: np.ndarray, w: np.ndarray, shift: float = 0.0) -> sp.csc_matrix:
    """Weighted graph Laplacian ``D − W`` (n×n) plus ``shift · I``."""
    degree = np.bincount(i, w, n) + np.bincount(j, w, n)
    W = sp.csc_matrix((np.concatenate([w, w]), (np.concatenate([i, j]), np.concatenate([j, i]))), shape=(n, n))
    return (sp.diags(degree + shift) - W).tocsc()


def dense_connection_laplacian(
    n: int, i: np.ndarray, j: np.ndarray, R: np.ndarray, w: np.ndarray, laplacian=None
) -> np.ndarray:
    """``connection_laplacian`` as a dense array (small parts); ``laplacian``: their dense ``laplacian_map``."""
    K = laplacian_map(n, i, j, R, dense=True) if laplacian is None else laplacian
    return (K @ w).reshape(3 * n, 3 * n)


def spectral_rotations(
    n: int,
    i: np.ndarray,
    j: np.ndarray,
    R: np.ndarray,
    w: np.ndarray,
    init: np.ndarray | None = None,
    cache: dict | None = None,
    tol: float = TOL,
) -> np.ndarray:
    """Absolute rotations ``R_i`` (n, 3, 3) from relative rotations ``R_ij = R_iᵀR_j`` with weights ``w``.

    Edges with ``w <= 0`` are ignored; every connected part is solved on its own and its first node is
    the identity (a node without edges too). ``init``: optional (n, 3, 3) rotation estimate (the previous
    IRLS iterate) to start and precondition the eigen-solver. ``cache``: a dict the caller keeps across
    calls on one graph (IRLS) so that a part reuses its preconditioner factorization while it still
    works. Both change the speed, not the result. ``tol``: LOBPCG residual tolerance relative to the
    largest weighted degree (parts of ``DENSE_NODES`` or more).
    """
    out = np.tile(np.eye(3), (n, 1, 1))
    cache = {} if cache is None else cache
    # Within IRLS the kept edges rarely change between iterations: reuse the parts and, while a part keeps its
    # nodes, its solver state: the Laplacian map over every edge inside it (the dropped ones have weight 0),
    # its last eigenvectors and preconditioner.
    keep = w > 0
    mask = keep.tobytes()
    if cache.get("mask") != mask:
        labels = connected_components(n, i, j, keep)
        cache["mask"] = mask
        cache["parts"] = list(split_components(labels, i, j, labels[i] == labels[j]))
        states = cache.get("states", {})
        cache["states"] = {key: states.get(key, {}) for key in (nodes.tobytes() for nodes, *_ in cache["parts"])}
    for nodes, edges, li, lj in cache["parts"]:
        m = len(nodes)
        state = cache["states"][nodes.tobytes()]
        if "map" not in state:
            state["map"] = laplacian_map(m, li, lj, R[edges], dense=m < DENSE_NODES)
        if m < DENSE_NODES:
            V = _dense_bottom(
                dense_connection_laplacian(m, li, lj, None, w[edges], state["map"]),
                None if init is None else init[nodes],
                tol,
            )
        else:
            V = _sparse_bottom(
                connection_laplacian(m, li, lj, None, w[edges], state["map"]),
                li,
                lj,
                R[edges],
                w[edges],
                None if init is None else init[nodes],
                state,
                tol,
            )
        Rs = _blocks_to_rotations(V)
        out[nodes] = Rs[0].T @ Rs
    return out


def _dense_bottom(L: np.ndarray, init: np.ndarray | None = None, tol: float = TOL) -> np.ndarray:
    """Bottom eigenvectors of a dense Laplacian. From an estimate ``init`` (the previous IRLS iterate):
    block inverse iteration with one Cholesky factorization, which converges at the rate λ₃/λ₄ (tiny once
    outliers are down-weighted) in 1-3 steps, 10× cheaper than ``eigh``; otherwise, or if it stalls, ``eigh``."""
    if init is not None:
        m = len(L)
        degree = L.diagonal()
        A = L.copy()
        A.flat[:: m + 1] += _SHIFT * degree.mean()
        # LAPACK directly: scipy's wrappers cost as much as the 180×180 factorization itself. A is symmetric,
        # so its transpose is the column-major array LAPACK factors in place.
        factor, info = scipy.linalg.lapack.dpotrf(A.T, lower=1, clean=0, overwrite_a=1)
        if info == 0:
            V, done = _inverse_iteration(
                L,
                lambda Y: scipy.linalg.lapack.dpotrs(factor, Y, lower=1)[0],
                np.swapaxes(init, 1, 2).reshape(-1, 3),
                tol * degree.max(),
                _DENSE_STEPS,
            )
            if done:
                return V
    try:
        return scipy.linalg.eigh(L, subset_by_index=[0, 2], check_finite=False)[1]
    except np.linalg.LinAlgError:  # LAPACK's subset driver (evr) fails on some near-degenerate matrices
        return np.linalg.eigh(L)[1][:, :3]


def _blocks_to_rotations(V: np.ndarray) -> np.ndarray:
    """Rotations ``Qᵀ R_i`` from a basis ``V`` (3n, 3) of the bottom eigenspace."""
    blocks = V.reshape(-1, 3, 3)
    # The basis is defined up to sign: a negatively oriented one would project to reflections, so flip
    # it to the orientation the majority of blocks agrees on.
    if np.sum(np.linalg.det(blocks)) < 0:
        blocks = -blocks
    return project_to_so3(np.swapaxes(blocks, 1, 2))


def _lobpcg(L: sp.csc_matrix, V: np.ndarray, precondition, tol: float, maxiter: int) -> tuple[np.ndarray, bool]:
    M = LinearOperator(L.shape, matvec=precondition, matmat=precondition, dtype=float)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # non-convergence is detected below from the residual
        vals, V = lobpcg(L, V, M=M, largest=False, tol=tol, maxiter=maxiter)
    return V, bool(np.linalg.norm(L @ V - V * vals, axis=0).max() <= tol)


def _conjugated(factor, est: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """``D (L_s + σI)⁻¹ Dᵀ Y`` with ``D = blockdiag(est_iᵀ)``: L's inverse if the edges agreed with ``est``."""
    n, k = len(est), Y.shape[1]
    Z = factor.solve((est @ Y.reshape(n, 3, k)).reshape(n, 3 * k)).reshape(n, 3, k)
    return (np.swapaxes(est, 1, 2) @ Z).reshape(3 * n, k)


def _sparse_bottom(
    L: sp.csc_matrix,
    i: np.ndarray,
    j: np.ndarray,
    R: np.ndarray,
    w: np.ndarray,
    init: np.ndarray | None,
    state: dict,
    tol: float,
) -> np.ndarray:
    """Bottom eigenvectors by preconditioned LOBPCG. ``state`` (kept by the caller across IRLS iterations for
    this part) holds the last eigenvectors (``"V"``, the start when ``init`` is given: closer to the new ones
    than ``init``'s rotations) and a factorization that still works (``"factor"``: kind, factor, fewest
    preconditioner applications it needed)."""
    n = L.shape[0] // 3
    degree = np.bincount(i, w, n) + np.bincount(j, w, n)
    shift = _SHIFT * degree.mean()
    tol = tol * degree.max()
    if init is None:
        positive = w > 0
        est = spanning_tree_rotations(n, i[positive], j[positive], R[positive], w[positive])
    else:
        est = init
    V = state["V"] if init is not None and "V" in state else np.swapaxes(est, 1, 2).reshape(3 * n, 3)

    def attempt(kind: str, factor, maxiter: int) -> tuple[bool, int]:
        nonlocal V
        calls = 0

        def precondition(Y: np.ndarray) -> np.ndarray:
            nonlocal calls
            calls += 1
            return factor.solve(Y) if kind == "exact" else _conjugated(factor, est, Y)

        V, done = _lobpcg(L, V, precondition, tol, maxiter)
        if done:
            state["V"] = V
        return done, calls

    # 1. The factorization of an earlier IRLS iteration (the weights change little between iterations),
    # kept while it converges as fast as it did at its best.
    previous = state.pop("factor", None)
    if previous is not None:
        kind, factor, best = previous
        done, calls = attempt(kind, factor, min(best, _PROBE) + _SLACK)
        if done:
            if calls <= best + _SLACK:
                state["factor"] = (kind, factor, min(best, calls))
            return V
    # 2. The scalar Laplacian seen through the estimated rotations: cheap, and exact when the edges agree.
    # After an exact factorization was needed, only probe it briefly: outliers may still have weight.
    probe = previous is not None and previous[0] == "exact"
    scalar = factor_spd(scalar_laplacian(n, i, j, w, shift))
    for _ in range(1 if probe else _RESTARTS):
        done, calls = attempt("scalar", scalar, _PROBE if probe else _MAXITER)
        if done:
            state["factor"] = ("scalar", scalar, calls)
            return V
        est = _blocks_to_rotations(V)  # a better estimate makes a better preconditioner
    # 3. Frustrated graphs (outliers with weight) are far from L_s ⊗ I: precondition with L itself.
    exact = factor_spd(L + shift * sp.eye(3 * n))
    done, calls = attempt("exact", exact, 4 * _MAXITER)
    if done:
        state["factor"] = ("exact", exact, calls)
        return V
    return _inverse_iteration(L, exact.solve, V, tol, 4 * _MAXITER)[0]


def _inverse_iteration(L, solve, V: np.ndarray, tol: float, steps: int) -> tuple[np.ndarray, bool]:
    """Block inverse iteration from ``V`` with ``solve`` (``(L + σI)⁻¹``) and a Rayleigh-Ritz step each time, until
    the residual is within ``tol`` or ``steps`` run out; the basis and whether it converged. Unlike ARPACK's
    shift-invert, the sparse solver's former fallback, which restarts from random vectors with a seed it keeps
    between calls, it is deterministic: where the bottom eigenvalues cluster (a group hung on edges far lighter than
    the rest) ARPACK returned a different basis of the cluster at every call, and so different rotations (a
    1000-scan graph at 60 % outliers: poses 7 m apart from one run to the next). From the LOBPCG iterate, the basis
    stays near the rotation estimate within such a cluster."""
    for _ in range(steps):
        V = np.linalg.qr(solve(V))[0]
        LV = L @ V
        vals, U = np.linalg.eigh(V.T @ LV)  # Rayleigh-Ritz in the 3-d subspace
        V, LV = V @ U, LV @ U
        if np.linalg.norm(LV - V * vals, axis=0).max() <= tol:
            return V, True
    return V, False


def spanning_tree_rotations(n: int, i: np.ndarray, j: np.ndarray, R: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rotations chained from node 0 along a maximum-weight spanning tree (a connected part is assumed)."""
    a, b = np.minimum(i, j), np.maximum(i, j)
    # One edge per node pair, the heaviest, so the sparse matrix below holds no summed duplicates.
    order = np.argsort(-w, kind="stable")
    keys, first = np.unique(a[order] * n + b[order], return_index=True)
    best = order[first]
    tree = minimum_spanning_tree(sp.csr_matrix((1.0 / w[best], (a[best], b[best])), shape=(n, n)))
    bfs, pred = breadth_first_order(tree, 0, directed=False, return_predecessors=True)
    child = bfs[1:]
    parent = pred[child]
    edge = best[np.searchsorted(keys, np.minimum(parent, child) * n + np.maximum(parent, child))]
    step = np.where((i[edge] == parent)[:, None, None], R[edge], np.swapaxes(R[edge], 1, 2))
    out = np.tile(np.eye(3), (n, 1, 1))
    for v, p, S in zip(child, parent, step):
        out[v] = out[p] @ S
    return out


def rotation_residuals(R: np.ndarray, i: np.ndarray, j: np.ndarray, R_ij: np.ndarray) -> np.ndarray:
    """Angle (radians) of ``R_ijᵀ R_iᵀ R_j`` for every edge: how far the poses disagree with it."""
    # trace(R_ijᵀ R_iᵀ R_j) = Σ (R_i R_ij) ∘ R_j: one batched product instead of two.
    c = (np.einsum("eab,eab->e", R[i] @ R_ij, R[j]) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))
