"""Consensus re-placement (sync/consensus.py) and the robust polish it belongs to: a scan whose wrong
placement is repeated on several of its edges (the paper's Fig. 2 case) is put back where the heavier group
of its edges says. Synthetic graphs only."""

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from test_sync import gauge_free, max_errors

from sghr_gtsam.se3 import inv_T, make_T, relative_errors
from sghr_gtsam.sync import synchronize
from sghr_gtsam.sync.consensus import (
    MARGIN,
    MAX_DEG,
    consensus_placement,
    consistent_edges,
    placement_support,
    translation_tolerance,
)
from sghr_gtsam.types import PoseGraph

FAST = settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def star_with_wrong_group(seed: int, good: int, bad: int) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """Scan 0 linked to ``good + bad`` partners that form a chain among themselves; ``bad`` of its edges
    agree on one wrong placement G·T_0 (a 90° turn or a 1 m shift). Noise-free. Returns the graph, the true
    poses and the wrong pose of scan 0."""
    rng = np.random.default_rng(seed)
    n = 1 + good + bad
    truth = make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.uniform(-2.0, 2.0, (n, 3)))
    if rng.random() < 0.5:
        G = make_T(Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix(), np.zeros(3))
    else:
        G = make_T(np.eye(3), [1.0, 0.0, 0.0])
    wrong = G @ truth[0]
    partners = rng.permutation(np.arange(1, n))
    i = np.r_[np.zeros(n - 1, int), partners[:-1]]
    j = np.r_[partners, partners[1:]]
    src = truth[i].copy()
    src[: n - 1][np.isin(partners, partners[:bad])] = wrong  # the bad edges see scan 0 at the wrong place
    T = inv_T(src) @ truth[j]
    return PoseGraph(n=n, i=i, j=j, T=T, weight=np.ones(len(i))), truth, wrong


@FAST
@given(seed=st.integers(0, 10**6), bad=st.integers(2, 4), margin=st.integers(1, 3))
def test_a_scan_moves_to_the_placement_more_of_its_edges_agree_on(seed, bad, margin):
    """``MARGIN`` more support than the current placement moves a scan (equal edge weights here)."""
    graph, truth, wrong = star_with_wrong_group(seed, int(np.floor(bad * (1 + MARGIN))) + margin, bad)
    start = truth.copy()
    start[0] = wrong  # where residual reweighting would leave it: the wrong group agrees with this pose
    out = consensus_placement(graph, start)
    np.testing.assert_allclose(out, truth, atol=1e-9)
    # Every good edge, and no bad one, is consistent with the result.
    assert consistent_edges(graph, out).sum() == graph.num_edges - bad


@FAST
@given(seed=st.integers(0, 10**6), bad=st.integers(2, 4))
def test_a_scan_stays_where_the_heavier_group_puts_it(seed, bad):
    """With no more good edges than bad ones the wrong placement keeps the support: it is kept (the
    result is the weighted majority, not the truth — the limit of any method that sees only the graph)."""
    graph, truth, wrong = star_with_wrong_group(seed, bad, bad)
    start = truth.copy()
    start[0] = wrong
    np.testing.assert_allclose(consensus_placement(graph, start)[0], wrong, atol=1e-9)


def ring_with_wrong_groups(seed: int, group: int, every: int, n: int = 30) -> tuple[PoseGraph, np.ndarray]:
    """A ring of ``n`` scans, each linked to its 4 nearest on either side (1° / 2 cm noise); every
    ``every``-th scan has a 90° wrong placement repeated on ``group`` of its 8 edges."""
    rng = np.random.default_rng(seed)
    truth = make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.uniform(-3.0, 3.0, (n, 3)))
    i, j = np.array([(a, b) for a in range(n) for b in range(a + 1, n) if min(b - a, n - b + a) <= 4]).T
    noise = make_T(
        Rotation.from_rotvec(rng.normal(0.0, np.radians(1.0), (len(i), 3))).as_matrix(),
        rng.normal(0.0, 0.02, (len(i), 3)),
    )
    src, dst = truth[i].copy(), truth[j].copy()
    turn = make_T(Rotation.from_rotvec([0.0, 0.0, np.pi / 2]).as_matrix(), np.zeros(3))
    for scan in range(0, n, every):
        edges = rng.choice(np.flatnonzero((i == scan) | (j == scan)), group, replace=False)
        src[edges[i[edges] == scan]] = turn @ truth[scan]
        dst[edges[j[edges] == scan]] = turn @ truth[scan]
    graph = PoseGraph(n=n, i=i, j=j, T=inv_T(src) @ dst @ noise, weight=rng.uniform(50.0, 100.0, len(i)))
    return graph, truth


