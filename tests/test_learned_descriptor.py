"""The learned local descriptor (``features.learned``): the numpy network against the same network in torch's
layers with the shipped weights, invariance to moving the scan, registration with it, and its inlier bar on every
pair of the kitchen and the bunny against their ground truth."""

import itertools

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation
from test_pairwise import boxes_scene

from sghr_gtsam.config import MIN_INLIERS, Config
from sghr_gtsam.features.learned import SECTORS, learned_descriptors, load_patch_net, torch_network
from sghr_gtsam.features.local import compute_features, default_voxel
from sghr_gtsam.registration.pairwise import register_pair
from sghr_gtsam.se3 import inv_T, make_T, relative_errors, transform_points
from sghr_gtsam.types import InputError


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 64))
def test_numpy_network_is_torchs(seed, batch):
    net = load_patch_net()
    rng = np.random.default_rng(seed)
    patches = rng.random((batch, 3, 5, 6, SECTORS)).astype(np.float32)
    patches[:, 1:] = 2 * patches[:, 1:] - 1  # mean cosines
    with torch.no_grad():
        expected = torch_network(net).eval()(torch.from_numpy(patches)).numpy()
    got = net(patches)
    np.testing.assert_allclose(got, expected, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-5)


@pytest.fixture(scope="module")
def boxes_learned():
    points = boxes_scene(seed=1)
    voxel = default_voxel([points])
    return compute_features(points, voxel, descriptor="learned"), voxel


@settings(max_examples=6, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_moving_the_scan_keeps_the_descriptors(boxes_learned, seed):
    # Invariant to turning a patch about its normal by whole sectors only: in between, the bins shift a little.
    f, voxel = boxes_learned
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    moved = learned_descriptors(f.points @ R.T + rng.uniform(-10, 10, 3), f.normals @ R.T, voxel)
    nearest = cKDTree(moved).query(f.descriptors)[1]
    same = np.linalg.norm(f.points[nearest] - f.points, axis=1) < 1.5 * voxel
    assert same.mean() > 0.85, same.mean()
    assert np.median(np.sum(moved * f.descriptors, axis=1)) > 0.9


def test_features_match_on_the_learned_descriptors_and_keep_fpfh(boxes_learned):
    f, _ = boxes_learned
    assert f.descriptors.shape == (len(f), 32) and f.descriptors.dtype == np.float32
    assert f.fpfh.shape == (len(f), 33) and f.keypoints is f.points


def test_learned_descriptor_recovers_a_known_transform(boxes_learned):
    fi, voxel = boxes_learned
    T_ij = make_T(Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix(), np.array([0.7, -0.4, 0.3]))
    fj = compute_features(transform_points(inv_T(T_ij), boxes_scene(seed=2)), voxel, descriptor="learned")
    result = register_pair(fi, fj, voxel)
    rot, trans = relative_errors(result.T, T_ij)
    assert rot < 0.1 and trans < 0.05 * voxel, (rot, trans)
    assert result.inliers > 100


@pytest.mark.data
@pytest.mark.parametrize("descriptor", list(MIN_INLIERS))
def test_inlier_bar_admits_no_wrong_pair_of_the_kitchen_and_the_bunny(kitchen, bunny, descriptor):
    """``MIN_INLIERS`` is one more than the most inliers a wrong pair reaches here; it keeps most right pairs."""
    right = wrong = 0
    for (gt, scans, voxel), bounds in ((kitchen, (5.0, 0.2)), (bunny, (1.0, 0.001))):
        feats = {name: compute_features(s, voxel, descriptor=descriptor) for name, s in scans.items()}
        for a, b in itertools.combinations(scans, 2):
            result = register_pair(feats[a], feats[b], voxel)
            rot, trans = relative_errors(result.T, inv_T(gt[a]) @ gt[b])
            admitted = result.inliers >= MIN_INLIERS[descriptor]
            if rot < bounds[0] and trans < bounds[1]:
                right += admitted
            else:
                wrong += admitted
    assert wrong == 0
    assert right >= 40, right  # of 51 right registrations with either descriptor (FPFH 50, learned 47 admitted)


def test_bad_descriptor_settings_are_input_errors(boxes_learned):
    f, voxel = boxes_learned
    with pytest.raises(InputError, match="unknown descriptor"):
        compute_features(f.points, voxel, descriptor="shot")
    with pytest.raises(InputError, match="descriptor must be one of"):
        Config(descriptor="shot").validate()
    with pytest.raises(InputError, match="choose one"):  # given descriptors are matched as they are
        Config(descriptor="learned", features="somewhere").validate()
    assert Config(descriptor="learned", min_inliers=20).validate().inlier_bar == 20  # an explicit bar wins
