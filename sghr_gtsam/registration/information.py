"""Information matrices of registrations, in gtsam's tangent order [rotation, translation].

``registration_information`` is the one every stage that registers or re-registers an edge uses: a
point-to-plane model of the final alignment with its point noise estimated from the alignment's own
residuals, so that its scale means something (``gtsam.Marginals`` on the pose graph then gives covariances in
the scene's units). Each grid point ``q`` of scan j within ``max_distance`` of its nearest neighbour ``p`` of
scan i (normal ``n``) gives the residual ``r = nᵀ(T q − p)``; perturbing ``T → T exp(ξ)`` changes it by
``J ξ`` with ``J = [q × n', n']``, ``n' = Rᵀn`` (``n`` seen from scan j). With independent normal noise of
variance ``σ²`` the information would be ``Σ JᵀJ / σ²``, with ``σ̂² = Σ r² / (m − 6)`` over the ``m`` pairs.

The residuals are not independent: neighbouring points share the ``COV_NEIGHBORS`` points their normals are
fitted on (and the sampled surface's detail), so the independent model was about 2× overconfident on objects
(edge NEES 11.6 against χ²₆'s 6). The information is therefore the inverse of the cluster-robust (sandwich)
covariance ``H⁻¹ M H⁻¹`` (``plane_information``), its cells as wide as a normal's neighbourhood
(``correlation_length``, measured on the grid: not a tuned constant): residuals in one cell may be correlated
in any way, residuals in different cells are taken as independent.

Degenerate geometry: a pair that sees only a plane, a corridor or a cylinder does not fix every direction of
``T``; ``free_directions`` finds those directions by moving the scan along them and bounds their information
by the overlap's extent (the linearized model alone would credit noisy normals with a spurious stiffness).
``pose_spread`` and ``loosest`` then judge a scan's pose covariance in the same metric (the displacement of its
own points), so a scan held only by such edges is reported loose (``verify``) rather than placed as if its pose were
certain.

Why point-to-plane: tangential offsets between two samplings of one surface are not noise in the pose, and
the point-to-point sum (``Σ [−[q]×, I]ᵀ[−[q]×, I]``) is blind to sliding along a plane; on simulated scenes
with known range noise the point-to-plane model gives per-edge normalized errors near the χ²₆ median where
the point-to-point one (with its σ̂ from the full 3-d residuals) is 3-15× overconfident on objects
(calibrated covariances in the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import gtsam
import numpy as np
import small_gicp
from scipy.linalg import eigh
from scipy.spatial import cKDTree
from scipy.special import ndtri

from sghr_gtsam.cells import unique_cells
from sghr_gtsam.features.local import COV_NEIGHBORS, GICP_THREADS
from sghr_gtsam.registration.icp import nearest_within

MIN_PAIRS = 7
"""Fewer close pairs than this leave σ̂² without a degree of freedom: no information."""
MIN_CELLS = 12
"""The sandwich's middle ``M`` sums one outer product per cell: with fewer cells than twice the pose's
dimension it is too poorly estimated to invert (cluster-robust covariances need many clusters)."""
SIGMA_FLOOR = 1e-3
"""Least residual σ, relative to the correlation length (a few grid cells). Scans that fit exactly (a scan given
twice, generated planes) have residuals of rounding alone: their information overflowed to infinity, and at a
floor of 10⁻⁶ of the overlap's extent it still spanned 10¹² against the other edges', past what gtsam's
marginals can factor (NaN covariances). Real residuals are 0.1-0.3 voxels, 50× above this floor."""
CORRELATION_SAMPLE = 2000
"""Points whose neighbour distances give ``correlation_length``'s median (a median needs no more; the
k-nearest-neighbour search on every point of a dense 3DMatch grid costs a tenth of a second a pair)."""
FREE_QUANTILE = 0.999
"""A direction is fixed when moving the scan along it raises the mean squared residual more than chance would at
this one-sided level (the level of synchronization's χ² tests, ``sync.consensus.NOISE_QUANTILE``)."""
FREE_FLOOR = 1e-6
"""Least information of a free direction, relative to the pair's best-determined one (both per unit RMS
displacement of the points): gtsam's Cholesky calls a pose block whose information spans more than about
10⁷ indeterminate (a corridor pair bounded by its overlap alone spans 10⁹), so a free direction keeps a
σ at most 1000× the best one's."""


class Grid(Protocol):
    """A scan's points on one grid, in its own frame, with unit ``normals`` (sign free: the information does
    not depend on it) and k-d trees over ``points`` (small_gicp's ``cloud_tree``, scipy's ``point_tree``): a
    ``ScanFeatures`` (the matching grid) or a ``refine.Pyramid`` level."""

    points: np.ndarray
    normals: np.ndarray
    cloud_tree: small_gicp.KdTree
    point_tree: cKDTree


def plane_information(
    q: np.ndarray, normals: np.ndarray, residuals: np.ndarray, cell: float | None = None
) -> np.ndarray:
    """Information (6, 6) of the point-to-plane alignment from points ``q`` (m, 3) of scan j, the matched
    normals ``normals`` (m, 3) expressed in scan j's frame, and the point-to-plane residuals (m,).

    ``cell`` None: independent residuals, ``Σ JᵀJ / σ̂²`` (module doc). ``cell`` a length: residuals correlated
    within cells of that side (``q``'s frame), the cluster-robust (sandwich) covariance ``H⁻¹ M H⁻¹`` with
    ``H = Σ JᵀJ`` and ``M = c Σ_cells s sᵀ``, ``s = Σ_{cell} J r``, ``c = G/(G−1) · (m−1)/(m−6)`` over ``G`` cells;
    the information is its inverse ``H M⁻¹ H``. With fewer than ``MIN_CELLS`` cells the independent model. With a
    ``cell``, σ̂ is at least ``SIGMA_FLOOR`` times it."""
    J = np.hstack([np.cross(q, normals), normals])
    H = J.T @ J
    floor = 0.0 if cell is None else (SIGMA_FLOOR * cell) ** 2
    if cell is not None:
        _, cells = unique_cells(np.floor(q / cell).astype(np.int64))
        G = int(cells.max()) + 1
        if G >= MIN_CELLS:
            s = np.zeros((G, 6))
            np.add.at(s, cells, J * residuals[:, None])
            M = s.T @ s * (G / (G - 1) * (len(q) - 1) / (len(q) - 6))
            if np.trace(M) > floor * np.trace(H):  # M ≈ σ² H: residuals above the floor
                try:
                    info = H @ np.linalg.solve(M, H)
                    return (info + info.T) / 2
                except np.linalg.LinAlgError:  # every cell's score in a subspace: fall back to independence
                    pass
    sigma2 = float(residuals @ residuals) / (len(q) - 6)
    return H / max(sigma2, floor, np.finfo(float).tiny)


def correlation_length(grid: Grid, points: np.ndarray) -> float:
    """Diameter of the neighbourhood a normal of ``grid`` is fitted on: twice the median distance from
    ``points`` (grid points) to their ``COV_NEIGHBORS``-th neighbour. Two residuals closer than this share
    neighbours of their normals, so their errors are correlated; farther apart they share none. The median
    is taken over at most ``CORRELATION_SAMPLE`` of ``points``, evenly spaced in their order."""
    sample = points[:: max(1, len(points) // CORRELATION_SAMPLE)]
    _, sq = grid.cloud_tree.batch_knn_search(sample, COV_NEIGHBORS, GICP_THREADS)
    return 2.0 * float(np.sqrt(np.median(np.asarray(sq)[:, -1])))


def displacement_metric(points: np.ndarray) -> np.ndarray:
    """(6, 6) ``A`` with ``ξᵀ A ξ`` the mean squared displacement of ``points`` (m, 3) when their pose ``T``
    becomes ``T exp(ξ)`` (``ξ = [ω, v]``; point ``q`` moves by ``ω × q + v``): the metric in which pose
    uncertainties of different units (radians, metres) compare, as movements of the scan's own points."""
    c = points.mean(axis=0)
    S = (points - c).T @ (points - c) / len(points)
    qx = np.array([[0.0, -c[2], c[1]], [c[2], 0.0, -c[0]], [-c[1], c[0], 0.0]])
    # mean of [−[q]×, I]ᵀ[−[q]×, I] with q = c + d (Σ d = 0): the rotation block is tr(S) I − S + [c]×ᵀ[c]×.
    A = np.zeros((6, 6))
    A[:3, :3] = np.trace(S) * np.eye(3) - S + qx.T @ qx
    A[:3, 3:] = qx
    A[3:, :3] = qx.T
    A[3:, 3:] = np.eye(3)
    return A


def _plane_residuals(target_i: Grid, q: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Point-to-plane residuals of ``q`` under ``T``, each point against its nearest target point."""
    moved = q @ T[:3, :3].T + T[:3, 3]
    nearest = np.asarray(target_i.cloud_tree.batch_nearest_neighbor_search(moved, GICP_THREADS)[0])
    return np.einsum("mk,mk->m", moved - target_i.points[nearest], target_i.normals[nearest])


def _clustered_error(values: np.ndarray, cells: np.ndarray) -> float:
    """Standard error of the mean of ``values`` whose errors may be correlated within a cell (``cells``: each
    value's cell index, at least two cells) and are independent across cells: the cluster-robust variance
    ``plane_information`` uses."""
    G = int(cells.max()) + 1
    s = np.bincount(cells, weights=values - values.mean(), minlength=G)
    return float(np.sqrt(s @ s * G / (G - 1))) / len(values)


def free_directions(
    target_i: Grid,
    q: np.ndarray,
    T: np.ndarray,
    information: np.ndarray,
    step: float,
    residuals: np.ndarray,
    cell: float,
) -> Information:
    """``information`` of ``T exp(ξ)`` with the directions the pair's geometry does not fix (a plane's three, a
    corridor's one, a cylinder's two) bounded only by the overlap's extent, and their number.

    A direction does not fix the pose when moving scan j's close points ``q`` by ``step`` (RMS) along it, with every
    point re-associated to its nearest target point, does not raise their mean squared point-to-plane residual
    significantly: by less than ``ndtri(FREE_QUANTILE)`` standard errors of that mean's change, its residuals
    correlated within cells of side ``cell`` as in ``plane_information``. The data then cannot tell the pose from
    one moved that far. The linearized information cannot say so: noisy normals tilt off a flat wall and give
    sliding along it a spurious stiffness, while re-associated points slide along the wall at no cost. Directions
    are tried from the least informative (generalized eigenvectors of the information in ``displacement_metric``)
    until one is fixed. A free one gets the information of a displacement σ equal to the RMS radius of ``q`` (two
    scans that overlap cannot slide beyond their overlap), or ``FREE_FLOOR`` times the best direction's when that
    is more (see there). ``residuals``: the point-to-plane residuals of ``q`` at ``T``, which the caller has
    already measured."""
    A = displacement_metric(q)
    try:
        values, vectors = eigh(information, A)  # vectorsᵀ A vectors = I: unit RMS displacement per unit
    except np.linalg.LinAlgError:  # collinear points (A singular) or a non-finite information: nothing to test
        return Information(information, 0, np.zeros((6, 6)), information)
    AV = A @ vectors
    if values[0] < FREE_FLOOR * values[-1]:
        # A direction the close points do not measure at all (a few points of a wrong registration: rank 4 seen on
        # noise scans) leaves the information singular, which synchronization and the g2o files refuse. It gets
        # the floor a free direction keeps; never reached on the real scenes' pairs
        # (the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md).
        values = np.maximum(values, FREE_FLOOR * values[-1])
        information = AV @ np.diag(values) @ AV.T
        information = (information + information.T) / 2
    _, cells = unique_cells(np.floor(q / cell).astype(np.int64))
    if cells.max() + 1 < MIN_CELLS:  # too few cells to estimate a spread from: independent, as the information
        cells = np.arange(len(q))
    z = float(ndtri(FREE_QUANTILE))
    free = 0
    for k in range(6):
        xi = step * vectors[:, k]
        moved = [_plane_residuals(target_i, q, T @ _exp(sign * xi)) ** 2 for sign in (1.0, -1.0)]
        rise = (moved[0] + moved[1]) / 2 - residuals**2
        if rise.mean() > z * _clustered_error(rise, cells):
            break
        free += 1
    if free == 0:
        return Information(information, 0, np.zeros((6, 6)), information)
    bound = max(1.0 / float(np.sum(np.var(q, axis=0))), FREE_FLOOR * values[-1])
    fixed = AV[:, free:] @ np.diag(values[free:]) @ AV[:, free:].T
    loose = bound * AV[:, :free] @ AV[:, :free].T
    return Information((fixed + fixed.T) / 2 + (loose + loose.T) / 2, free, (loose + loose.T) / 2, information)


def _exp(xi: np.ndarray) -> np.ndarray:
    """SE(3) exponential of ``[ω, v]`` (gtsam's Pose3.Expmap) as a 4×4 matrix."""
    return gtsam.Pose3.Expmap(xi).matrix()


@dataclass
class Information:
    """An edge's information ``matrix`` (6, 6) with its free directions bounded by the overlap alone, the number
    of directions its geometry leaves ``free`` (``free_directions``), ``loose``: the part of ``matrix`` along
    them (zeros when none is free), and ``measured``: the point-to-plane information before that bounding.

    Synchronization weighs an edge by ``measured``; the reported covariances and the ``loose`` status use
    ``matrix``: a doubt belongs in what is reported, not in where the scans go."""

    matrix: np.ndarray
    free: int
    loose: np.ndarray
    measured: np.ndarray


def registration_information(
    target_i: Grid,
    source_j: Grid,
    T: np.ndarray,
    max_distance: float,
    search: tuple[np.ndarray, np.ndarray] | None = None,
) -> Information | None:
    """Information of ``T`` (``T_ij``: scan j into scan i's frame) for ``T exp(ξ)``, from the grid points of
    scan j that ``T`` brings within ``max_distance`` of scan i; None with fewer than ``MIN_PAIRS``. Both grids
    must be those ``T`` was aligned on: its residuals there are what σ̂ and the sum measure. The directions
    free under a move of ``max_distance`` (``free_directions``) are counted and bounded only by the overlap.
    ``search``: ``icp.nearest_within`` of ``source_j``'s points moved by ``T`` (to at least ``max_distance``), when
    the caller has it."""
    q = source_j.points
    R, t = T[:3, :3], T[:3, 3]
    moved = q @ R.T + t
    nearest, sq_dist = nearest_within(target_i, moved, max_distance) if search is None else search
    close = sq_dist < max_distance**2
    if np.count_nonzero(close) < MIN_PAIRS:
        return None
    nearest = nearest[close]
    n = target_i.normals[nearest]
    residuals = np.einsum("mk,mk->m", moved[close] - target_i.points[nearest], n)
    cell = correlation_length(target_i, target_i.points[nearest])
    information = plane_information(q[close], n @ R, residuals, cell)
    return free_directions(target_i, q[close], T, information, max_distance, residuals, cell)


def pose_spread(covariance: np.ndarray, points: np.ndarray) -> float:
    """σ of the displacement of a scan's ``points`` (m, 3, its own frame) along the least determined direction
    of its pose covariance (6, 6, gtsam order at the pose): the root of the largest eigenvalue of ``C A``
    (``A`` the ``displacement_metric``). In the scene's units, whatever mix of rotation and translation that
    direction is; inf when the covariance is not finite."""
    if not np.isfinite(covariance).all():
        return float("inf")
    w, V = np.linalg.eigh(displacement_metric(points))
    L = V * np.sqrt(np.maximum(w, 0.0))  # A = L Lᵀ, also for collinear points (A singular)
    return float(np.sqrt(max(np.linalg.eigvalsh(L.T @ covariance @ L)[-1], 0.0)))


def loosest(
    covariances: np.ndarray, points: Sequence[np.ndarray], registered: Sequence[int]
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) ``pose_spread`` of each ``registered`` scan (inf where its covariance is not finite, NaN for the others)
    and (N, 3) the unit axis along which its position is least determined (the translation block's longest axis;
    NaN where not judged). ``points[k]``: scan k's points in its own frame, read once."""
    spreads, axes = np.full(len(covariances), np.nan), np.full((len(covariances), 3), np.nan)
    for k in registered:
        spreads[k] = pose_spread(covariances[k], points[k])
        if np.isfinite(covariances[k]).all():
            axes[k] = np.linalg.eigh(covariances[k][3:, 3:])[1][:, -1]
    return spreads, axes