def test_robust_polish_recovers_repeated_wrong_placements_that_irls_keeps():
    """Every second scan with 3 of 8 edges on one wrong placement: IRLS (then LM) leaves scans 90° off; the
    default robust polish puts every scan within 3° of the truth."""
    graph, truth = ring_with_wrong_groups(1, group=3, every=2)
    assert max_errors(synchronize(graph, polish="lm").poses, truth)[0] > 45.0
    robust = synchronize(graph, polish="robust")
    assert max_errors(robust.poses, truth)[0] < 3.0
    assert np.all(robust.component == 0)
    np.testing.assert_allclose(gauge_free(robust.poses)[0], np.eye(4), atol=1e-12)


def test_loop_polish_places_every_scan_the_edge_count_decides():
    """The same ring for the default loop polish, which votes by edge counts: every scan whose right
    placement has more edges than any wrong one ends within 3°; a tie (3 right edges against 3 wrong ones,
    scans 10 and 28 here) the graph does not decide, and the weights are no better than a coin."""
    graph, truth = ring_with_wrong_groups(1, group=3, every=2)
    tol = translation_tolerance(graph)
    count = replace(graph, weight=np.ones(graph.num_edges))
    decided = []
    for s in range(graph.n):
        edges = np.flatnonzero((graph.i == s) | (graph.j == s))
        _, support, current, right, _ = placement_support(count, truth, s, edges, MAX_DEG, tol)
        decided.append(current > support[~right].max(initial=0.0))
    decided = np.array(decided)
    assert 25 <= decided.sum() < graph.n
    result = synchronize(graph)
    anchor = np.flatnonzero(decided)[0]
    rot, _ = relative_errors(inv_T(result.poses[anchor]) @ result.poses[decided], inv_T(truth[anchor]) @ truth[decided])
    assert rot.max() < 3.0


@pytest.mark.parametrize("seed", range(6))
def test_robust_polish_keeps_a_right_irls_result(seed):
    """Near-ties (a wrong group about as heavy as a scan's good edges) must not pull a scan that IRLS placed
    right: consensus moves need ``MARGIN`` more support."""
    graph, truth = ring_with_wrong_groups(seed, group=3, every=3)
    assert max_errors(synchronize(graph, polish="lm").poses, truth)[0] < 3.0
    assert max_errors(synchronize(graph, polish="robust").poses, truth)[0] < 3.0
    assert max_errors(synchronize(graph).poses, truth)[0] < 3.0


@FAST
@given(seed=st.integers(0, 10**6), heavy=st.floats(2.0, 1e3))
def test_a_lone_heavy_edge_does_not_pull_a_scan(seed, heavy):
    """One wrong edge, however heavy, proposes an uncorroborated placement (``MIN_AGREEING``): the scan stays
    where its other edges agree; two agreeing heavy wrong edges do move it."""
    graph, truth, wrong = star_with_wrong_group(seed, 3, 1)
    w = graph.weight.copy()
    w[0] = heavy * 3  # the wrong edge outweighs the three right ones
    lone = PoseGraph(n=graph.n, i=graph.i, j=graph.j, T=graph.T, weight=w)
    np.testing.assert_allclose(consensus_placement(lone, truth)[0], truth[0], atol=1e-9)
    graph, truth, wrong = star_with_wrong_group(seed, 3, 2)
    w = graph.weight.copy()
    w[:2] = heavy * 3
    pair = PoseGraph(n=graph.n, i=graph.i, j=graph.j, T=graph.T, weight=w)
    np.testing.assert_allclose(consensus_placement(pair, truth)[0], wrong, atol=1e-9)
