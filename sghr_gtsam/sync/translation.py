"""Weighted least-squares translations given absolute rotations (SGHR step 3, second half).

Minimises ``Σ w_ij ‖t_j − t_i − R_i t_ij‖²``. Its normal equations are the scalar weighted graph Laplacian
(the same for the three coordinates) with three right-hand sides; grounding the first node of every
connected part at the origin makes the matrix block-diagonal positive definite, so all parts are solved by
one sparse factorization.
"""

from __future__ import annotations

import numpy as np

from sghr_gtsam.sync.rotation import connected_components, factor_spd, scalar_laplacian


def solve_translations(
    n: int, i: np.ndarray, j: np.ndarray, R: np.ndarray, t_ij: np.ndarray, w: np.ndarray
) -> np.ndarray:
    """Translations (n, 3) from absolute rotations ``R`` (n, 3, 3) and measured ``t_ij`` (E, 3).

    Edges with ``w <= 0`` are ignored; the first node of every connected part is at the origin.
    """
    keep = w > 0
    i, j, w = i[keep], j[keep], w[keep]
    labels = connected_components(n, i, j, np.ones(len(i), dtype=bool))
    anchors = np.zeros(n, dtype=bool)
    anchors[np.unique(labels, return_index=True)[1]] = True  # first node of every part
    t = np.zeros((n, 3))
    free = np.flatnonzero(~anchors)
    if len(free) == 0:
        return t
    r = w[:, None] * np.einsum("eab,eb->ea", R[i], t_ij[keep])
    b = np.zeros((n, 3))
    np.add.at(b, j, r)
    np.subtract.at(b, i, r)
    L = scalar_laplacian(n, i, j, w)
    t[free] = factor_spd(L[free][:, free]).solve(b[free])
    return t
