"""Robust rigid estimation from putative point correspondences by second-order spatial compatibility, in the
manner of SC²-PCR (Chen et al., CVPR 2022): two correspondences are compatible when they preserve the
distance between their points; a correspondence's second-order compatibility with a seed counts the
correspondences compatible with both. Seeds are picked by the leading eigenvector of the compatibility
matrix (spread out by non-maximum suppression); each seed grows a consensus set from its most
second-order-compatible correspondences, which gives one hypothesis by weighted SVD; the hypothesis that
the most correspondences agree with wins and is refined on its inliers. Everything is deterministic."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.distance import pdist, squareform


@dataclass(frozen=True)
class SC2Params:
    """Lengths in voxels. ``compatibility``: two correspondences are compatible when the distances between
    their points differ by less than this. ``inlier``: a correspondence agrees with a hypothesis when the
    transform brings its points this close. ``max_correspondences``: above this the strongest (by leading
    eigenvector) are kept, which bounds the N² cost. ``seed_fraction`` / ``max_seeds``: seeds per
    correspondence and their cap; ``nms_radius``: seeds are at least this far apart (in scan i).
    ``k1`` / ``k2``: consensus set sizes of the two stages. ``refine_iterations``: SVD rounds on the
    winner's inliers."""

    compatibility: float = 2.0
    inlier: float = 1.5
    max_correspondences: int = 2000
    seed_fraction: float = 0.1
    max_seeds: int = 100
    nms_radius: float = 2.0
    k1: int = 30
    k2: int = 20
    refine_iterations: int = 3


