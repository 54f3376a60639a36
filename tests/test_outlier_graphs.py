"""The robustness benchmark's graph generator, checked against the 3DMatch ground truth it is built from."""

import hashlib

import numpy as np
import pytest

from data_tools.outlier_graphs import KINDS, SCAN_CENTRE, SCENES, load_scene, make_graph
from sghr_gtsam.evaluate import registration_recall
from sghr_gtsam.se3 import inv_T, relative_errors

pytestmark = pytest.mark.data


def _placement_gap(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation (degrees) and scan-centre distance (m) between placements A and B (..., 4, 4) of a scan."""
    rot, _ = relative_errors(A, B)
    centre = np.append(SCAN_CENTRE, 1.0)
    return rot, np.linalg.norm((A - B) @ centre, axis=-1)


@pytest.mark.parametrize("scene", SCENES)
def test_gt_loader_scores_gt_poses_as_fully_recalled(data_dir, scene):
    gt = load_scene(scene, data_dir)
    assert np.isfinite(gt.poses).all() and len(gt.ids) == len(gt.poses)
    result = registration_recall(gt.ids, gt.poses, gt.gt_log, gt.gt_info)
    assert len(result.pairs) > 0 and result.recall == 1.0


@pytest.mark.parametrize("noisy", [False, True])
@pytest.mark.parametrize("kind", KINDS)
def test_inliers_carry_the_stated_noise_and_outliers_are_far(data_dir, kind, noisy):
    rot_in, centre_in = [], []
    for scene in SCENES:
        graph, P, out = make_graph(scene, 0.4, kind, seed=1, noisy_overlap=noisy, root=data_dir)
        # Edge T_ij places scan j relative to scan i: compare with where GT puts it.
        rot, centre = _placement_gap(P[graph.i] @ graph.T, P[graph.j])
        rot_in.append(rot[~out])
        centre_in.append(centre[~out])
        assert ((rot[out] > 15.0) | (centre[out] > 0.5)).all()
        assert graph.num_edges >= 5 * graph.n  # top-10 union: between N·10/2 and N·10 edges
        assert np.all(graph.weight > 0)
    rot_in, centre_in = np.concatenate(rot_in), np.concatenate(centre_in)
    assert 1.85 < rot_in.mean() < 2.15 and rot_in.max() < 8.0  # mean 2°, Maxwell tail
    assert 0.045 < centre_in.mean() < 0.055 and centre_in.max() < 0.25  # mean 5 cm at the scan's centre


@pytest.mark.parametrize("kind", KINDS)
def test_outlier_fraction_is_as_asked_and_prefers_low_overlap(data_dir, kind):
    low, high = [], []
    for ratio in (0.0, 0.1, 0.3, 0.6):
        for scene in SCENES:
            graph, _, out = make_graph(scene, ratio, kind, seed=2, root=data_dir)
            assert out.sum() == round(ratio * graph.num_edges)
            if 0 < ratio:
                overlap = load_scene(scene, data_dir).overlap[graph.i, graph.j]
                low.append(overlap[out].mean())
                high.append(overlap[~out].mean())
    assert np.mean(low) < np.mean(high)


def test_ratio_zero_is_the_same_inlier_graph_for_both_kinds(data_dir):
    a, _, _ = make_graph(SCENES[0], 0.0, "random", seed=3, root=data_dir)
    b, _, _ = make_graph(SCENES[0], 0.0, "structured", seed=3, root=data_dir)
    np.testing.assert_array_equal(a.T, b.T)
    np.testing.assert_array_equal(a.weight, b.weight)


@pytest.mark.parametrize("ratio", [0.1, 0.5])
def test_structured_outliers_repeat_one_wrong_placement(data_dir, ratio):
    for scene in SCENES:
        graph, P, out = make_graph(scene, ratio, "structured", seed=4, root=data_dir)
        edges = np.flatnonzero(out)
        # Where each outlier edge places each of its two scans, given the other at its GT pose.
        place_j = P[graph.i] @ graph.T
        place_i = P[graph.j] @ inv_T(graph.T)
        placements = {}  # scan -> list of (edge, wrong placement)
        for e in edges:
            for scan, placed in ((graph.j[e], place_j[e]), (graph.i[e], place_i[e])):
                rot, centre = _placement_gap(placed, P[scan])
                if rot > 15.0 or centre > 0.5:
                    placements.setdefault(scan, []).append((e, placed))
        for e in edges:
            shared = False
            for scan in (graph.i[e], graph.j[e]):
                mine = [T for f, T in placements.get(scan, []) if f == e]
                others = [T for f, T in placements.get(scan, []) if f != e]
                for A in mine:
                    for B in others:
                        rot, centre = _placement_gap(A, B)
                        # The 2° noise acts about the other scan's centre, metres away: allow its lever arm.
                        shared |= rot < 10.0 and centre < 0.6
            assert shared, f"{scene}: outlier edge {e} shares its wrong placement with no other edge"


# Digests of make_graph's arrays: the edges and the outlier mask exactly, the transforms, weights and GT poses
# rounded to 1e-8 (the published robustness tables depend on these graphs). The byte-exact digests recorded at
# 245048d stopped matching on a fresh install (numpy 2.4.6, scipy 1.17.1) at 455a186 too, where the code had not
# changed: float64 last bits differ between builds, so they are compared rounded. Re-recorded at that install.
_RECORDED = {
    (SCENES[0], 0, 0.0, "random", False, "s*r"): "683a81bac0988fc12a0e73dca4a266ab",
    (SCENES[1], 1, 0.3, "random", False, "s*r"): "27cf2de647bd107fe20de12183c92f5c",
    (SCENES[3], 2, 0.6, "structured", False, "s*r"): "2e19416b30080bffa4ffe2f746ee3dd7",
    (SCENES[7], 3, 0.5, "structured", True, "r"): "0c1e6e110fba99f9c4ee42cd4df9a803",
    (SCENES[5], 4, 0.7, "random", True, "s"): "83caca9a25e4380edddaaab3dfad17e8",
}


@pytest.mark.parametrize("case", list(_RECORDED), ids=lambda c: f"{c[0][:12]}-{c[2]}-{c[3]}")
def test_real_scene_graphs_are_as_recorded(data_dir, case):
    scene, seed, ratio, kind, noisy, weight = case
    graph, P, out = make_graph(scene, ratio, kind, seed, noisy_overlap=noisy, root=data_dir, weight=weight)
    assert out.mean() == pytest.approx(ratio, abs=0.01)
    digest = hashlib.sha256()
    for a in (graph.i, graph.j, out):
        digest.update(np.ascontiguousarray(a).tobytes())
    for a in (graph.T, graph.weight, P):
        digest.update(np.ascontiguousarray(np.round(a, 8) + 0.0).tobytes())  # + 0.0: no negative zeros
    assert digest.hexdigest()[:32] == _RECORDED[case]
