"""The verification layer (``verify``): rigid parts from loops of registrations that close within their noise,
joins through one registration or one scan reported and not trusted, one status per scan."""

import json

import networkx as nx
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.sync.consensus import MAX_DEG
from sghr_gtsam.types import PoseGraph
from sghr_gtsam.verify import REASONS, SEEN_THROUGH, STATUSES, Verification, placement_turns, verify


def _poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack(
        [make_T(Rotation.random(random_state=seed + k).as_matrix(), rng.uniform(-3, 3, 3)) for k in range(n)]
    )


def _graph(poses: np.ndarray, edges: list[tuple[int, int]], wrong: dict[int, np.ndarray] | None = None) -> PoseGraph:
    """Exact measurements of ``edges`` between ``poses``; ``wrong[e]`` (4, 4) moves edge e's measurement."""
    i, j = np.array(edges).T
    T = inv_T(poses[i]) @ poses[j]
    for e, move in (wrong or {}).items():
        T[e] = T[e] @ move
    return PoseGraph(
        n=len(poses),
        i=i,
        j=j,
        T=T,
        weight=np.full(len(edges), 10.0),
        information=np.tile(np.eye(6) * 1e4, (len(edges), 1, 1)),
    )


def _verdict(graph: PoseGraph, poses: np.ndarray, kept: np.ndarray | None = None, conflicts: np.ndarray | None = None):
    names = [f"s{k}" for k in range(graph.n)]
    kept = np.ones(graph.num_edges, dtype=bool) if kept is None else kept
    return verify(names, graph, kept, poses, np.ones(graph.n, dtype=bool), Verification(), conflicts=conflicts)


def _conflicting(n: int, pairs: list[tuple[int, int]]) -> np.ndarray:
    """(n, n) symmetric free-space conflicts of ``pairs``."""
    conflicts = np.zeros((n, n), dtype=bool)
    for a, b in pairs:
        conflicts[a, b] = conflicts[b, a] = True
    return conflicts


def _clique(nodes: range) -> list[tuple[int, int]]:
    return [(a, b) for a in nodes for b in nodes if a < b]


def test_a_ring_of_scans_is_one_verified_part():
    """A turntable's scans, each registered to its neighbours: one loop checks every pose."""
    poses = _poses(6, 0)
    verdict = _verdict(_graph(poses, [(k, (k + 1) % 6) for k in range(6)]), poses)
    assert [p.scans for p in verdict.parts] == [[f"s{k}" for k in range(6)]]
    assert verdict.status == {f"s{k}": "verified" for k in range(6)} and verdict.doubts == {}
    assert verdict.trusted() == [f"s{k}" for k in range(6)]


def test_groups_joined_by_one_registration_are_two_parts_and_a_chain_is_all_doubtful():
    poses = _poses(9, 1)
    edges = _clique(range(5)) + _clique(range(5, 9)) + [(4, 5)]
    verdict = _verdict(_graph(poses, edges), poses)
    assert [p.scans for p in verdict.parts] == [[f"s{k}" for k in range(5)], [f"s{k}" for k in range(5, 9)]]
    join = verdict.parts[1].join
    assert join.to == 0 and join.edges == [("s4", "s5")] and "bridge" in join.why
    assert set(verdict.status.values()) == {"verified"}  # right inside each part; the join is what is doubted
    assert verdict.trusted() == [f"s{k}" for k in range(5)]

    chain = _verdict(_graph(poses[:3], [(0, 1), (1, 2)]), poses[:3])
    assert chain.doubts == {"s0": "single registration", "s1": "single registration", "s2": "single registration"}


def test_a_group_hung_on_one_scan_is_a_part_of_its_own():
    """Three registrations of one scan to a group, all agreeing (as a symmetric room's can all be wrong the same
    way): no edge is a bridge, but the group hangs on that one scan (an articulation point)."""
    poses = _poses(9, 2)
    edges = _clique(range(5)) + _clique(range(5, 9)) + [(4, 5), (4, 6), (4, 7)]
    verdict = _verdict(_graph(poses, edges), poses)
    assert [len(p.scans) for p in verdict.parts] == [5, 4]
    assert "articulation point" in verdict.parts[1].join.why


