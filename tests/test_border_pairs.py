"""data_tools.border_pairs: which border pairs overlap, the move each registration proposes, and families of
moves that agree."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from data_tools.border_pairs import Registration, border_pairs, families, group_moves
from sghr_gtsam.se3 import inv_T, make_T, relative_errors


def _agree(a: np.ndarray, b: np.ndarray, tolerance=(5.0, 0.2)) -> bool:
    rot, trans = relative_errors(a[None], b[None])
    return bool(rot[0] <= tolerance[0] and trans[0] <= tolerance[1])


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**31 - 1), st.integers(1, 12))
def test_families_partition_the_moves_into_groups_that_agree(seed, n):
    rng = np.random.default_rng(seed)
    # A few placements, each proposed by some moves with small errors: the clusters a border's registrations form.
    centres = [
        make_T(Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.uniform(-3, 3, 3)) for _ in range(3)
    ]
    noise = [make_T(Rotation.from_rotvec(rng.normal(0, 0.03, 3)).as_matrix(), rng.normal(0, 0.05, 3)) for _ in range(n)]
    moves = np.stack([centres[rng.integers(3)] @ e for e in noise])
    weights = rng.uniform(1, 50, n)
    found = families(moves, weights)
    assert sorted(k for f in found for k in f) == list(range(n))  # a partition
    for f in found:
        assert all(_agree(moves[a], moves[b]) for a in f for b in f)
    # Greedy and maximal: a move left to a later family disagrees with some member of every earlier one.
    for x, f in enumerate(found):
        for later in found[x + 1 :]:
            assert all(any(not _agree(moves[k], moves[m]) for m in f) for k in later)
    assert found[0][0] == int(np.argmax(weights))  # the heaviest move seeds the first family


def test_right_registrations_propose_no_move_and_agree():
    rng = np.random.default_rng(0)
    poses = np.stack([make_T(Rotation.random(random_state=k).as_matrix(), rng.uniform(-4, 4, 3)) for k in range(5)])
    turn = make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.zeros(3))
    right = [Registration(a, b, inv_T(poses[a]) @ poses[b], 30, True) for a, b in [(0, 3), (1, 3), (2, 4)]]
    # Two look-alikes that put the group turned 90° about the same place; one turned 90° about another place.
    wrong = [Registration(a, b, inv_T(poses[a]) @ turn @ poses[b], 40, False) for a, b in [(0, 4), (1, 4)]]
    far = make_T(turn[:3, :3], np.array([2.0, 0.0, 0.0]))
    wrong.append(Registration(2, 3, inv_T(poses[2]) @ far @ poses[3], 50, False))
    registrations = right + wrong
    moves = group_moves(poses, registrations, centre=np.zeros(3))
    np.testing.assert_allclose(moves[:3], np.broadcast_to(np.eye(4), (3, 4, 4)), atol=1e-9)
    found = families(moves, [r.inliers for r in registrations])
    assert sorted(map(sorted, found)) == [[0, 1, 2], [3, 4], [5]]


def test_border_pairs_are_the_overlapping_pairs_across_the_group():
    rng = np.random.default_rng(1)
    wall = np.c_[rng.uniform(0, 2, (4000, 2)), np.zeros(4000)]  # a 2 m square, seen by scans 0, 1 and 3
    poses = np.stack([np.eye(4), np.eye(4), make_T(np.eye(3), np.array([10.0, 0, 0])), np.eye(4)])
    corner = wall[wall[:, 0] < 0.3]  # 15 % of the wall
    scans = [wall, wall + rng.normal(0, 0.002, wall.shape), wall, corner]  # scan 2 is 10 m away
    pairs = border_pairs(scans, poses, group={1, 2}, voxel=0.05)
    # Scan 3 covers 15 % of scan 1, but all of scan 3 lies on scan 1: the larger direction counts.
    assert pairs == [(0, 1), (3, 1)]
    assert border_pairs(scans, poses, group={3}, voxel=0.05) == [(0, 3), (1, 3)]
    assert border_pairs(scans, poses, group={1, 2}, voxel=0.05, min_overlap=None) == [(0, 1), (0, 2), (3, 1), (3, 2)]
