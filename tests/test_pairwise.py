"""Local features and pairwise registration: a generated scene with a known transform, and real pairs
of the 3DMatch kitchen and the Stanford bunny against their ground truth."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.distance import pdist, squareform
from scipy.spatial.transform import Rotation

from sghr_gtsam.features.local import compute_features, default_voxel
from sghr_gtsam.registration.estimators import _compatibility, _first_stage, _pick_seeds, sc2_estimate
from sghr_gtsam.registration.information import registration_information
from sghr_gtsam.registration.pairwise import mutual_matches, register_pair, score_pair
from sghr_gtsam.se3 import inv_T, make_T, relative_errors, transform_points
from sghr_gtsam.types import InputError


def boxes_scene(seed: int, layout: int = 0, n_boxes: int = 12, density: float = 4000.0) -> np.ndarray:
    """Points sampled (by ``seed``) on the surfaces of randomly sized, placed and rotated boxes (chosen
    by ``layout``) in a 4 m cube."""
    rng = np.random.default_rng(seed)
    box_rng = np.random.default_rng(layout)
    parts = []
    for _ in range(n_boxes):
        size = box_rng.uniform(0.2, 1.0, 3)
        R = Rotation.random(random_state=box_rng.integers(1 << 31)).as_matrix()
        centre = box_rng.uniform(-2.0, 2.0, 3)
        for axis in range(3):
            u, w = [a for a in range(3) if a != axis]
            n = int(density * size[u] * size[w])
            for side in (-0.5, 0.5):
                p = rng.uniform(-0.5, 0.5, (n, 3)) * size
                p[:, axis] = side * size[axis]
                parts.append(p @ R.T + centre)
    return np.concatenate(parts)


@pytest.fixture(scope="module")
def boxes():
    T_ij = make_T(Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix(), np.array([0.7, -0.4, 0.3]))
    scan_i = boxes_scene(seed=1)
    scan_j = transform_points(inv_T(T_ij), boxes_scene(seed=2))  # same surfaces, other samples
    voxel = default_voxel([scan_i, scan_j])
    return T_ij, voxel, compute_features(scan_i, voxel), compute_features(scan_j, voxel)


def test_features_are_well_formed(boxes):
    _, _, fi, _ = boxes
    assert fi.points.shape == fi.normals.shape == (len(fi), 3) and fi.points.dtype == np.float64
    assert fi.fpfh.shape == (len(fi), 33) and fi.fpfh.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(fi.normals, axis=1), 1.0, atol=1e-6)
    assert np.all(np.einsum("ij,ij->i", fi.normals, -fi.points) >= 0)  # towards the scan's origin


@pytest.mark.parametrize("matcher", ["sc2", "kiss", "ransac"])
def test_known_transform_is_recovered(boxes, matcher):
    T_ij, voxel, fi, fj = boxes
    result = register_pair(fi, fj, voxel, matcher=matcher)
    rot, trans = relative_errors(result.T, T_ij)
    assert rot < 0.1 and trans < 0.05 * voxel, (rot, trans)
    assert result.inliers > 100
    assert result.fitness > 0.9 and result.rmse < 0.5 * voxel


def test_information_is_the_calibrated_point_to_plane_one(boxes):
    _, voxel, fi, fj = boxes
    result = register_pair(fi, fj, voxel)
    np.testing.assert_allclose(result.information, registration_information(fi, fj, result.T, 1.5 * voxel).matrix)
    assert np.all(np.linalg.eigvalsh(result.information) > 0)


def test_a_registration_under_the_bar_is_the_same_but_gets_no_information(boxes):
    """``min_inliers`` decides the information only: the transform and its score do not depend on it."""
    _, voxel, fi, fj = boxes
    free, barred = register_pair(fi, fj, voxel), register_pair(fi, fj, voxel, min_inliers=10**6)
    np.testing.assert_array_equal(barred.T, free.T)
    assert (barred.inliers, barred.fitness) == (free.inliers, free.fitness)
    assert free.information is not None and barred.information is None
    assert register_pair(fi, fj, voxel, min_inliers=free.inliers).information is not None


def test_unrelated_scans_give_few_inliers(boxes):
    # sc2 maximises agreement, so between unrelated box scenes it lines up one box with another: a
    # tenth of the right pair's inliers, but crowded in a few cells.
    _, voxel, fi, fj = boxes
    other = compute_features(boxes_scene(seed=3, layout=1), voxel)
    right, wrong = register_pair(fi, fj, voxel), register_pair(fi, other, voxel)
    assert wrong.inliers < 0.15 * right.inliers, (wrong.inliers, right.inliers)
    assert wrong.coverage < 0.15 * right.coverage, (wrong.coverage, right.coverage)
    assert register_pair(fi, other, voxel, matcher="kiss").inliers < 0.05 * right.inliers


def test_bad_arguments_are_input_errors(boxes):
    _, voxel, fi, fj = boxes
    with pytest.raises(InputError):
        register_pair(fi, fj, voxel, matcher="teaser")
    with pytest.raises(InputError):
        compute_features(np.zeros((10, 2)), voxel)
    with pytest.raises(InputError):
        default_voxel([])


@settings(max_examples=25, deadline=None)
@given(angle=st.floats(0.0, 3.0), shift=st.floats(0.0, 4.0), axis=st.integers(0, 2), sign=st.sampled_from([-1, 1]))
def test_a_score_without_matches_is_the_score_on_every_mutual_match(boxes, angle, shift, axis, sign):
    """A loop closure is scored without the pair's matches (``agreeing_matches`` looks up only the points that
    can agree): the same inliers, cells and everything else as on all mutual matches, at the right transform and
    at transforms a few voxels to half a turn off it."""
    T_ij, voxel, fi, fj = boxes
    off = make_T(Rotation.from_rotvec(sign * angle * np.eye(3)[axis]).as_matrix(), shift * voxel * np.eye(3)[axis - 1])
    T = T_ij @ off
    alone, full = score_pair(fi, fj, T, voxel, 1.5), score_pair(fi, fj, T, voxel, 1.5, mutual_matches(fi, fj))
    assert (alone.inliers, alone.coverage, alone.fitness, alone.rmse) == (
        full.inliers,
        full.coverage,
        full.fitness,
        full.rmse,
    )
    np.testing.assert_array_equal(alone.information, full.information)
    assert alone.matches is None


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), inlier_fraction=st.sampled_from([0.03, 0.1, 0.5, 1.0]))
def test_sc2_recovers_a_transform_among_outliers(seed, inlier_fraction):
    """Correspondences on a 4 m scene at a 4 cm voxel, a random rigid transform, inliers perturbed by up to
    a third of a voxel and the rest drawn anywhere: the estimate is within the noise of the truth and
    its inliers are the true ones (an outlier lands within 1.5 voxels by chance only rarely)."""
    rng = np.random.default_rng(seed)
    voxel, n = 0.04, 800
    T = make_T(Rotation.random(random_state=seed).as_matrix(), rng.uniform(-2, 2, 3))
    p_j = rng.uniform(-2, 2, (n, 3))
    p_i = transform_points(T, p_j) + rng.uniform(-1, 1, (n, 3)) * voxel / (3 * np.sqrt(3))
    good = np.arange(n) < max(24, int(inlier_fraction * n))
    p_i[~good] = rng.uniform(-2, 2, (int(np.sum(~good)), 3)) + T[:3, 3]
    est = sc2_estimate(p_i, p_j, voxel)
    rot, trans = relative_errors(est.T, T)
    assert rot < 0.5 and trans < 0.5 * voxel, (rot, trans)
    assert np.all(est.inliers[good]) and np.sum(est.inliers[~good]) <= 0.02 * n
    np.testing.assert_array_equal(sc2_estimate(p_i, p_j, voxel).T, est.T)  # deterministic


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(3, 120), density=st.floats(0.02, 0.9), k1=st.integers(1, 40))
def test_sc2_first_stage_ranks_each_seed_by_its_definition(seed, n, density, k1):
    """The batched first stage (one product for every seed) picks, per seed, the correspondences compatible with
    it ranked by how many are compatible with both, ties by index, padded with the seed: the per-seed definition
    on its compatible set alone (``sc2_estimate`` asks for at most as many as there are correspondences)."""
    k1 = min(k1, n)
    rng = np.random.default_rng(seed)
    C = (rng.random((n, n)) < density).astype(np.float32)
    C = np.maximum(C, C.T)
    np.fill_diagonal(C, 1.0)
    seeds = rng.choice(n, size=min(n, 10), replace=False)
    for s, picked in zip(seeds, _first_stage(C, seeds, k1)):
        nbr = np.flatnonzero(C[s])
        both = C[np.ix_(nbr, nbr)].sum(axis=1)
        ranked = nbr[sorted(range(len(nbr)), key=lambda m: (-both[m], m))][:k1]
        np.testing.assert_array_equal(picked, np.concatenate([ranked, np.full(k1 - len(ranked), s)]))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 300), spread=st.floats(1.0, 50.0))
def test_sc2_compatibility_tests_each_pair_by_its_distances(seed, n, spread):
    """The banded matrix is, to the bit, each pair's test on pdist's distances, mirrored, with a unit diagonal."""
    rng = np.random.default_rng(seed)
    a, b = rng.uniform(0, spread, (n, 3)), rng.uniform(0, spread, (n, 3))
    C = squareform((np.abs(pdist(a) - pdist(b)) < 2.0).astype(np.float32))
    np.fill_diagonal(C, 1.0)
    np.testing.assert_array_equal(_compatibility(a, b, 2.0), C)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 400), spread=st.floats(1.0, 30.0), count=st.integers(1, 120))
def test_sc2_seeds_are_the_greedy_suppression(seed, n, spread, count):
    """The blocked non-maximum suppression picks what the greedy pass over all correspondences picks: by
    decreasing score (ties by index), each one unless an earlier seed lies within the radius."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(0, spread, (n, 3))
    score = rng.integers(0, 5, n).astype(np.float32)  # ties
    seeds: list[int] = []
    taken = np.zeros(n, dtype=bool)
    for k in np.argsort(-score, kind="stable"):
        if not taken[k]:
            seeds.append(int(k))
            if len(seeds) == count:
                break
            taken |= np.sum((p - p[k]) ** 2, axis=1) < 2.0**2
    np.testing.assert_array_equal(_pick_seeds(score, p, 2.0, count), seeds)


