"""Sparse pose graph: overlap scores from global features, then each scan's top-k partners.

All scores come from one float32 Gram matrix ``G = F Fᵀ`` (``gram32``: BLAS ``ssyrk``, half the flops of a
general product, upper triangle mirrored so ``G`` is exactly symmetric), clipped to [−1, 1] and mapped to
float64 by the score form. ``overlap_scores`` (the full matrix), ``top_k_graph`` (edges straight from the
features, never building a float64 N×N matrix) and ``top_k_edges`` on those scores see the same numbers, so
they choose exactly the same edges; near-equal scores are ranked as these float32-derived values rank them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.linalg.blas import ssyrk

FORMS = ("paper", "authors")
_TILE = 128  # tile edge for mirroring the Gram matrix (fits L1/L2 while transposing)
_PAD = 3  # candidates kept per row beyond the k best and the diagonal; more only when ties spill over
_CHUNK = 512  # rows per block of the candidate selection and of the rows that need their full row


def gram32(F: np.ndarray) -> np.ndarray:
    """``F Fᵀ`` (N, N) in float32 by ``ssyrk``; exactly symmetric (one product per pair, mirrored)."""
    F32 = np.ascontiguousarray(F, dtype=np.float32)
    if F32.ndim != 2:
        raise ValueError(f"global features must be (N, D), got shape {F32.shape}")
    n, d = F32.shape
    if n == 0 or d == 0:
        return np.zeros((n, n), dtype=np.float32)
    # F32.T is Fortran-ordered (D, N), so ssyrk reads it without a copy; its (N, N) Fortran result, seen in C
    # order, holds G[i, j] for i >= j. numpy's ``F32 @ F32.T`` makes the same ssyrk call (same bits), then
    # mirrors element by element, which costs ~4x more than these tiles.
    G = ssyrk(1.0, F32.T, trans=1).T
    for i0 in range(0, n, _TILE):
        i1 = min(i0 + _TILE, n)
        for j0 in range(0, i0, _TILE):
            G[j0 : j0 + _TILE, i0:i1] = G[i0:i1, j0 : j0 + _TILE].T
        block = G[i0:i1, i0:i1]
        upper = np.triu_indices(i1 - i0, 1)
        block[upper] = block.T[upper]
    return G


def _check_form(form: str) -> None:
    if form not in FORMS:
        raise ValueError(f"unknown score form {form!r} (paper, authors)")


def scores_from_gram(G: np.ndarray, form: str = "paper") -> np.ndarray:
    """Overlap scores (float64, any shape) from float32 Gram values; monotone non-decreasing in ``G``."""
    _check_form(form)
    x = np.clip(G, -1.0, 1.0).astype(np.float64)
    if form == "paper":
        x += 1.0
        x /= 2.0  # (G + 1) / 2, the same operations in the same order as before, so the same bits
        return x
    x *= 2.0
    np.subtract(2.0, x, out=x)
    np.maximum(x, 0.0, out=x)
    np.sqrt(x, out=x)
    np.subtract(2.0, x, out=x)
    x /= 2.0  # (2 − sqrt(max(2 − 2G, 0))) / 2
    return x


def overlap_scores(F: np.ndarray, form: str = "paper") -> np.ndarray:
    """Overlap scores of unit global features ``F`` (N, D), float64 (N, N); the diagonal is ~1.

    ``paper``: ``s_ij = (F_iᵀF_j + 1) / 2``; ``authors``: ``(2 − ‖F_i − F_j‖) / 2`` as the authors' released
    code computes it (same ranking, since ‖F_i − F_j‖² = 2 − 2F_iᵀF_j). ``F_iᵀF_j`` is the float32 ``gram32``
    value (error ~1e-7 on unit vectors), clipped to [−1, 1]. To choose edges, ``top_k_graph`` gives the same
    edges as ``top_k_edges`` on this matrix without building it.
    """
    _check_form(form)
    return scores_from_gram(gram32(F), form)


def _rowwise_top_k(V: np.ndarray, k: int, key: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Each row's ``k`` best columns (the diagonal excluded) by ``key(V[i, j])``, ties to the lower column: the
    first ``k`` of a stable sort by descending key. Returns (rows, cols), ``k`` per row.

    ``key`` must be monotone non-decreasing (float64 out). ``np.argpartition`` (by blocks of rows, which keeps
    it in cache: 4x faster at N = 5000) takes the ``K = k + 1 + _PAD`` largest raw values of each row; a row is
    settled from them when the key of their smallest is below the row's k-th
    best key (then no other column can reach or tie it). Other rows (ties spilling past ``K``) are solved
    exactly on the full row.
    """
    n = len(V)
    K = min(k + 1 + _PAD, n)
    cols = np.concatenate([np.argpartition(V[r : r + _CHUNK], n - K, axis=1)[:, n - K :] for r in range(0, n, _CHUNK)])
    vals = np.take_along_axis(V, cols, 1)
    rows = np.arange(n)
    by_col = np.argsort(cols, axis=1)
    cols = np.take_along_axis(cols, by_col, 1)
    keys = key(np.take_along_axis(vals, by_col, 1))
    order = np.argsort(-keys, axis=1, kind="stable")  # descending key, then ascending column
    cols = np.take_along_axis(cols, order, 1)
    keys = np.take_along_axis(keys, order, 1)
    valid = cols != rows[:, None]
    rank = np.cumsum(valid, axis=1)
    take = valid & (rank <= k)
    kth = keys[rows, np.argmax(valid & (rank == k), axis=1)]  # k-th best key (>= k valid candidates a row)
    settled = np.ones(n, dtype=bool) if K == n else key(vals.min(axis=1)) < kth
    out_rows, out_cols = [np.repeat(rows[settled], k)], [cols[settled][take[settled]]]
    hard = np.flatnonzero(~settled)
    for c0 in range(0, len(hard), _CHUNK):
        r = hard[c0 : c0 + _CHUNK]
        full = key(V[r])
        better = full > kth[r, None]
        ties = full == kth[r, None]
        better[np.arange(len(r)), r] = False
        ties[np.arange(len(r)), r] = False
        need = k - better.sum(axis=1)
        chosen = better | (ties & (np.cumsum(ties, axis=1) <= need[:, None]))
        i, j = np.nonzero(chosen)
        out_rows.append(r[i])
        out_cols.append(j)
    return np.concatenate(out_rows), np.concatenate(out_cols)