def test_a_scan_shared_by_two_groups_goes_to_the_one_whose_registrations_hold_it_most():
    """Scan 4 closes loops with a large group by two light registrations and with a small one by three heavy ones:
    the groups are placed against each other by scan 4 alone, and it goes with the heavier evidence for its own
    pose, not with the larger group."""
    poses = _poses(8, 8)
    edges = _clique(range(4)) + [(4, 0), (4, 1)] + _clique(range(5, 8)) + [(4, 5), (4, 6), (4, 7)]
    graph = _graph(poses, edges)
    graph.weight[[len(_clique(range(4))), len(_clique(range(4))) + 1]] = 1.0  # 4-0 and 4-1: light
    verdict = _verdict(graph, poses)
    assert [p.scans for p in verdict.parts[:2]] == [["s0", "s1", "s2", "s3"], ["s4", "s5", "s6", "s7"]]
    graph.weight[:] = 10.0  # equal weights: 4's three registrations to the small group still outweigh its two
    assert verdict.parts[1].scans == _verdict(graph, poses).parts[1].scans


def test_a_registration_that_breaks_its_loop_leaves_the_part_and_its_scan_is_doubted():
    """Scan 5 hangs on two registrations; one is 30° off, so their loop does not close within any noise: the
    scan is no longer checked by a loop, and the wrong registration's failure is the reason given."""
    poses = _poses(6, 3)
    edges = _clique(range(5)) + [(0, 5), (1, 5)]
    turn = make_T(Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.zeros(3))
    graph = _graph(poses, edges, {len(edges) - 1: turn})
    verdict = _verdict(graph, poses)  # the poses are the truth: the wrong edge does not fit them
    assert verdict.doubts == {"s5": "loop error"}
    assert [p.scans for p in verdict.parts][0] == [f"s{k}" for k in range(5)]


def test_dropped_registrations_that_agree_on_another_placement_split_the_group_off():
    """A 4-scan group held by two light registrations, while three heavier dropped ones agree on placing it 90°
    turned: the join is disputed and the group is a part of its own, each part verified inside."""
    poses = _poses(9, 4)
    edges = _clique(range(5)) + _clique(range(5, 9)) + [(0, 5), (1, 6), (2, 7), (3, 8), (4, 5)]
    turn = make_T(Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.array([0.5, 0.0, 0.0]))
    graph = _graph(poses, edges)
    for e in range(len(edges) - 5, len(edges) - 2):  # measured as if the group were moved by ``turn`` in the world
        graph.T[e] = inv_T(poses[graph.i[e]]) @ turn @ poses[graph.j[e]]
    graph.weight[len(edges) - 5 : len(edges) - 2] = 40.0
    kept = np.ones(graph.num_edges, dtype=bool)
    kept[len(edges) - 5 : len(edges) - 2] = False
    verdict = _verdict(graph, poses, kept)
    assert [len(p.scans) for p in verdict.parts] == [5, 4]
    assert "another placement" in verdict.parts[1].join.why
    centre = poses[5:9, :3, 3].mean(axis=0)  # the join says how far the other placement lies
    shift = np.linalg.norm(turn[:3, :3] @ centre + turn[:3, 3] - centre)
    np.testing.assert_allclose(verdict.parts[1].join.elsewhere, [90.0, shift], rtol=1e-3)
    assert "90.0° / " in verdict.summary()[1]
    graph.weight[len(edges) - 5 : len(edges) - 2] = 1.0  # lighter than what holds the group: no dispute
    assert [len(p.scans) for p in _verdict(graph, poses, kept).parts] == [9]
    # Heavier, but 15° off: within two error budgets of where the group is (one for the dropped registrations, one
    # for those that hold it), so it is the same placement measured worse, not another one.
    centre = poses[5:9, :3, 3].mean(axis=0)
    turn = make_T(Rotation.from_euler("z", 1.5 * MAX_DEG, degrees=True).as_matrix(), np.zeros(3))
    near = make_T(np.eye(3), centre) @ turn @ make_T(np.eye(3), -centre)  # about the group's centre
    for e in range(len(edges) - 5, len(edges) - 2):
        graph.T[e] = inv_T(poses[graph.i[e]]) @ near @ poses[graph.j[e]]
    graph.weight[len(edges) - 5 : len(edges) - 2] = 40.0
    assert [len(p.scans) for p in _verdict(graph, poses, kept).parts] == [9]


