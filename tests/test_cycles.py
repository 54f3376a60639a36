"""Loop evidence (sghr_gtsam.sync.cycles): triangles, their consistency, growing, group moves, and the
default loop polish against plain least squares and against a group hung on a heavy wrong edge."""

import networkx as nx
import numpy as np
from hypothesis import given, strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.se3 import inv_T, make_T, relative_errors
from sghr_gtsam.sync import synchronize
from sghr_gtsam.sync.cycles import credibility, grow, replace_groups, triangle_support, triangles
from sghr_gtsam.types import PoseGraph

from test_sync import FAST, max_errors, random_graph


@FAST
@given(seed=st.integers(0, 10**6), n=st.integers(3, 30), extra=st.integers(0, 4))
def test_triangles_are_those_of_networkx(seed, n, extra):
    """Every triangle once, each row's edges joining (a, b), (b, c), (a, c); parallel and weightless edges
    take no part twice."""
    graph, _, _ = random_graph(seed, n, extra=extra)
    graph.weight[: len(graph.weight) // 7] = 0.0
    tri = triangles(graph)
    used = graph.weight > 0
    G = nx.Graph(list(zip(graph.i[used].tolist(), graph.j[used].tolist())))
    G.remove_edges_from(nx.selfloop_edges(G))
    expected = {tuple(sorted(c)) for c in nx.enumerate_all_cliques(G) if len(c) == 3}
    nodes = [tuple(sorted({graph.i[e] for e in row} | {graph.j[e] for e in row})) for row in tri]
    assert sorted(nodes) == sorted(expected)
    for e_ab, e_bc, e_ca in tri:
        ab, bc, ca = ({graph.i[e], graph.j[e]} for e in (e_ab, e_bc, e_ca))
        assert len(ab & bc) == 1 and len(bc & ca) == 1 and len(ca & ab) == 1 and graph.weight[[e_ab, e_bc, e_ca]].min() > 0


def test_random_outliers_close_no_consistent_triangle():
    graph, _, bad = random_graph(4, 40, extra=5, rot_deg=1.0, trans_sigma=0.02, outliers=0.4)
    support = triangle_support(graph)
    assert bad.sum() > 40 and np.all(support[bad] == 0)
    assert np.mean(support[~bad] > 0) > 0.5


def test_growing_places_every_scan_of_a_clean_graph():
    graph, truth, _ = random_graph(5, 30, extra=4, rot_deg=1.0, trans_sigma=0.02)
    poses = grow(graph, credibility(graph), triangle_support(graph))
    # Chained registration errors, no least squares: a few degrees at most, and no scan misplaced.
    assert max_errors(poses, truth)[0] < 10.0


def _hung_group(seed: int = 2) -> tuple[PoseGraph, np.ndarray, int]:
    """Two well-connected clusters of 15 and 8 scans (1° / 2 cm noise) joined by three right light edges
    and one heavy wrong one (the small cluster turned 180°). Returns the graph, the truth and the wrong edge."""
    a, truth_a, _ = random_graph(seed, 15, extra=3, rot_deg=1.0, trans_sigma=0.02)
    b, truth_b, _ = random_graph(seed + 1, 8, extra=3, rot_deg=1.0, trans_sigma=0.02)
    truth = np.concatenate([truth_a, truth_b])
    flip = make_T(Rotation.from_euler("z", 180, degrees=True).as_matrix(), np.zeros(3))
    links = [(3, 17, False), (5, 19, True), (8, 16, True), (11, 21, True)]
    T = [inv_T(truth[p]) @ (truth[q] if ok else flip @ truth[q]) for p, q, ok in links]
    graph = PoseGraph(n=23, i=np.r_[a.i, b.i + 15, [p for p, _, _ in links]],
                      j=np.r_[a.j, b.j + 15, [q for _, q, _ in links]], T=np.concatenate([a.T, b.T, T]),
                      weight=np.r_[a.weight, b.weight, 1000.0, 1.0, 1.0, 1.0])
    return graph, truth, len(a.i) + len(b.i)


def test_a_group_hung_on_a_heavy_wrong_edge_is_moved_back():
    """Placed across the heavy wrong edge, the small cluster agrees with itself everywhere: no scan gains
    by moving alone. Its three right links agree on one correction of the whole group, which moves it."""
    graph, truth, wrong = _hung_group()
    flip = make_T(Rotation.from_euler("z", 180, degrees=True).as_matrix(), np.zeros(3))
    start = truth.copy()
    G = truth[3] @ graph.T[wrong] @ inv_T(truth[17])  # the small cluster as the wrong edge places it
    start[15:] = G @ truth[15:]
    assert not np.allclose(G, np.eye(4), atol=0.1) and np.isclose(abs(np.trace(flip[:3, :3])), 1.0)
    moved = replace_groups(graph, start, credibility(graph))
    assert max_errors(moved, truth)[0] < 5.0
    result = synchronize(graph)
    assert max_errors(result.poses, truth)[0] < 3.0 and result.weights[wrong] == 0.0


def test_loop_polish_is_plain_least_squares_without_outliers():
    """No outliers: every edge is kept and the poses are those of plain Levenberg-Marquardt."""
    graph, truth, _ = random_graph(6, 50, extra=4, rot_deg=2.0, trans_sigma=0.05)
    result = synchronize(graph)
    plain = synchronize(graph, method="lm")
    assert np.all(result.weights > 0)
    rot, trans = relative_errors(inv_T(result.poses[0]) @ result.poses, inv_T(plain.poses[0]) @ plain.poses)
    assert rot.max() < 0.05 and trans.max() < 1e-3
    assert result.loop_support is not None and result.loop_support.shape == (graph.num_edges,)
