"""The whole-model check (one rigid alignment, then per-scan errors) and the paper's recall with unplaced fragments."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.evaluate import (
    align_rigid,
    registration_recall,
    registration_recall_counting_unplaced,
    score_run,
    whole_model_errors,
)
from sghr_gtsam.io.poses import read_gt_info, read_gt_log, read_poses
from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.types import InputError

seeds = st.integers(0, 2**32 - 1)


def _random_T(rng: np.random.Generator, scale: float = 3.0) -> np.ndarray:
    return make_T(Rotation.random(random_state=rng.integers(2**32)).as_matrix(), rng.normal(scale=scale, size=3))


def _trajectory(rng: np.random.Generator, n: int) -> np.ndarray:
    """GT poses whose positions span 3-D (the alignment is then unique)."""
    return np.stack([_random_T(rng) for _ in range(n)])


@settings(max_examples=50, deadline=None)
@given(seeds, st.integers(4, 30))
def test_a_rigid_transform_of_gt_is_recovered_exactly(seed, n):
    rng = np.random.default_rng(seed)
    gt = _trajectory(rng, n)
    G = _random_T(rng, 10.0)
    est = G[None] @ gt  # the same model in another world frame
    err = whole_model_errors([f"s{k}" for k in range(n)], est, gt)
    np.testing.assert_allclose(err.alignment, inv_T(G), atol=1e-8)
    assert err.rotation_deg.max() < 1e-5 and err.translation.max() < 1e-8 and err.ate_rmse < 1e-8
    assert err.within(1e-4, 1e-6).all() and err.doubted(1e-4, 1e-6) == []


@settings(max_examples=50, deadline=None)
@given(seeds, st.integers(4, 30), st.floats(1.0, 90.0))
def test_a_scan_turned_in_place_shows_its_angle_and_no_other_scan_moves(seed, n, angle):
    rng = np.random.default_rng(seed)
    gt = _trajectory(rng, n)
    est = _random_T(rng)[None] @ gt
    bad = int(rng.integers(n))
    axis = rng.normal(size=3)
    est[bad, :3, :3] = (
        est[bad, :3, :3] @ Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).as_matrix()
    )
    err = whole_model_errors([f"s{k}" for k in range(n)], est, gt)  # positions untouched: alignment exact
    assert err.rotation_deg[bad] == pytest.approx(angle, abs=1e-6)
    assert np.delete(err.rotation_deg, bad).max() < 1e-5 and err.translation.max() < 1e-8
    assert err.doubted(angle / 2, 1e-6) == [f"s{bad}"]


@settings(max_examples=50, deadline=None)
@given(seeds, st.integers(0, 20), st.floats(0.2, 2.0))
def test_a_displaced_scan_is_the_worst_and_alignment_never_beats_gt_frame(seed, extra, shift):
    rng = np.random.default_rng(seed)
    # positions spread over a 6 m cube (its corners plus points inside), so no scan can pull the alignment alone
    corners = np.array([[x, y, z] for x in (-3, 3) for y in (-3, 3) for z in (-3, 3)], float)
    positions = np.concatenate([corners, rng.uniform(-3, 3, size=(extra, 3))])
    n = len(positions)
    gt = np.stack([make_T(Rotation.random(random_state=rng.integers(2**32)).as_matrix(), p) for p in positions])
    est = gt.copy()
    bad = int(rng.integers(n))
    direction = rng.normal(size=3)
    est[bad, :3, 3] += shift * direction / np.linalg.norm(direction)
    err = whole_model_errors([f"s{k}" for k in range(n)], est, gt)
    # the alignment minimises the squared position errors, and GT's own frame (error `shift` on one scan) is a candidate
    assert err.ate_rmse <= shift / np.sqrt(n) + 1e-9
    assert int(np.argmax(err.translation)) == bad and err.translation[bad] >= shift / 2


@settings(max_examples=30, deadline=None)
@given(seeds, st.integers(3, 40))
def test_align_rigid_is_a_least_squares_minimum_and_a_proper_rotation(seed, n):
    rng = np.random.default_rng(seed)
    src = rng.normal(size=(n, 3))
    dst = (
        src @ Rotation.random(random_state=rng.integers(2**32)).as_matrix().T
        + rng.normal(size=3)
        + rng.normal(scale=0.3, size=(n, 3))
    )
    A = align_rigid(src, dst)
    assert np.linalg.det(A[:3, :3]) == pytest.approx(1.0) and np.allclose(A[:3, :3].T @ A[:3, :3], np.eye(3))

    def cost(T):
        return np.sum((dst - src @ T[:3, :3].T - T[:3, 3]) ** 2)

    for _ in range(5):
        nudge = make_T(Rotation.from_rotvec(rng.normal(scale=0.01, size=3)).as_matrix(), rng.normal(scale=0.01, size=3))
        assert cost(A) <= cost(nudge @ A) + 1e-12


def test_align_rigid_never_returns_a_reflection():
    src = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]])
    A = align_rigid(src, src * np.array([1, 1, -1]))  # the mirror image: best proper rotation, not the mirror
    assert np.linalg.det(A[:3, :3]) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        align_rigid(src, src[:3])


def _ring(n: int) -> tuple[list[str], np.ndarray, dict, dict]:
    """n fragments on a circle, every pair in a gt.log with identity information."""
    poses = np.stack(
        [
            make_T(
                Rotation.from_euler("z", 360.0 * k / n, degrees=True).as_matrix(),
                [np.cos(2 * np.pi * k / n), np.sin(2 * np.pi * k / n), 0.1 * k],
            )
            for k in range(n)
        ]
    )
    log = {(a, b): inv_T(poses[a]) @ poses[b] for a in range(n) for b in range(a + 1, n)}
    return [f"cloud_bin_{k}.ply" for k in range(n)], poses, log, {p: np.eye(6) for p in log}


def test_an_unplaced_fragment_fails_its_pairs_where_the_old_recall_skips_them():
    _, gt, log, info = _ring(8)
    keep = [k for k in range(8) if k != 3]
    skipping = registration_recall(keep, gt[keep], log, info)
    counting = registration_recall_counting_unplaced(keep, gt[keep], log, info, scene_ids=list(range(8)))
    scored = {(a, b) for a in range(8) for b in range(a + 2, 8)}  # |i - j| > 1
    lost = {p for p in scored if 3 in p}
    assert skipping.recall == 1.0 and len(skipping.pairs) == len(scored - lost)
    assert len(counting.pairs) == len(scored)
    assert counting.recall == pytest.approx(len(scored - lost) / len(scored))
    # a fragment outside the scene (the kitchen folder holds 9 of 60) is no failure
    outside = registration_recall_counting_unplaced(keep, gt[keep], log, info, scene_ids=keep)
    assert outside.recall == 1.0 and len(outside.pairs) == len(skipping.pairs)


def test_score_run_counts_unregistered_and_missing_scans_and_names_the_doubted_one():
    names, gt, log, info = _ring(8)
    est = _random_T(np.random.default_rng(0))[None] @ gt
    est[5] = est[5] @ make_T(Rotation.from_euler("x", 60, degrees=True).as_matrix(), np.zeros(3))
    est[2] = np.eye(4)  # garbage pose of a scan the run could not place: must not count
    run_names = names[:7]  # the run never loaded the last scan
    score = score_run(
        run_names, est[:7], names, gt, unregistered=[names[2]], flagged=[names[5], names[2]], gt_log=log, gt_info=info
    )
    assert score.scans == 8 and len(score.placed) == 6
    assert score.unregistered == [names[2], names[7]] and score.flagged == [names[5]]
    assert score.doubted == [names[5]] and score.within == 5 and score.unflagged_wrong == []
    assert score_run(run_names, est[:7], names, gt, unregistered=[names[2]]).unflagged_wrong == [names[5]]
    # pairs with 2 or 7 fail (unplaced), pairs with 5 fail (60°: quaternion part 0.5 > 0.2), the rest are right
    scored = [(a, b) for a in range(8) for b in range(a + 2, 8)]
    right = [p for p in scored if not {2, 5, 7} & set(p)]
    assert score.recall.recall == pytest.approx(len(right) / len(scored))
    few = score_run(run_names, est[:7], names, gt, flagged=names[2:7])  # two unflagged: no alignment to judge by
    assert few.certain is None and few.unflagged_wrong == []
    with pytest.raises(InputError):
        score_run(["elsewhere.ply"], est[:1], names, gt)
    with pytest.raises(InputError):
        score_run(names[:2], est[:2], names, gt, unregistered=names[:2])


def test_ground_truth_scores_perfectly_on_the_kitchen(data_dir):
    gt_dir = data_dir / "kitchen" / "gt"
    names, gt = read_poses(gt_dir / "gt_poses.txt")
    score = score_run(
        names, gt, names, gt, gt_log=read_gt_log(gt_dir / "gt.log"), gt_info=read_gt_info(gt_dir / "gt.info")
    )
    assert score.recall.recall == 1.0 and score.within == len(names) and score.whole.ate_rmse < 1e-9


def test_score_result_reads_the_runs_own_lists():
    from types import SimpleNamespace

    from sghr_gtsam.evaluate import score_result
    from sghr_gtsam.verify import Part, Verdict

    names, gt, _, _ = _ring(6)
    doubts = {names[4]: "single registration", names[0]: "free space"}
    placed = [n for n in names if n != names[1]]
    verdict = Verdict(
        parts=[Part(0, placed)], status={n: "doubtful" if n in doubts else "verified" for n in placed}, doubts=doubts
    )
    result = SimpleNamespace(names=names, poses=gt, unregistered=[names[1]], verdict=verdict)
    score = score_result(result, names, gt)
    assert score.unregistered == [names[1]] and score.flagged == [names[0], names[4]] and score.within == 5
    assert score.recall is None


@settings(max_examples=30, deadline=None)
@given(seeds, st.integers(2, 5), st.floats(1.0, 20.0))
def test_a_flagged_group_placed_far_off_does_not_make_the_unflagged_scans_read_wrong(seed, group, shift):
    """Aligned on every scan, a misplaced group drags the right ones out of tolerance; aligned on the unflagged
    scans alone, they are right, and a misplaced scan left unflagged is named (with whatever its pull on the
    alignment carries out of tolerance)."""
    rng = np.random.default_rng(seed)
    gt = _trajectory(rng, 10)
    names = [f"s{k}" for k in range(10)]
    est = _random_T(rng)[None] @ gt
    est[:group] = make_T(np.eye(3), np.array([shift, 0.0, 0.0])) @ est[:group]
    score = score_run(names, est, names, gt, flagged=names[:group])
    assert score.unflagged_wrong == [] and score.certain.within(5.0, 0.2).tolist() == [False] * group + [True] * (
        10 - group
    )
    assert names[0] in score_run(names, est, names, gt, flagged=names[1:group]).unflagged_wrong


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_pose_alignment_recovers_a_rigid_change_of_world(seed):
    rng = np.random.default_rng(seed)
    gt = np.stack(
        [
            make_T(Rotation.random(random_state=rng.integers(2**31)).as_matrix(), rng.normal(size=3) * 0.01)
            for _ in range(6)
        ]
    )  # an object's scans: positions nearly coincide
    A = make_T(Rotation.random(random_state=rng.integers(2**31)).as_matrix(), rng.normal(size=3))
    w = whole_model_errors([str(k) for k in range(6)], inv_T(A)[None] @ gt, gt, align="poses")
    assert w.rotation_deg.max() < 1e-4 and w.translation.max() < 1e-9  # arccos resolves ~1e-6 deg


@settings(max_examples=50, deadline=None)
@given(seeds, st.sampled_from(["two", "one line"]))
def test_positions_that_leave_a_rotation_free_are_aligned_with_the_rotations(seed, layout):
    """Two positions (``demo --scans 2``) or any on one line leave the rotation about their line free: the SVD
    picked one, and two right scans read "0 of 2 within tolerance". The rotations fix it."""
    rng = np.random.default_rng(seed)
    gt = _trajectory(rng, 2 if layout == "two" else 5)
    if layout == "one line":
        gt[:, :3, 3] = np.linspace(-3.0, 3.0, len(gt))[:, None] * rng.normal(size=3)
    G = _random_T(rng, 10.0)
    err = whole_model_errors([f"s{k}" for k in range(len(gt))], G[None] @ gt, gt)
    np.testing.assert_allclose(err.alignment, inv_T(G), atol=1e-8)
    assert err.within(1e-4, 1e-6).all()
