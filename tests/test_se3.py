"""The shared SE(3)/SO(3) helpers: the nearest rotation by Newton's polar iteration against its definition."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.se3 import make_T, non_rigid, project_to_so3, rotation_angle


def _nearest_by_svd(M: np.ndarray) -> np.ndarray:
    """The textbook nearest rotation: U diag(1, 1, det(U Vᵀ)) Vᵀ from the SVD M = U Σ Vᵀ."""
    U, _, Vt = np.linalg.svd(M)
    D = np.tile(np.eye(3), M.shape[:-2] + (1, 1))
    D[..., 2, 2] = np.linalg.det(U @ Vt)
    return U @ D @ Vt


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 300), st.floats(1e-6, 1e6), st.floats(0.0, 3.0))
def test_the_nearest_rotation_of_any_matrix_is_the_svd_one(seed, n, scale, noise):
    """Scaled noisy rotations (the spectral blocks), and with large noise any matrix, either sign of det."""
    rng = np.random.default_rng(seed)
    M = scale * (Rotation.random(n, random_state=rng).as_matrix() + noise * rng.normal(size=(n, 3, 3)))
    R = project_to_so3(M)
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.tile(np.eye(3), (n, 1, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    # The nearest rotation is unique unless the two smallest singular values of M make a tie.
    s = np.linalg.svd(M, compute_uv=False)
    unique = (s[:, 1] - s[:, 2]) > 1e-6 * s[:, 0]
    np.testing.assert_allclose(R[unique], _nearest_by_svd(M)[unique], atol=1e-9)


def test_rotations_stay_and_degenerate_matrices_still_give_rotations():
    rng = np.random.default_rng(0)
    R = Rotation.random(50, random_state=rng).as_matrix()
    np.testing.assert_allclose(project_to_so3(R), R, atol=1e-15)
    np.testing.assert_allclose(project_to_so3(R[0]), R[0], atol=1e-15)  # one (3, 3) matrix
    flat = rng.normal(size=(20, 3, 3))
    flat[:, :, 2] = flat[:, :, 0] + 1e-12 * flat[:, :, 1]  # rank 2: det ≈ 0
    reflected = -R[:20]  # det −1
    for M in (flat, reflected, np.zeros((3, 3, 3))):
        out = project_to_so3(M)
        np.testing.assert_allclose(np.swapaxes(out, -1, -2) @ out, np.tile(np.eye(3), (len(M), 1, 1)), atol=1e-12)
        np.testing.assert_allclose(np.linalg.det(out), 1.0, atol=1e-12)
    np.testing.assert_allclose(project_to_so3(reflected), _nearest_by_svd(reflected), atol=1e-9)
    assert project_to_so3(np.zeros((0, 3, 3))).shape == (0, 3, 3)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.5, 2.0), st.sampled_from(["rigid", "scaled", "reflected", "row"]))
def test_non_rigid_tells_rotations_from_scales_reflections_and_bad_rows(seed, scale, change):
    """The one rigidity test the pose graph check, the pose writers and the incremental session share."""
    T = make_T(Rotation.random(random_state=seed).as_matrix(), np.random.default_rng(seed).normal(size=3))
    if change == "scaled":
        T[:3, :3] *= scale if abs(scale - 1.0) > 0.02 else 1.5
    elif change == "reflected":
        T[:3, 2] *= -1
    elif change == "row":
        T[3, 0] = 1e-6
    assert bool(non_rigid(T)) == (change != "rigid")
    assert bool(non_rigid(np.where(np.eye(4, dtype=bool), np.nan, T)))


@given(
    st.lists(st.floats(-1, 1), min_size=3, max_size=3).filter(lambda v: np.linalg.norm(v) > 1e-3),
    st.floats(-12, np.log10(np.pi)),
    st.booleans(),
)
def test_the_rotation_angle_is_exact_at_every_angle(axis, log_angle, near_pi):
    """Built from an axis and an angle from 1e-12 rad to π (or as far below π), the rotation reads its angle back to
    float precision: no 1e-8 rad floor near 0 (one ulp of the trace) and none near π."""
    angle = 10.0**log_angle
    if near_pi:
        angle = np.pi - angle
    R = Rotation.from_rotvec(angle * np.asarray(axis) / np.linalg.norm(axis)).as_matrix()
    assert abs(rotation_angle(R) - angle) <= 1e-15 + 4e-16 * angle
