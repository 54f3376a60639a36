"""Small SE(3)/SO(3) helpers shared by every stage (plain numpy, batched where it matters)."""

from __future__ import annotations

import numpy as np


def project_to_so3(M: np.ndarray) -> np.ndarray:
    """Nearest rotation (Frobenius) to each 3x3 matrix in ``M`` (shape (..., 3, 3))."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


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
    """Rotation angle in radians of each rotation in ``R`` (..., 3, 3), numerically safe near 0 and pi."""
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def relative_errors(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation error (degrees) and translation error (scene units) between transforms (..., 4, 4)."""
    R_err = np.swapaxes(T_est[..., :3, :3], -1, -2) @ project_to_so3(T_gt[..., :3, :3])
    rot = np.degrees(rotation_angle(R_err))
    trans = np.linalg.norm(T_est[..., :3, 3] - T_gt[..., :3, 3], axis=-1)
    return rot, trans


def transform_points(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Apply one rigid transform (4, 4) to points (N, 3)."""
    return P @ T[:3, :3].T + T[:3, 3]
