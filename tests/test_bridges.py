"""Bridges against networkx on random graphs (parallel edges, several parts, isolated nodes)."""

import networkx as nx
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sghr_gtsam.sync.bridges import blocks, bridge_edges


def _reference(n: int, i: np.ndarray, j: np.ndarray, keep: np.ndarray) -> np.ndarray:
    G = nx.MultiGraph()
    G.add_nodes_from(range(n))
    G.add_edges_from(zip(i[keep].tolist(), j[keep].tolist()))
    found = {frozenset(e) for e in nx.bridges(nx.Graph(G))}
    # networkx's bridges ignore multiplicity on a simple graph: a doubled edge is on a cycle.
    multi = {frozenset((a, b)) for a, b in zip(i[keep].tolist(), j[keep].tolist())}
    doubled = {p for p in multi if G.number_of_edges(*tuple(p)) > 1}
    return np.array([bool(k) and frozenset((a, b)) in found - doubled for a, b, k in zip(i, j, keep)])


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 10**6), n=st.integers(1, 60), density=st.floats(0.0, 2.5), chain=st.booleans())
def test_bridges_match_networkx(seed, n, density, chain):
    rng = np.random.default_rng(seed)
    m = int(density * n)
    i, j = rng.integers(0, n, m), rng.integers(0, n, m)
    if chain and n > 1:  # long paths: deep trees for the lowest-common-ancestor search
        i, j = np.r_[i, np.arange(n - 1)], np.r_[j, np.arange(1, n)]
    ok = i != j
    i, j = i[ok], j[ok]
    keep = rng.random(len(i)) < 0.9
    np.testing.assert_array_equal(bridge_edges(n, i, j, keep), _reference(n, i, j, keep))
    # Blocks: two nodes share one exactly when a path of non-bridge kept edges joins them.
    label = blocks(n, i, j, keep)
    G = nx.Graph()
    G.add_nodes_from(range(n))
    cut = keep & ~bridge_edges(n, i, j, keep)
    G.add_edges_from(zip(i[cut].tolist(), j[cut].tolist()))
    for comp in nx.connected_components(G):
        comp = sorted(comp)
        assert len(set(label[comp].tolist())) == 1
        assert np.sum(label == label[comp[0]]) == len(comp)


def test_a_cycle_has_no_bridge_and_a_tail_is_all_bridges():
    i = np.array([0, 1, 2, 2, 4])
    j = np.array([1, 2, 0, 3, 3])
    np.testing.assert_array_equal(bridge_edges(5, i, j), [False, False, False, True, True])
