"""Small SE(3)/SO(3) helpers shared by every stage (plain numpy, batched where it matters)."""

from __future__ import annotations

import numpy as np

# Entry k = 3·row + col of a 3×3 matrix X has the cofactor X[_A]·X[_B] − X[_C]·X[_D].
_A = np.array([4, 5, 3, 7, 8, 6, 1, 2, 0])
_B = np.array([8, 6, 7, 2, 0, 1, 5, 3, 4])
_C = np.array([5, 3, 4, 8, 6, 7, 2, 0, 1])
_D = np.array([7, 8, 6, 1, 2, 0, 4, 5, 3])
_POLAR_ITERS = 12
"""Newton steps before falling back to the SVD; a scaled Newton iteration from a well-conditioned matrix
reaches rounding level in 4-8."""


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to each 3×3 matrix in ``M`` (shape (..., 3, 3)).

    For ``det M > 0`` it is the orthogonal polar factor, found by Newton's iteration ``X ← (γX + X⁻ᵀ/γ)/2``
    with ``γ = det(X)^(−1/3)`` (Higham 1986) on all matrices at once, entries as rows of a (9, n) array:
    3× faster than numpy's batched SVD from 50 matrices (5,000 3×3 blocks: 3 ms against 9), equal to
    it to ~1e-15. Matrices with ``det M`` near 0 or negative (their nearest rotation is not the polar factor),
    or a batch that does not converge, take the SVD."""
    M = np.asarray(M, dtype=float)
    X = M.reshape(-1, 9).T.copy()
    C = X[_A] * X[_B] - X[_C] * X[_D]
    det = np.einsum("kn,kn->n", X[:3], C[:3])
    good = det > 1e-6 * np.abs(X).max(axis=0, initial=0.0) ** 3
    out = np.empty_like(X)
    X, C, det = X[:, good], C[:, good], det[good]
    converged = False
    for _ in range(_POLAR_ITERS):
        g = np.cbrt(det)
        Y = 0.5 * (X / g + C * (g / det))  # X⁻ᵀ = C / det
        converged = np.abs(Y - X).max(initial=0.0) <= 8 * np.finfo(float).eps
        X = Y
        if converged:
            break
        C = X[_A] * X[_B] - X[_C] * X[_D]
        det = np.einsum("kn,kn->n", X[:3], C[:3])
    out[:, good] = X
    svd = ~good if converged else np.ones_like(good)
    if svd.any():
        out[:, svd] = _svd_project(M.reshape(-1, 3, 3)[svd]).reshape(-1, 9).T
    return out.T.reshape(M.shape)


def _svd_project(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


RIGID_TOL = 1e-2
"""How far a measured rotation may be from orthonormal (largest entry of ``RᵀR − I``): the 3DMatch ground truth is
off by up to 5e-4."""


def non_rigid(T: np.ndarray, rotation_tol: float = RIGID_TOL, row_tol: float = 1e-9) -> np.ndarray:
    """(...,) bool: which of ``T`` (..., 4, 4) are no rigid transform: a rotation block not orthonormal to
    ``rotation_tol`` or of determinant ≤ 0, or a last row not ``0 0 0 1`` to ``row_tol``; non-finite ones too."""
    R = T[..., :3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # a huge entry overflows to inf: not orthonormal either
        orthonormal = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1)) <= rotation_tol
        last_row = np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=-1) <= row_tol
        proper = np.linalg.det(R) > 0
    return ~(orthonormal & proper & last_row)


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Stack rotations (..., 3, 3) and translations (..., 3) into homogeneous (..., 4, 4)."""
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms (..., 4, 4) without a general matrix inverse."""
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    return make_T(Rt, -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3]))


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Rotation angle in radians of each rotation in ``R`` (..., 3, 3): the atan2 of its sine (half the norm of the
    skew part) and its cosine (from the trace), exact to float precision at every angle, where the arccos of the
    trace alone reads one ulp of it as 2e-8 rad."""
    c = np.trace(R, axis1=-2, axis2=-1) - 1.0
    x, y, z = R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]
    return np.arctan2(np.sqrt(x * x + y * y + z * z), c)  # both sides twice the sine and cosine


def relative_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation error (degrees) and translation error (scene units) between transforms (..., 4, 4)."""
    R_err = np.swapaxes(T_est[..., :3, :3], -1, -2) @ project_to_so3(T_gt[..., :3, :3])
    rot = np.degrees(rotation_angle(R_err))
    trans = np.linalg.norm(T_est[..., :3, 3] - T_gt[..., :3, 3], axis=-1)
    return rot, trans


def transform_points(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Apply one rigid transform (4, 4) to points (N, 3)."""
    return P @ T[:3, :3].T + T[:3, 3]
