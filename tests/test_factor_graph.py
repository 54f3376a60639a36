"""The gtsam polish: weight → noise mapping, the graph error, Levenberg–Marquardt from a perturbed start,
anchoring of every part, and the per-iteration records. Synthetic graphs only."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation
from test_sync import gauge_free, random_graph

from sghr_gtsam.factor_graph import ROT_SIGMA_DEG, edge_information, graph_error, polish
from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.sync import synchronize
from sghr_gtsam.sync.rotation import connected_components
from sghr_gtsam.types import PoseGraph


def _perturb(poses: np.ndarray, seed: int, rot_deg: float, trans: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = make_T(
        Rotation.from_rotvec(rng.normal(0.0, np.radians(rot_deg), (len(poses), 3))).as_matrix(),
        rng.normal(0.0, trans, (len(poses), 3)),
    )
    out = poses @ noise
    out[0] = poses[0]
    return out


def test_information_is_the_base_scaled_by_weight_over_median_or_the_edges_own():
    graph, _, _ = random_graph(0, 10, extra=2)
    w = np.linspace(1.0, 9.0, graph.num_edges)
    w[0] = 0.0
    info = edge_information(graph, w)
    median = np.median(w[1:])
    sigma_r = np.radians(ROT_SIGMA_DEG)
    sigma_t = sigma_r * np.median(np.linalg.norm(graph.T[1:, :3, 3], axis=1))
    base = np.diag([sigma_r**-2] * 3 + [sigma_t**-2] * 3)
    np.testing.assert_allclose(info[1:], (w[1:] / median)[:, None, None] * base)
    np.testing.assert_array_equal(info[0], 0.0)
    # The edges' own (calibrated) information, when the graph has it, enters as it is on every kept edge.
    own = np.tile(np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]), (graph.num_edges, 1, 1))
    graph.information = own
    np.testing.assert_array_equal(edge_information(graph, w)[1:], own[1:])
    np.testing.assert_array_equal(edge_information(graph, w)[0], 0.0)


@given(angle=st.floats(-2.0, 2.0), shift=st.floats(-5.0, 5.0))
@settings(max_examples=30, deadline=None)
def test_graph_error_is_half_the_weighted_squared_log(angle, shift):
    """One edge T_01 = I: a pose T_1 = (Rz(θ), d) has residual Log(T_1) = (θ e_z, J⁻¹(θ)d), and with d along
    the axis J⁻¹ d = d, so the error is ½ (p_r θ² + p_t d²)."""
    graph = PoseGraph(n=2, i=np.array([0]), j=np.array([1]), T=np.eye(4)[None], weight=np.ones(1))
    information = np.diag([3.0, 3.0, 5.0, 7.0, 7.0, 11.0])[None]
    poses = np.stack([np.eye(4), make_T(Rotation.from_rotvec([0.0, 0.0, angle]).as_matrix(), np.array([0, 0, shift]))])
    assert np.isclose(graph_error(graph, poses, information), 0.5 * (5.0 * angle**2 + 11.0 * shift**2), rtol=1e-9)


def test_information_weighted_mean_of_parallel_edges():
    """Two measurements of the same pure translation: least squares returns their information-weighted mean."""
    t1, t2 = np.array([1.0, 0.0, 0.0]), np.array([0.0, 2.0, 0.0])
    T = make_T(np.stack([np.eye(3)] * 2), np.stack([t1, t2]))
    graph = PoseGraph(
        n=2,
        i=np.array([0, 0]),
        j=np.array([1, 1]),
        T=T,
        weight=np.ones(2),
        information=np.stack([np.eye(6) * 1.0, np.eye(6) * 3.0]),
    )
    result = synchronize(graph, method="lm")
    np.testing.assert_allclose(result.poses[1], make_T(np.eye(3), (t1 + 3.0 * t2) / 4.0), atol=1e-9)


@pytest.mark.parametrize("n", [8, 60])
def test_polish_recovers_a_noise_free_graph_from_a_perturbed_start(n):
    graph, truth, _ = random_graph(3, n, extra=2)
    start = inv_T(truth[0]) @ _perturb(truth, 4, rot_deg=5.0, trans=0.3)
    information = edge_information(graph, graph.weight)
    component = np.zeros(n, dtype=int)
    seen = []
    result = polish(graph, start, information, component, on_iteration=seen.append)
    np.testing.assert_allclose(gauge_free(result.poses), gauge_free(truth), atol=1e-8)
    np.testing.assert_allclose(result.poses[0], np.eye(4), atol=1e-12)
    assert result.converged and result.final_error < 1e-12 < result.initial_error
    assert seen == result.history and [r.iteration for r in seen] == list(range(1, len(seen) + 1))
    assert all(r.stage == "lm" for r in seen)
    costs = [result.initial_error] + [r.cost for r in seen]
    assert np.all(np.diff(costs) <= 1e-12)
    assert seen[-1].residual_deg.max() < 1e-5
    assert np.isclose(graph_error(graph, result.poses, information), result.final_error, atol=1e-12)


def test_polish_anchors_every_part_and_skips_dropped_edges():
    a, truth_a, _ = random_graph(5, 6, extra=2)
    b, truth_b, _ = random_graph(6, 4, extra=2)
    rng = np.random.default_rng(7)
    junk = make_T(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
    # Nodes 0-5 and 6-9 are two parts; node 10 only has a dropped (weight 0) wrong edge.
    graph = PoseGraph(
        n=11,
        i=np.r_[a.i, b.i + 6, 10],
        j=np.r_[a.j, b.j + 6, 0],
        T=np.concatenate([a.T, b.T, junk[None]]),
        weight=np.r_[a.weight, b.weight, 0.0],
    )
    component = connected_components(11, graph.i, graph.j, graph.weight > 0)
    truth = np.concatenate([inv_T(truth_a[0]) @ truth_a, inv_T(truth_b[0]) @ truth_b, np.eye(4)[None]])
    start = _perturb(truth, 8, rot_deg=3.0, trans=0.2)
    start[[0, 6, 10]] = np.eye(4)  # the anchors, as synchronize hands them over
    result = polish(graph, start, edge_information(graph, graph.weight), component)
    np.testing.assert_allclose(result.poses, truth, atol=1e-8)


def test_polish_lowers_the_error_of_a_noisy_graph_to_its_minimum():
    graph, truth, _ = random_graph(9, 40, extra=3, rot_deg=2.0, trans_sigma=0.05)
    information = edge_information(graph, graph.weight)
    component = np.zeros(graph.n, dtype=int)
    result = polish(graph, inv_T(truth[0]) @ truth, information, component, relative_tol=1e-12)
    assert result.final_error < result.initial_error
    # A minimum: moving any single pose a little only raises the error.
    rng = np.random.default_rng(10)
    for k in rng.choice(np.arange(1, graph.n), 5, replace=False):
        moved = result.poses.copy()
        moved[k] = moved[k] @ make_T(Rotation.from_rotvec(rng.normal(0, 1e-3, 3)).as_matrix(), rng.normal(0, 1e-3, 3))
        assert graph_error(graph, moved, information) > result.final_error
