"""data_tools.refit_gt: GT poses re-fitted to the scans come back to the truth from a wrong GT, and stay at it
from the right one (a generated room: its GT is exact)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from data_tools.refit_gt import refit
from sghr_gtsam.se3 import relative_errors
from sghr_gtsam.synthetic import make_scene


@pytest.fixture(scope="module")
def room():
    return make_scene("room", 6, seed=3)


def _errors(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return np.array([relative_errors(T, G) for T, G in zip(poses, truth)])


@pytest.mark.parametrize("seed", [0, 1])
def test_a_gt_off_by_two_degrees_is_pulled_back_by_the_scans(room, seed):
    rng = np.random.default_rng(seed)
    wrong = room.poses.copy()
    for k in (2, 4):
        axis = rng.normal(size=3)
        off = np.eye(4)
        off[:3, :3] = Rotation.from_rotvec(np.radians(2.0) * axis / np.linalg.norm(axis)).as_matrix()
        off[:3, 3] = 0.04 * rng.normal(size=3) / np.sqrt(3)
        wrong[k] = wrong[k] @ off
    fit = refit(list(room.scans), wrong, room.voxel)
    assert not fit.failed and len(fit.pairs) >= 10
    before, after = _errors(wrong, room.poses), _errors(fit.poses, room.poses)
    assert (after[:, 0] < 0.5).all() and (after[:, 1] < 0.6 * room.voxel).all(), after
    assert (after[[2, 4], 0] < before[[2, 4], 0] / 4).all(), (before, after)
    # the ICP optima of the pairs with a wrong scan lie where the truth is, not where the wrong GT was
    assert fit.icp_move[:, 0].max() > 1.0


def test_an_exact_gt_stays_where_it_is(room):
    fit = refit(list(room.scans), room.poses, room.voxel)
    after = _errors(fit.poses, room.poses)
    assert (after[:, 0] < 0.5).all() and (after[:, 1] < 0.6 * room.voxel).all(), after
