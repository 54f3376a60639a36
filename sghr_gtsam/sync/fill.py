"""What a direct (Cholesky) solve of a graph's normal equations costs, from gtsam's symbolic elimination. Loop
closures between far-apart nodes leave an elimination no small separators (uniformly random ones make an expander,
whose fill grows as N³: 20,000 poses with 100,000 random edges need ~1e14 flops and ~30 GB for one 6-dof solve),
and there the solvers switch to conjugate gradients, which such well-connected graphs make converge fast."""

from __future__ import annotations

import gtsam
import numpy as np


def direct_cost(n: int, i: np.ndarray, j: np.ndarray, dof: int = 6) -> float:
    """Estimated flops of one direct (multifrontal Cholesky, COLAMD order) solve over the edges ``(i, j)`` between
    ``n`` nodes of ``dof`` unknowns each (milliseconds to estimate where the fill is small, seconds at 20,000 nodes
    with 100,000 random edges): a clique of ``f`` frontal and ``s`` separator nodes costs ``F³/3 + F²S + FS²``
    with ``F = dof·f``, ``S = dof·s``."""
    if not len(i):
        return 0.0
    symbolic = gtsam.SymbolicFactorGraph()
    for a, b in zip(np.asarray(i).tolist(), np.asarray(j).tolist()):
        symbolic.push_factor(a, b)
    tree = symbolic.eliminateMultifrontal(gtsam.Ordering.ColamdSymbolicFactorGraph(symbolic))
    cliques = {}
    for key in np.unique(np.r_[i, j]).tolist():
        conditional = tree[key].conditional()
        cliques[conditional.firstFrontalKey()] = (conditional.nrFrontals(), conditional.nrParents())
    f, s = float(dof) * np.array(list(cliques.values()), dtype=float).T
    return float(np.sum(f**3 / 3 + f**2 * s + f * s**2))


__all__ = ["direct_cost"]
