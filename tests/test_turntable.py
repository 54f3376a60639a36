"""data_tools.simulate.make_turntable: equal steps on a circle around the object, scans consistent with GT."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from data_tools.simulate import make_turntable
from sghr_gtsam.se3 import inv_T, rotation_angle


@pytest.fixture(scope="module")
def turntable():
    return make_turntable(10, seed=3)


def test_sensors_turn_in_equal_steps_on_a_level_circle(turntable):
    poses = turntable.poses
    assert len(turntable.scans) == len(poses) == 10
    eyes = poses[:, :3, 3]
    np.testing.assert_allclose(np.linalg.norm(eyes, axis=1), 2.2, atol=1e-9)
    np.testing.assert_allclose(eyes[:, 2], 2.2 * np.sin(np.radians(20.0)), atol=1e-9)
    steps = [np.degrees(rotation_angle(poses[k, :3, :3].T @ poses[(k + 1) % 10, :3, :3])) for k in range(10)]
    np.testing.assert_allclose(steps, 36.0, atol=1e-6)
    # every sensor looks at the turntable's centre: its z axis points from the eye to the origin
    np.testing.assert_allclose(np.einsum("kij,kj->ki", poses[:, :3, :3], [[0, 0, 1.0]] * 10), -eyes / 2.2, atol=1e-9)


def test_neighbouring_scans_coincide_under_gt(turntable):
    """Points of scan k+1 put into scan k's frame by the GT relative pose land on scan k's surface where
    the two overlap (1 mm range noise, ~7 mm ray spacing), and far from it where they do not."""
    T = inv_T(turntable.poses[0]) @ turntable.poses[1]
    A, B = turntable.scans[0], turntable.scans[1]
    d, _ = cKDTree(A).query(B @ T[:3, :3].T + T[:3, 3])
    assert np.mean(d < 0.01) > 0.5  # 36° apart: most of the next view is seen again
    assert np.median(d) < 0.01
    wrong = inv_T(turntable.poses[0]) @ turntable.poses[5]  # the opposite side is a wrong guess
    d_wrong, _ = cKDTree(A).query(B @ wrong[:3, :3].T + wrong[:3, 3])
    assert np.median(d_wrong) > 0.05


def test_deterministic_and_rejects_one_scan():
    a, b = make_turntable(3, seed=1), make_turntable(3, seed=1)
    np.testing.assert_array_equal(a.scans[2], b.scans[2])
    np.testing.assert_array_equal(a.poses, b.poses)
    with pytest.raises(ValueError):
        make_turntable(1)
