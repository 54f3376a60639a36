"""Sparse pose graph: overlap scores from global features, then each scan's top-k partners."""

from __future__ import annotations

import numpy as np


def overlap_scores(F: np.ndarray, form: str = "paper") -> np.ndarray:
    """Overlap scores of unit global features ``F`` (N, D); the diagonal is 1.

    ``paper``: ``s_ij = (F_iᵀF_j + 1) / 2``; ``authors``: ``(2 − ‖F_i − F_j‖) / 2`` as the authors' released
    code computes it (same ranking, since ‖F_i − F_j‖² = 2 − 2F_iᵀF_j).
    """
    G = np.clip(F @ F.T, -1.0, 1.0)
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
    S = scores.astype(float).copy()
    np.fill_diagonal(S, -np.inf)
    k = min(k, n - 1)
    # Stable sort on -S: equal scores keep index order.
    partners = np.argsort(-S, axis=1, kind="stable")[:, :k]
    rows = np.repeat(np.arange(n), k)
    pairs = np.stack([rows, partners.ravel()], axis=1)
    pairs = np.sort(pairs, axis=1)
    return np.unique(pairs, axis=0)
