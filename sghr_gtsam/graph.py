"""Sparse pose graph: overlap scores from global features, then each scan's top-k partners."""

from __future__ import annotations

import numpy as np


def overlap_scores(F: np.ndarray, form: str = "paper") -> np.ndarray:
    """Overlap scores of unit global features ``F`` (N, D); the diagonal is 1.

    ``paper``: ``s_ij = (F_iᵀF_j + 1) / 2``; ``authors``: ``(2 − ‖F_i − F_j‖) / 2`` as the authors' released
    code computes it (same ranking, since ‖F_i − F_j‖² = 2 − 2F_iᵀF_j).
    """
    F32 = np.asarray(F, dtype=np.float32)  # float32 Gram: 4x faster at N = 5000, error ~1e-7 on unit vectors
    G = np.clip(F32 @ F32.T, -1.0, 1.0).astype(np.float64)
    if form == "paper":
        return (G + 1.0) / 2.0
    if form == "authors":
        return (2.0 - np.sqrt(np.maximum(2.0 - 2.0 * G, 0.0))) / 2.0
    raise ValueError(f"unknown score form {form!r} (paper, authors)")


def top_k_edges(scores: np.ndarray, k: int) -> np.ndarray:
    """Edges (E, 2) with i < j: the symmetric union of every scan's ``k`` best-scoring partners.

    Between N·k/2 and N·k pairs (a choice made by both ends counts once), instead of N(N−1)/2.
    Ties break by scan index so the graph is deterministic.
    """
    n = len(scores)
    if n < 2 or k < 1:
        return np.zeros((0, 2), dtype=int)
    k = min(k, n - 1)
    neg = -np.asarray(scores, dtype=float)
    np.fill_diagonal(neg, np.inf)
    # The k-th best score of each row by partial sort (O(N) a row), then every strictly better partner
    # plus the lowest-index ties up to k: the same choice as a stable full sort, without sorting.
    kth = np.partition(neg, k - 1, axis=1)[:, k - 1:k]
    better = neg < kth
    ties = neg == kth
    need = k - better.sum(axis=1)
    chosen = better | ties
    crowded = np.flatnonzero(ties.sum(axis=1) > need)  # rows where ties at the k-th score compete
    chosen[crowded] = better[crowded] | (ties[crowded] & (np.cumsum(ties[crowded], axis=1) <= need[crowded, None]))
    pairs = np.sort(np.stack(np.nonzero(chosen), axis=1), axis=1)
    return np.unique(pairs, axis=0)