def test_a_join_whose_scans_see_each_other_in_their_free_space_splits_the_part():
    """Two groups held together by two registrations that close a loop, as look-alike rooms register: the loop
    passes, but scans across the join stand in each other's free space. More such pairs than registrations in the
    join: it fails and each group is a part of its own, verified inside. As many or fewer: the join stands, and a
    scan in conflict with two or more others is blamed for it."""
    poses = _poses(10, 6)
    edges = _clique(range(5)) + _clique(range(5, 10)) + [(4, 5), (3, 6)]
    graph = _graph(poses, edges)
    across = [(a, b) for a in range(5) for b in range(5, 10)]
    verdict = _verdict(graph, poses, conflicts=_conflicting(10, across[:3]))
    assert [p.scans for p in verdict.parts] == [[f"s{k}" for k in range(5)], [f"s{k}" for k in range(5, 10)]]
    assert verdict.parts[1].join.why == SEEN_THROUGH and sorted(verdict.parts[1].join.edges) == [
        ("s3", "s6"),
        ("s4", "s5"),
    ]
    assert set(verdict.status.values()) == {"verified"}
    held = _verdict(graph, poses, conflicts=_conflicting(10, across[:2]))  # s0 in conflict with s5 and s6
    assert [len(p.scans) for p in held.parts] == [10] and held.doubts == {"s0": "free space"}


def test_a_scan_in_conflict_with_more_scans_than_its_registrations_is_cut_off():
    """A scan held by three registrations in a loop, placed where four scans of its part saw empty space: the
    minimum cut between it and them is its own registrations, and it is alone, doubted for the free space."""
    poses = _poses(7, 7)
    edges = _clique(range(6)) + [(6, 0), (6, 1), (6, 2)]
    verdict = _verdict(_graph(poses, edges), poses, conflicts=_conflicting(7, [(6, k) for k in range(1, 5)]))
    assert [p.scans for p in verdict.parts] == [[f"s{k}" for k in range(6)], ["s6"]]
    assert verdict.doubts == {"s6": "free space"}


@settings(max_examples=30, deadline=None)
@given(n=st.integers(3, 12), seed=st.integers(0, 10**6), extra=st.integers(0, 20), clashes=st.integers(0, 15))
def test_free_space_conflicts_only_split_parts(n, seed, extra, clashes):
    """Any conflicts between scans of exact registrations: every part lies inside one part of the run without
    them, but for the scans two loops share (which go where their registrations hold them most, and may follow a
    loop the cut left whole), and no scan stays in a part in conflict with more of its scans than it has
    registrations there (cutting those would pass)."""
    rng = np.random.default_rng(seed)
    poses = _poses(n, seed % 1000)
    edges = sorted(
        {(k, k + 1) for k in range(n - 1)} | {tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(extra)}
    )
    graph = _graph(poses, edges)
    conflicts = _conflicting(n, [tuple(rng.choice(n, 2, replace=False)) for _ in range(clashes)])
    before, split = _verdict(graph, poses).part_of(), _verdict(graph, poses, conflicts=conflicts)
    shared = {f"s{k}" for k in nx.articulation_points(nx.Graph(edges))}
    assert all(len({before[s] for s in p.scans if s not in shared}) <= 1 for p in split.parts)
    assert sorted(s for p in split.parts for s in p.scans) == sorted(before)
    label = np.array([split.part_of()[f"s{k}"] for k in range(n)])
    same = label[:, None] == label[None]
    inside = np.bincount(
        np.r_[graph.i, graph.j], weights=np.r_[same[graph.i, graph.j], same[graph.i, graph.j]], minlength=n
    )
    assert np.all((conflicts & same).sum(axis=1) <= inside)