def _union(rows: np.ndarray, cols: np.ndarray, n: int) -> np.ndarray:
    """Pairs (i, j) as sorted unique edges (E, 2), i < j."""
    lo = np.minimum(rows, cols).astype(np.int64)
    hi = np.maximum(rows, cols).astype(np.int64)
    code = np.unique(lo * n + hi)
    return np.stack([code // n, code % n], axis=1)


def top_k_edges(scores: np.ndarray, k: int) -> np.ndarray:
    """Edges (E, 2) with i < j: the symmetric union of every scan's ``k`` best-scoring partners.

    Between N·k/2 and N·k pairs (a choice made by both ends counts once), instead of N(N−1)/2.
    Ties break by scan index (a stable sort of each row) so the graph is deterministic.
    """
    S = np.asarray(scores)
    n = len(S)
    if n < 2 or k < 1:
        return np.zeros((0, 2), dtype=int)
    k = min(k, n - 1)
    if S.dtype not in (np.float32, np.float64):
        S = S.astype(np.float64)  # float32 ranks exactly as its float64 values, so it stays as it is
    S = np.ascontiguousarray(S)
    rows, cols = _rowwise_top_k(S, k, key=lambda v: v.astype(np.float64))
    return _union(rows, cols, n)


def top_k_graph(F: np.ndarray, k: int, form: str = "paper", *, full_scores: bool = False) -> tuple[np.ndarray, ...]:
    """The top-k graph straight from unit global features ``F`` (N, D): ``(edges, edge_scores)``.

    ``edges`` equals ``top_k_edges(overlap_scores(F, form), k)`` and ``edge_scores`` equals
    ``overlap_scores(F, form)[edges[:, 0], edges[:, 1]]``, bit for bit, but only the float32 Gram matrix is
    built (4·N² bytes), not the float64 score matrix. ``full_scores=True`` also returns that matrix, from the
    same Gram product: ``(edges, edge_scores, scores)``.
    """
    _check_form(form)
    G = gram32(F)
    n = len(G)
    if n < 2 or k < 1:
        edges, s = np.zeros((0, 2), dtype=int), np.zeros(0)
    else:
        edges = _union(*_rowwise_top_k(G, min(k, n - 1), key=lambda g: scores_from_gram(g, form)), n)
        s = scores_from_gram(G[edges[:, 0], edges[:, 1]], form)
    if full_scores:
        return edges, s, scores_from_gram(G, form)
    return edges, s


def bridge_components(edges: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """``edges`` (E, 2) plus, if they leave the scans in several connected parts, the best-scoring pair
    between parts until all are joined (Kruskal on the parts: a maximum spanning tree of the parts).

    The union of top-k choices can split a scene into parts that never see each other's partners (a small k,
    or scans in two rooms); a part with no edge to the rest cannot be placed. The bridges are the pairs most
    likely to overlap among the ones not chosen; when even they do not register, the parts stay apart and
    the run says so. Returns the edges, new ones appended, i < j.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n = len(scores)
    if n < 2:
        return edges
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    parts, label = connected_components(graph, directed=False)
    if parts == 1:
        return edges
    a, b = np.triu_indices(n, 1)
    cross = label[a] != label[b]
    a, b = a[cross], b[cross]
    order = np.argsort(-scores[a, b], kind="stable")  # ties: the lower pair index first
    root = np.arange(parts)

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    added = []
    for e in order:
        ra, rb = find(label[a[e]]), find(label[b[e]])
        if ra != rb:
            root[max(ra, rb)] = min(ra, rb)
            added.append((a[e], b[e]))
            if len(added) == parts - 1:
                break
    return np.vstack([edges, np.array(added, dtype=edges.dtype)])
