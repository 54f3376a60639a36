"""The comparison methods recover exact graphs, and the robust gtsam ones (and the oracle) see through gross
outliers. Synthetic graphs only: no data needed."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.evaluate import scan_errors
from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.sync.baselines import BASELINES, eigse3, gnc_tls, l1_irls, oracle, rotavg
from sghr_gtsam.types import PoseGraph


def _graph(
    seed: int, n: int = 15, chords: int = 30, rot_sigma_deg: float = 0.0, trans_sigma: float = 0.0, outliers: int = 0
) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """Poses spread over a few metres; a ring (so the graph is connected) plus random chords; weights 1-100.
    Returns the graph, the true poses and the outlier mask."""
    rng = np.random.default_rng(seed)
    poses = make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.uniform(-2.0, 2.0, (n, 3)))
    ring = np.stack([np.arange(n), (np.arange(n) + 1) % n], axis=1)
    extra = rng.integers(0, n, (chords, 2))
    pairs = np.unique(np.sort(np.vstack([ring, extra[extra[:, 0] != extra[:, 1]]]), axis=1), axis=0)
    i, j = pairs.T
    noise = make_T(
        Rotation.from_rotvec(rng.normal(0.0, np.radians(rot_sigma_deg), (len(i), 3))).as_matrix(),
        rng.normal(0.0, trans_sigma, (len(i), 3)),
    )
    T = inv_T(poses[i]) @ poses[j] @ noise
    bad = np.zeros(len(i), dtype=bool)
    # Outliers only on chords, so the inlier edges keep the ring and stay connected.
    chord = np.flatnonzero(((j - i) % n != 1) & ((i - j) % n != 1))
    bad[rng.choice(chord, outliers, replace=False)] = True
    T[bad] = make_T(Rotation.random(outliers, random_state=rng).as_matrix(), rng.uniform(-3.0, 3.0, (outliers, 3)))
    return PoseGraph(n=n, i=i, j=j, T=T, weight=rng.uniform(1.0, 100.0, len(i))), poses, bad


def _max_errors(result, poses) -> tuple[float, float]:
    errors = scan_errors([str(k) for k in range(len(poses))], result.poses, poses)
    return float(errors.rotation_deg.max()), float(errors.translation.max())


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(3, 30))
def test_numpy_baselines_recover_an_exact_graph(seed, n):
    graph, poses, _ = _graph(seed, n=n, chords=2 * n)
    for method in (eigse3, l1_irls, rotavg):
        result = method(graph)
        rot, trans = _max_errors(result, poses)
        assert rot < 1e-5 and trans < 1e-6, method.__name__
        assert np.all(result.component == 0)
        np.testing.assert_allclose(result.poses[0], np.eye(4), atol=1e-9)


@pytest.mark.parametrize("name", ["gnc_tls", "shonan", "open3d", "open3d_all_uncertain"])
def test_gtsam_and_open3d_baselines_recover_an_exact_graph(name):
    graph, poses, _ = _graph(1)
    result = BASELINES[name](graph)
    rot, trans = _max_errors(result, poses)
    assert rot < 1e-4 and trans < 1e-5
    assert result.weights.shape == (graph.num_edges,) and np.all(result.weights > 0)


def test_oracle_recovers_an_exact_graph():
    graph, poses, _ = _graph(2)
    rot, trans = _max_errors(oracle(graph, np.ones(graph.num_edges, dtype=bool)), poses)
    assert rot < 1e-4 and trans < 1e-5


def test_gnc_and_oracle_reject_gross_outliers():
    graph, poses, bad = _graph(3, n=20, chords=50, rot_sigma_deg=0.5, trans_sigma=0.01, outliers=6)
    for result in (gnc_tls(graph), oracle(graph, ~bad)):
        rot, trans = _max_errors(result, poses)
        assert rot < 1.5 and trans < 0.05
        np.testing.assert_array_equal(result.weights[bad], 0.0)
        assert np.all(result.weights[~bad] > 0)