@settings(max_examples=20, deadline=None)
@given(n=st.integers(3, 12), seed=st.integers(0, 10**6), extra=st.integers(0, 20))
def test_parts_partition_the_placed_scans_and_a_loop_verifies(n, seed, extra):
    """Exact measurements on a random graph: the parts partition the scans, every scan of a part of two or more is
    verified (a loop's scans, less the articulation point it shares with a larger part), every scan alone is
    doubtful for a single registration, and moving the world moves nothing."""
    rng = np.random.default_rng(seed)
    poses = _poses(n, seed % 1000)
    edges = [(k, k + 1) for k in range(n - 1)] + [tuple(sorted(rng.choice(n, 2, replace=False))) for _ in range(extra)]
    edges = sorted(set(edges))
    graph = _graph(poses, edges)
    verdict = _verdict(graph, poses)
    scans = sorted(s for p in verdict.parts for s in p.scans)
    assert scans == sorted(f"s{k}" for k in range(n))
    for p in verdict.parts:
        expected = "verified" if len(p.scans) >= 2 else "doubtful"
        assert all(verdict.status[s] == expected for s in p.scans), (p, verdict.status)
        assert all(verdict.doubts[s] == "single registration" for s in p.scans if len(p.scans) == 1)
    world = make_T(Rotation.random(random_state=seed % 97).as_matrix(), rng.uniform(-5, 5, 3))
    moved = _verdict(graph, world[None] @ poses)
    assert [p.scans for p in moved.parts] == [p.scans for p in verdict.parts] and moved.doubts == verdict.doubts


def test_the_verdict_reads_as_strict_json_and_says_itself_in_few_lines():
    poses = _poses(40, 5)
    edges = [(k, k + 1) for k in range(39)] + _clique(range(4))
    verdict = _verdict(_graph(poses, edges), poses)
    data = json.loads(json.dumps(verdict.as_dict(), allow_nan=False))
    assert set(data["status"].values()) <= set(STATUSES) and set(data["doubts"].values()) <= set(REASONS)
    lines = verdict.summary()
    assert len(lines) <= 15 and "36 scan(s) on their own" in lines[-1], lines


@settings(max_examples=30, deadline=None)
@given(st.integers(3, 9), st.floats(0.0, 4.0), st.integers(0, 10**6))
def test_placement_turns_grow_as_a_random_walk_along_the_kept_path(n, step, seed):
    """A chain of n scans whose kept registrations each disagree with the poses by a turn of ``step``° (and one
    dropped registration far off, which counts for nothing): two scans k registrations apart may carry
    step·√k, at most the loop test's budget; a scan no kept registration reaches carries nothing."""
    rng = np.random.default_rng(seed)
    poses = np.stack([make_T(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3)) for _ in range(n + 1)])
    i, j = np.arange(n - 1), np.arange(1, n)
    axes = rng.normal(size=(n - 1, 3))
    turns = [
        make_T(Rotation.from_rotvec(np.radians(step) * a / np.linalg.norm(a)).as_matrix(), np.zeros(3)) for a in axes
    ]
    T = np.stack([inv_T(poses[a]) @ poses[b] @ t for a, b, t in zip(i, j, turns)])
    far = (
        inv_T(poses[0])[None] @ poses[n - 1][None] @ make_T(Rotation.from_rotvec([0, 0, 1.0]).as_matrix(), np.zeros(3))
    )
    graph = PoseGraph(n + 1, np.r_[i, 0], np.r_[j, n - 1], np.concatenate([T, far]), np.ones(n))
    kept = np.r_[np.ones(n - 1, dtype=bool), False]
    out = np.stack([placement_turns(graph, kept, poses)(a) for a in range(n + 1)])
    hops = np.abs(np.arange(n)[:, None] - np.arange(n)[None])
    np.testing.assert_allclose(out[:n, :n], np.minimum(step * np.sqrt(hops), MAX_DEG), atol=1e-6)
    assert not out[n].any() and not out[:, n].any()