def test_sc2_with_too_few_correspondences_is_the_identity():
    est = sc2_estimate(np.zeros((2, 3)), np.ones((2, 3)), 0.04)
    np.testing.assert_array_equal(est.T, np.eye(4))
    assert not est.inliers.any()


# --- real data ------------------------------------------------------------------------------------


@pytest.mark.data
def test_default_voxel_fits_both_scenes(kitchen, bunny):
    assert 0.025 <= kitchen[2] <= 0.045  # metres: 3DMatch fragments are a few metres across
    assert 0.0015 <= bunny[2] <= 0.003  # the bunny is ~15 cm


@pytest.mark.data
def test_kitchen_pair_and_a_pair_without_overlap(kitchen):
    gt, scans, voxel = kitchen
    f = {n: compute_features(scans[n], voxel) for n in ("cloud_bin_0.ply", "cloud_bin_1.ply", "cloud_bin_21.ply")}
    right = register_pair(f["cloud_bin_0.ply"], f["cloud_bin_1.ply"], voxel)
    rot, trans = relative_errors(right.T, inv_T(gt["cloud_bin_0.ply"]) @ gt["cloud_bin_1.ply"])
    assert rot < 5.0 and trans < 0.1, (rot, trans)
    # Fragments 1 and 21 do not overlap at all (3DMatch gt_overlap.log: 0.0).
    wrong = register_pair(f["cloud_bin_1.ply"], f["cloud_bin_21.ply"], voxel)
    assert wrong.inliers < 0.1 * right.inliers, (wrong.inliers, right.inliers)


@pytest.mark.data
def test_bunny_pair_is_precise(bunny):
    gt, scans, voxel = bunny
    fi, fj = (compute_features(scans[n], voxel) for n in ("bun000.ply", "bun045.ply"))
    result = register_pair(fi, fj, voxel)
    rot, trans = relative_errors(result.T, inv_T(gt["bun000.ply"]) @ gt["bun045.ply"])
    assert rot < 1.0 and trans < 0.001, (rot, trans)