def _leading_eigenvector(M: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Power iteration on a (batch of) non-negative symmetric matrices (..., n, n); a constant start makes
    it deterministic and, by Perron-Frobenius, never orthogonal to the answer."""
    v = np.ones(M.shape[:-1], dtype=M.dtype)
    for _ in range(iterations):
        v = np.einsum("...ij,...j->...i", M, v)
        v /= np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    return v


def _weighted_kabsch(p_i: np.ndarray, p_j: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Batched rigid transforms (..., 4, 4) minimising Σ w ‖T p_j − p_i‖² for (..., n, 3) point sets."""
    w = w / np.maximum(w.sum(axis=-1, keepdims=True), 1e-12)
    mu_i = np.einsum("...n,...nd->...d", w, p_i)
    mu_j = np.einsum("...n,...nd->...d", w, p_j)
    H = np.einsum("...n,...na,...nb->...ab", w, p_j - mu_j[..., None, :], p_i - mu_i[..., None, :])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    D = np.broadcast_to(np.eye(3), H.shape).copy()
    D[..., 2, 2] = np.where(d == 0, 1.0, d)
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    T = np.broadcast_to(np.eye(4), H.shape[:-2] + (4, 4)).copy()
    T[..., :3, :3] = R
    T[..., :3, 3] = mu_i - np.einsum("...ab,...b->...a", R, mu_j)
    return T


def _residuals(T: np.ndarray, p_i: np.ndarray, p_j: np.ndarray) -> np.ndarray:
    """‖T p_j − p_i‖ for hypotheses T (M, 4, 4) over all correspondences (N, 3): (M, N)."""
    moved = p_j @ np.swapaxes(T[:, :3, :3], 1, 2) + T[:, None, :3, 3]
    return np.sqrt(np.sum((moved - p_i) ** 2, axis=-1))


def _pick_seeds(score: np.ndarray, p_i: np.ndarray, radius: float, count: int) -> np.ndarray:
    """Greedy non-maximum suppression: by decreasing score, a correspondence becomes a seed unless a
    seed already lies within ``radius`` of it (scan i's side)."""
    seeds: list[int] = []
    taken = np.zeros(len(score), dtype=bool)
    for k in np.argsort(-score, kind="stable"):
        if taken[k]:
            continue
        seeds.append(int(k))
        if len(seeds) == count:
            break
        taken |= np.sum((p_i - p_i[k]) ** 2, axis=1) < radius**2
    return np.array(seeds, dtype=np.int64)


@dataclass
class Estimate:
    """``T`` (4, 4) maps scan j's points onto scan i's; ``inliers`` (N,) bool: the correspondences it
    brings within the inlier distance."""

    T: np.ndarray
    inliers: np.ndarray


def sc2_estimate(p_i: np.ndarray, p_j: np.ndarray, voxel: float, params: SC2Params = SC2Params()) -> Estimate:
    """``T`` with ``T p_j ≈ p_i`` for correspondences (N, 3) + (N, 3), most of which may be outliers."""
    n = len(p_i)
    if n < 3:
        return Estimate(np.eye(4), np.zeros(n, dtype=bool))
    a, b = p_i / voxel, p_j / voxel  # voxel units
    C = _compatibility(a, b, params.compatibility)
    eig = _leading_eigenvector(C)
    keep = np.arange(n)
    if n > params.max_correspondences:
        keep = np.sort(np.argsort(-eig, kind="stable")[: params.max_correspondences])
        C, eig = C[np.ix_(keep, keep)], eig[keep]
    a_k, b_k = a[keep], b[keep]

    count = min(params.max_seeds, max(1, round(params.seed_fraction * len(keep))))
    seeds = _pick_seeds(eig, a_k, params.nms_radius, count)
    k1 = min(params.k1, len(keep))
    first = _first_stage(C, seeds, k1)  # (M, k1)
    # Second stage: rank the set by second-order compatibility with the seed within the set alone.
    local = C[first[:, :, None], first[:, None, :]]  # (M, k1, k1)
    row = C[seeds[:, None], first]  # (M, k1): the seed's row
    local_sc2 = row * np.einsum("mk,mkl->ml", row, local)
    k2 = min(params.k2, k1)
    second = np.argsort(-local_sc2, axis=1, kind="stable")[:, :k2]
    idx = np.take_along_axis(first, second, axis=1)  # (M, k2)
    sub = C[idx[:, :, None], idx[:, None, :]]
    weights = _leading_eigenvector(sub)
    T = _weighted_kabsch(a_k[idx], b_k[idx], weights.astype(np.float64))

    # Score each hypothesis on all correspondences (a truncated linear score: near inliers count more).
    r = _residuals(T, a, b)
    score = np.clip(1.0 - r / params.inlier, 0.0, None).sum(axis=1)
    best = T[int(np.argmax(score))]
    for _ in range(params.refine_iterations):
        r = _residuals(best[None], a, b)[0]
        inl = r < params.inlier
        if inl.sum() < 3:
            break
        best = _weighted_kabsch(a[inl], b[inl], np.ones(int(inl.sum())))
    r = _residuals(best[None], a, b)[0]
    best = best.copy()
    best[:3, 3] *= voxel
    return Estimate(best, r < params.inlier)


def _first_stage(C: np.ndarray, seeds: np.ndarray, k1: int) -> np.ndarray:
    """(M, k1): per seed, the ``k1`` correspondences of highest second-order compatibility with it: compatible
    with it, ranked by how many correspondences are compatible with both (ties by index). A seed with fewer than
    ``k1`` compatible ones is padded with itself (its weight stays one vote)."""
    rows = C[seeds]  # (M, N), 0/1
    # Row s of rows @ C counts, for every l, the correspondences compatible with both s and l (C is symmetric);
    # counts below 2^24 are exact in float32, so any summation order gives the same ranking.
    sc2 = rows @ C
    top = np.argsort(np.where(rows > 0, -sc2, np.inf), axis=1, kind="stable")[:, :k1]
    return np.where(np.arange(k1) < rows.sum(axis=1, keepdims=True), top, seeds[:, None])


def _compatibility(a: np.ndarray, b: np.ndarray, threshold: float) -> np.ndarray:
    """(N, N) float32: 1 where correspondences k and l keep their distance within ``threshold``."""
    # scipy's pdist, not BLAS: a 3-d inner product gains nothing from BLAS, whose threads contend with the other
    # worker processes. Each pair once (the same distances as cdist's), expanded after the test: at 2,000
    # correspondences 21 ms against 140 ms for both full matrices.
    C = squareform((np.abs(pdist(a) - pdist(b)) < threshold).astype(np.float32))
    np.fill_diagonal(C, 1.0)
    return C
