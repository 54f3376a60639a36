"""The generated building (data_tools.building): a connected, sparse, 3DMatch-like ground truth with long cycles."""

import numpy as np
import pytest

from data_tools.building import make_building
from data_tools.outlier_graphs import SCAN_CENTRE, corrupt, make_graph
from sghr_gtsam.evaluate import registration_recall
from sghr_gtsam.graph import top_k_edges
from sghr_gtsam.se3 import inv_T, relative_errors
from sghr_gtsam.sync.baselines import oracle
from sghr_gtsam.sync.rotation import connected_components

N = 200


@pytest.fixture(scope="module")
def gt():
    return make_building(N, seed=0)


def test_overlap_is_a_symmetric_fraction(gt):
    overlap = gt.overlap
    assert overlap.shape == (N, N) and np.array_equal(overlap, overlap.T)
    assert overlap.min() >= 0.0 and overlap.max() <= 1.0 and not np.diag(overlap).any()
    consecutive = overlap[np.arange(N - 1), np.arange(1, N)]
    assert np.median(consecutive) > 0.4  # a hand-held walk: neighbours in time see much the same


def test_top_k_graph_is_connected_sparse_and_has_long_cycles(gt):
    i, j = top_k_edges(gt.overlap, 10).T
    assert 5 * N <= len(i) <= 7 * N  # ~N·k/2 plus the one-sided choices, as the real scenes' 11.5–12.7 a scan
    assert (connected_components(N, i, j, np.ones(len(i), dtype=bool)) == 0).all()
    assert np.mean(gt.overlap[i, j] == 0) < 0.01  # edges between scans that share nothing (real: 0–13 %)
    assert np.mean(np.abs(i - j) > 50) > 0.05  # revisits after a long detour, not one dense blob


def test_gt_pairs_are_the_overlapping_ones_with_positive_definite_information(gt):
    pairs = np.array(sorted(gt.gt_log))
    assert len(pairs) > 2 * N
    assert (gt.overlap[pairs[:, 0], pairs[:, 1]] > 0.3).all()
    assert np.count_nonzero(np.triu(gt.overlap, 1) > 0.3) == len(pairs)
    for (a, b), info in gt.gt_info.items():
        np.testing.assert_allclose(gt.gt_log[(a, b)], inv_T(gt.poses[a]) @ gt.poses[b], atol=1e-12)
        assert np.allclose(info[:3, :3], info[0, 0] * np.eye(3))  # count · I, as 3DMatch's gt.info
        assert np.linalg.eigvalsh(info / info[0, 0]).min() > 1e-4
    assert registration_recall(gt.ids, gt.poses, gt.gt_log, gt.gt_info).recall == 1.0


def test_scans_are_camera_views_at_hand_height(gt):
    assert np.all((gt.poses[:, 2, 3] >= 1.2) & (gt.poses[:, 2, 3] <= 1.8))
    forward = gt.poses[:, :3, 2]  # camera z
    assert np.degrees(np.arcsin(np.abs(forward @ gt.vertical))).max() < 45.0  # roughly horizontal
    # The corruption turns a scan about SCAN_CENTRE: 2.3 m ahead of the camera is inside the building.
    centres = gt.poses[:, :3, :3] @ SCAN_CENTRE + gt.poses[:, :3, 3]
    assert np.all((centres[:, 2] > 0.0) & (centres[:, 2] < 3.0))


@pytest.mark.parametrize("seed", [0, 1])
def test_oracle_recovers_the_building_without_outliers(seed):
    truth = make_building(N, seed)
    graph, P, outlier = make_graph(f"gen{N}", 0.0, "random", seed)
    assert not outlier.any() and np.array_equal(P, truth.poses)
    poses = oracle(graph, ~outlier).poses
    assert registration_recall(truth.ids, poses, truth.gt_log, truth.gt_info).recall >= 0.99
    a, b = np.triu_indices(N, 1)
    rot, trans = relative_errors(inv_T(poses[a]) @ poses[b], inv_T(P[a]) @ P[b])
    assert np.mean((rot <= 5.0) & (trans <= 0.2)) > 0.9  # drift over the whole floor stays small


def test_corruption_of_a_building_matches_its_ratio_and_kind(gt):
    for kind in ("random", "structured"):
        graph, _, outlier = corrupt(gt, 0.5, kind, seed=0)
        assert outlier.sum() == round(0.5 * graph.num_edges)


def test_too_few_scans_are_refused():
    with pytest.raises(ValueError, match="at least 20 scans"):
        make_building(5, 0)
