"""Effort where the graph is weak: scans left unregistered, unverified or hanging on
fewer than ``MIN_DEGREE`` kept edges get global registration against their next candidates by overlap
score: an adaptive k instead of one k for everyone."""

from __future__ import annotations

import numpy as np

MIN_DEGREE = 2
"""A scan held by one kept edge has nothing to check that edge against."""


def weak_scans(
    n: int, i: np.ndarray, j: np.ndarray, kept: np.ndarray, component: np.ndarray, unverified: np.ndarray
) -> np.ndarray:
    """(N,) bool: scans outside the largest part, ``unverified``, or with fewer than ``MIN_DEGREE`` kept edges."""
    degree = np.bincount(np.r_[i[kept], j[kept]], minlength=n)
    return (component != 0) | unverified | (degree < MIN_DEGREE)


def retry_pairs(weak: np.ndarray, scores: np.ndarray, registered: np.ndarray, per_scan: int) -> np.ndarray:
    """(R, 2) pairs to register: each weak scan with its ``per_scan`` best-scoring partners not yet
    ``registered`` ((N, N) bool), each pair once."""
    chosen: set[tuple[int, int]] = set()
    for a in np.flatnonzero(weak):
        s = np.where(registered[a] | (np.arange(len(weak)) == a), -np.inf, scores[a])
        for b in np.argsort(-s, kind="stable")[:per_scan]:
            if np.isfinite(s[b]):
                chosen.add((min(a, b), max(a, b)))
    return np.array(sorted(chosen), dtype=np.int64).reshape(-1, 2)
