"""The incremental session (``sghr_gtsam.incremental``) on a generated room with known poses: georeferenced scans,
scan names, ``add_node``'s checks and roll-back, ``run_result`` for the writers, and the session's own input checks.

The room's scans are given in its world frame (``world``), so every true pose is the identity."""

import csv
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.config import Config
from sghr_gtsam.gtsam_api import pose_covariances
from sghr_gtsam.incremental import Session
from sghr_gtsam.io.poses import read_poses, write_poses
from sghr_gtsam.io.results import write_results
from sghr_gtsam.merged import merged_cloud
from sghr_gtsam.se3 import inv_T, make_T, relative_errors, transform_points
from sghr_gtsam.synthetic import make_scene
from sghr_gtsam.types import InputError

UTM = np.array([5e5, 4.2e6, 100.0])
"""A georeferenced offset: easting, northing, height (m)."""
INFO = np.diag([1e4] * 3 + [1e2] * 3)
"""A caller's edge information (gtsam order: 0.6° and 10 cm)."""
MAX_DEG, MAX_M = 0.1, 0.005
"""What the room's registrations reach against the truth (observed: 0.02° and 0.6 mm)."""


def _config(**kw: object) -> Config:
    return Config(**{"workers": 1, "record": False, **kw})


def _shift(c: np.ndarray) -> np.ndarray:
    return make_T(np.eye(3), np.asarray(c, dtype=float))


def _local(poses: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Poses in a frame offset by ``offset`` seen from a frame at it (the same scans without the offset)."""
    return inv_T(_shift(offset))[None] @ poses @ _shift(offset)[None]


def _fed(scans: list[np.ndarray], names: list[str] | None = None) -> Session:
    session = Session(_config(), voxel=0.05)
    for k, points in enumerate(scans):
        session.add_scan(names[k] if names else f"scan_{k}", points)
    return session


def _state(session: Session) -> tuple:
    """What a refused call must leave as it was."""
    return (
        list(session.names),
        len(session.edges),
        [(e.i, e.j, e.kept) for e in session.edges],
        session.poses.copy(),
        session.robust_runs,
    )


def _assert_unchanged(session: Session, before: tuple) -> None:
    after = _state(session)
    assert after[:3] == before[:3] and after[4] == before[4]
    np.testing.assert_array_equal(after[3], before[3])  # NaN (not placed) equal to NaN


def _refused(call, *args: object) -> str:
    with pytest.raises(InputError) as error:
        call(*args)
    message = str(error.value)
    assert message and "\n" not in message
    return message


@pytest.fixture(scope="module")
def scene():
    return make_scene(kind="room", n_scans=4, seed=1)


@pytest.fixture(scope="module")
def world(scene) -> list[np.ndarray]:
    return [transform_points(T, P) for T, P in zip(scene.poses, scene.scans)]


@pytest.fixture(scope="module")
def near(world) -> Session:
    """The room fed scan by scan near the origin (tests only read it)."""
    return _fed(world)


def _truth_edge(scene, a: int, b: int) -> np.ndarray:
    return inv_T(scene.poses[a]) @ scene.poses[b]


def _graph_session(scene, nodes: int = 2) -> Session:
    """A session fed the room's true relative poses by ``add_node``, ``nodes`` nodes."""
    session = Session(_config(), voxel=0.05)
    session.add_node("0", [])
    for b in range(1, nodes):
        session.add_node(str(b), [(a, _truth_edge(scene, a, b), 1.0, INFO) for a in range(b)])
    return session


def _assert_truth(session: Session, scene, max_deg: float = 1e-6, max_m: float = 1e-6) -> None:
    n = len(session.names)
    rot, trans = relative_errors(session.poses, inv_T(scene.poses[0])[None] @ scene.poses[:n])
    assert rot.max() < max_deg and trans.max() < max_m, (rot.max(), trans.max())


# --- 1. georeferenced scans ----------------------------------------------------------------------------------------


def test_georeferenced_scans_register_as_near_the_origin(world, near):
    """4 200 km north: every scan placed, as accurately as near the origin, its poses applying to the input
    points, and the same relative poses (to float64 precision) wherever the far frame is."""
    truth = np.broadcast_to(np.eye(4), (len(world), 4, 4))
    far = _fed([P + UTM for P in world])
    poses = far.poses
    assert np.isfinite(poses).all() and np.array_equal(poses[0], np.eye(4))
    assert np.array_equal(near.poses[0], np.eye(4))  # exactly, as the docstring says
    for _session, local in ((near, near.poses), (far, _local(poses, UTM))):
        rot, trans = relative_errors(local, truth)
        assert rot.max() < MAX_DEG and trans.max() < MAX_M, (rot.max(), trans.max())
    rot, trans = relative_errors(_local(poses, UTM), near.poses)  # float32 stages round differently
    assert rot.max() < 0.05 and trans.max() < 0.002, (rot.max(), trans.max())
    for T, P in zip(poses, world):
        assert np.abs(transform_points(T, P + UTM) - (P + UTM)).max() < 2 * MAX_M

    elsewhere = UTM + [2e3, -3e3, 50.0]
    other = _fed([P + elsewhere for P in world])
    rot, trans = relative_errors(_local(other.poses, elsewhere), _local(poses, UTM))
    assert rot.max() < 1e-4 and trans.max() < 1e-5, (rot.max(), trans.max())

    r = far.run_result()  # mapped back to the input frame as a batch run is
    np.testing.assert_allclose(r.poses, poses, rtol=0, atol=1e-6)
    assert np.isfinite(r.covariances).all() and not r.covariances[0].any()
    assert np.abs(merged_cloud(r).mean(0) - merged_cloud(near.run_result()).mean(0) - UTM).max() < MAX_M


# --- 2. names ------------------------------------------------------------------------------------------------------

NAMES = st.one_of(
    st.text(max_size=6),
    st.sampled_from(["", " ", "a\nb", "a\rb", "x\u2028y", "#x", " a", "a ", "0"]),
    st.integers(),
    st.none(),
    st.just(b"bytes"),
)


@settings(max_examples=60, deadline=None)
@given(name=NAMES)
def test_a_name_is_taken_only_when_it_is_new_and_reads_back_from_a_pose_file(scene, tmp_path_factory, name):
    session = _graph_session(scene, nodes=1)  # node "0"
    before = _state(session)
    try:
        session.add_node(name, [(0, _truth_edge(scene, 0, 1), 1.0, INFO)])
    except InputError as e:
        assert "\n" not in str(e)
        _assert_unchanged(session, before)
        return
    path = tmp_path_factory.mktemp("names") / "poses.txt"
    write_poses(path, session.names, session.poses)
    assert read_poses(path)[0] == session.names == ["0", name]


def test_add_scan_refuses_a_name_already_in_the_session(world):
    session = _fed(world[:1], names=["a"])
    before = _state(session)
    assert "'a'" in _refused(session.add_scan, "a", world[1])
    _assert_unchanged(session, before)


# --- 3. add_node's edges -------------------------------------------------------------------------------------------


def _bad_edges(T: np.ndarray) -> dict[str, tuple]:
    shear = np.eye(4)
    shear[0, 1] = 0.1
    return {
        "unknown partner": (5, T, 1.0, INFO),
        "negative partner": (-1, T, 1.0, INFO),
        "fractional partner": (0.5, T, 1.0, INFO),
        "bool partner": (True, T, 1.0, INFO),
        "scaled T": (1, np.diag([2.0, 2.0, 2.0, 1.0]) @ T, 1.0, INFO),
        "sheared T": (1, shear @ T, 1.0, INFO),
        "reflected T": (1, np.diag([1.0, 1.0, -1.0, 1.0]) @ T, 1.0, INFO),
        "NaN T": (1, np.full((4, 4), np.nan), 1.0, INFO),
        "3x4 T": (1, T[:3], 1.0, INFO),
        "negative weight": (1, T, -1.0, INFO),
        "NaN weight": (1, T, np.nan, INFO),
        "inf weight": (1, T, np.inf, INFO),
        "str weight": (1, T, "1", INFO),
        "NaN information": (1, T, 1.0, np.full((6, 6), np.nan)),
        "3x3 information": (1, T, 1.0, np.eye(3)),
        "asymmetric information": (1, T, 1.0, INFO + np.triu(np.ones((6, 6)), 1)),
        "indefinite information": (1, T, 1.0, np.diag([1.0] * 5 + [-1.0])),
        "singular information": (1, T, 1.0, np.zeros((6, 6))),
        "no information": (1, T, 1.0, None),
        "3-tuple": (1, T, 1.0),
    }


@pytest.mark.parametrize("bad", list(_bad_edges(np.eye(4))))
def test_add_node_refuses_a_bad_edge_and_leaves_the_session_as_it_was(scene, bad):
    session = _graph_session(scene)
    before = _state(session)
    good = (1, _truth_edge(scene, 1, 2), 1.0, INFO)
    _refused(session.add_node, "2", [good, _bad_edges(good[1])[bad]])
    _assert_unchanged(session, before)
    session.add_node("2", [good])  # no phantom node: indices as before
    _assert_truth(session, scene)


@settings(max_examples=40, deadline=None)
@given(
    quaternion=st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
    t=st.lists(st.floats(-100, 100), min_size=3, max_size=3),
    column=st.integers(0, 2),
    scale=st.floats(0.5, 2.0).filter(lambda s: abs(s - 1.0) > 1e-4),
)
def test_add_node_takes_any_rigid_edge_exactly_and_no_scaled_one(quaternion, t, column, scale):
    T = make_T(Rotation.from_quat(quaternion).as_matrix(), np.array(t))
    session = Session(_config(), voxel=0.05)
    session.add_node("0", [])
    scaled = T.copy()
    scaled[:3, column] *= scale
    _refused(session.add_node, "1", [(0, scaled, 1.0, INFO)])
    assert session.names == ["0"]
    session.add_node("1", [(0, T, 1.0, INFO)])
    np.testing.assert_allclose(session.poses[1], T, rtol=0, atol=1e-9)


def test_a_back_end_gtsam_cannot_solve_is_rolled_back(scene):
    """An information positive definite but too ill-conditioned for gtsam: refused, and the session goes on exactly
    as one that never saw it."""
    session, reference = _graph_session(scene), _graph_session(scene)
    before = _state(session)
    T = _truth_edge(scene, 1, 2)
    assert "cannot place" in _refused(session.add_node, "2", [(1, T, 1.0, np.diag([1e30, 1, 1, 1, 1, 1e-10]))])
    _assert_unchanged(session, before)
    for s in (session, reference):
        for b in (2, 3):
            s.add_node(str(b), [(a, _truth_edge(scene, a, b), 1.0, INFO) for a in range(b)])
    np.testing.assert_array_equal(session.poses, reference.poses)
    _assert_truth(session, scene)


# --- 4. run_result -------------------------------------------------------------------------------------------------


def test_run_result_gives_the_writers_every_edge_with_its_registration(near, tmp_path):
    r = near.run_result()
    assert r.graph.num_edges == len(near.edges) == len(r.pairs) > 0
    for pair, T in zip(r.pairs, r.graph.T):
        np.testing.assert_allclose(pair.T, T, rtol=0, atol=1e-12)
        assert pair.inliers > 0 and pair.information is not None
    np.testing.assert_allclose(r.poses, near.poses, rtol=0, atol=1e-12)
    assert np.isfinite(r.covariances).all() and not r.covariances[0].any() and r.covariances[1:].any()
    write_results(tmp_path, r, Config(voxel=0.05), time.perf_counter(), merged_cloud(r))
    assert (tmp_path / "report.json").is_file()
    with open(tmp_path / "edges.csv", newline="") as f:
        assert len(list(csv.reader(f))) == 1 + r.graph.num_edges
    names, poses = read_poses(tmp_path / "poses.txt")
    rot, trans = relative_errors(poses, np.broadcast_to(np.eye(4), poses.shape))
    assert names == near.names and rot.max() < MAX_DEG and trans.max() < MAX_M


def test_run_result_of_an_empty_session_is_refused_and_of_one_scan_is_the_world(world, tmp_path):
    session = Session(_config(), voxel=0.05)
    _refused(session.run_result)
    session.add_scan("a", world[0])
    r = session.run_result()
    assert r.names == ["a"] and r.unregistered == [] and r.graph.num_edges == 0
    assert np.array_equal(r.poses[0], np.eye(4)) and np.array_equal(r.covariances, np.zeros((1, 6, 6)))
    assert np.array_equal(pose_covariances(r), np.zeros((1, 6, 6)))  # no edge: the max over none failed
    write_results(tmp_path, r, Config(voxel=0.05), time.perf_counter(), merged_cloud(r))
    assert read_poses(tmp_path / "poses.txt")[0] == ["a"]


def test_add_scan_after_add_node_registers_against_the_scans(world):
    """A node without a scan (a GNSS fix, say) first: the scans still pair with each other, not with it."""
    session = Session(_config(), voxel=0.05)
    session.add_node("fix", [])
    session.add_scan("a", world[0])
    session.add_scan("b", world[1])
    graph = session.graph()
    assert list(zip(graph.i.tolist(), graph.j.tolist())) == [(1, 2)]
    rot, trans = relative_errors(graph.T[0], np.eye(4))
    assert rot < MAX_DEG and trans < MAX_M


# --- 5. the session's own checks -----------------------------------------------------------------------------------


@pytest.mark.parametrize("voxel", ["0.05", np.inf, np.nan, True, 0.0, -0.05, [0.05]])
def test_session_refuses_a_voxel_that_is_not_a_positive_finite_number(voxel):
    _refused(Session, _config(), voxel)


def test_session_voxel_none_is_the_config_voxel():
    assert Session(_config(voxel=0.05), None).voxel == 0.05


def test_non_finite_rows_are_dropped_as_the_batch_loader_drops_them(world, near):
    rng = np.random.default_rng(0)
    holed = []
    for P in world:
        bad = rng.choice([np.nan, np.inf, -np.inf], size=(200, 3))
        bad[:, :2] = rng.uniform(-1, 1, (200, 2))  # one non-finite coordinate is enough
        holed.append(np.insert(P, rng.integers(0, len(P), 200), bad, axis=0))
    session = _fed(holed)
    np.testing.assert_allclose(session.poses, near.poses, rtol=0, atol=1e-12)

    before = _state(session)
    sparse = world[0][:150].copy()
    sparse[60:] = np.nan  # 60 finite points, fewer than min_points
    assert "60 finite points" in _refused(session.add_scan, "sparse", sparse)
    _assert_unchanged(session, before)


def test_a_session_with_a_node_without_points_writes_every_output(world, tmp_path):
    """An ``add_node`` node has no points: summary.png failed on its empty grid (a zero-size minimum)."""
    session = Session(_config(), voxel=0.05)
    session.add_scan("a", world[0])
    session.add_scan("b", world[1])
    session.add_node("fix", [(0, np.eye(4), 1.0, 100.0 * np.eye(6))])
    r = session.run_result()
    write_results(tmp_path, r, Config(voxel=0.05), time.perf_counter(), merged_cloud(r))
    assert (tmp_path / "summary.png").stat().st_size > 0
    assert read_poses(tmp_path / "poses.txt")[0] == ["a", "b", "fix"]


# --- 6. the caller's factors: odometry, priors, GNSS, any gtsam factor ---------------------------------------------

ODOMETRY = np.diag([1e4] * 3 + [1e2] * 3)
"""An odometry step's information (gtsam order: 0.6° and 10 cm)."""


def _truth_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    T = make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.uniform(-3, 3, (n, 3)))
    return inv_T(T[0])[None] @ T


def _noisy(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return T @ make_T(Rotation.from_rotvec(rng.normal(0, 0.01, 3)).as_matrix(), rng.normal(0, 0.1, 3))


def _batch(n: int, factors: list, initial: np.ndarray, anchor: bool = True) -> np.ndarray:
    """gtsam's batch LM over ``factors`` (keys ``x0..``) from ``initial``, with the session's anchor prior."""
    import gtsam

    graph = gtsam.NonlinearFactorGraph()
    for factor in factors:
        graph.add(factor)
    if anchor:
        graph.add(
            gtsam.PriorFactorPose3(gtsam.symbol("x", 0), gtsam.Pose3(), gtsam.noiseModel.Isotropic.Precision(6, 1e12))
        )
    values = gtsam.Values()
    for k in range(n):
        values.insert(gtsam.symbol("x", k), gtsam.Pose3(initial[k]))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-15)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.stack([result.atPose3(gtsam.symbol("x", k)).matrix() for k in range(n)])


def _between(a: int, b: int, T: np.ndarray, info: np.ndarray = ODOMETRY):
    import gtsam

    return gtsam.BetweenFactorPose3(
        gtsam.symbol("x", a), gtsam.symbol("x", b), gtsam.Pose3(T), gtsam.noiseModel.Gaussian.Information(info)
    )


def _odometry_session(truth: np.ndarray, rng: np.random.Generator, anchor: bool = True) -> tuple[Session, list]:
    """Nodes without scans chained by noisy odometry (``add_between``) and closed by one loop factor."""
    session, factors = Session(Config(), voxel=None, anchor=anchor), []
    session.add_node("n0", [])
    for k in range(1, len(truth)):
        session.add_node(f"n{k}", [])  # no edge: placed by its odometry
        T = _noisy(inv_T(truth[k - 1]) @ truth[k], rng)
        session.add_between(k - 1, f"n{k}", T, ODOMETRY)
        factors.append(_between(k - 1, k, T))
    T = _noisy(inv_T(truth[-1]) @ truth[0], rng)
    session.add_between(len(truth) - 1, 0, T, ODOMETRY)
    factors.append(_between(len(truth) - 1, 0, T))
    return session, factors


def test_a_back_end_only_session_needs_no_voxel_and_add_scan_says_it_does(world):
    session = Session(Config(), voxel=None)
    session.add_node("0", [])
    session.add_node("1", [(0, make_T(np.eye(3), np.array([1.0, 0, 0])), 1.0, INFO)])
    np.testing.assert_allclose(session.poses[1][:3, 3], [1, 0, 0], atol=1e-9)
    before = _state(session)
    assert "voxel" in _refused(session.add_scan, "scan", world[0])
    _assert_unchanged(session, before)
    r = session.run_result()  # the writers' RunResult, without a grid
    assert r.names == ["0", "1"] and np.isfinite(r.poses).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_an_odometry_chain_and_a_loop_through_the_session_match_a_batch_lm_solve(seed):
    rng = np.random.default_rng(seed)
    truth = _truth_poses(7, seed)
    session, factors = _odometry_session(truth, rng)
    batch = _batch(len(truth), factors, truth)
    np.testing.assert_allclose(session.poses, batch, rtol=0, atol=1e-6)
    rot, _ = relative_errors(session.poses, truth)
    assert 0.1 < rot.max() < 5.0  # the noise reached the poses, and the loop held them near the truth


def test_a_prior_moves_the_solution_as_a_batch_solve_does():
    import gtsam

    rng = np.random.default_rng(3)
    truth = _truth_poses(6, 3)
    session, factors = _odometry_session(truth, rng)
    before = session.poses[3].copy()
    target = truth[3] @ make_T(np.eye(3), np.array([0.5, 0.0, 0.0]))  # half a metre off in its own x
    info = np.diag([1e2] * 3 + [1e4] * 3)  # a stiff position, a loose rotation
    session.add_prior("n3", target, info)
    factors.append(
        gtsam.PriorFactorPose3(gtsam.symbol("x", 3), gtsam.Pose3(target), gtsam.noiseModel.Gaussian.Information(info))
    )
    np.testing.assert_allclose(session.poses, _batch(len(truth), factors, truth), rtol=0, atol=1e-6)
    after = session.poses[3]
    assert np.linalg.norm(after[:3, 3] - target[:3, 3]) < 0.5 * np.linalg.norm(before[:3, 3] - target[:3, 3])


def test_gnss_positions_and_a_prior_fix_the_world_without_an_anchor():
    """A SLAM stack's world: no anchor, a prior on the first node where it is in that world, GNSS fixes of an
    antenna 1 m above each node's origin, odometry between them; as gtsam's batch LM over the same factors."""
    import gtsam

    rng = np.random.default_rng(4)
    offset = make_T(Rotation.from_euler("z", 40, degrees=True).as_matrix(), np.array([120.0, -40.0, 3.0]))
    truth = offset[None] @ _truth_poses(6, 4)
    session = Session(Config(), voxel=None, anchor=False)
    session.add_node("n0", [])
    prior_info = np.diag([1e2] * 3 + [1.0] * 3)  # 6° and 1 m
    session.add_prior(0, truth[0], prior_info)
    arm, gnss = np.array([0.0, 0.0, 1.0]), np.eye(3) / 0.02**2
    factors = [
        gtsam.PriorFactorPose3(
            gtsam.symbol("x", 0), gtsam.Pose3(truth[0]), gtsam.noiseModel.Gaussian.Information(prior_info)
        )
    ]
    for k in range(len(truth)):
        if k:
            session.add_node(f"n{k}", [])
            T = _noisy(inv_T(truth[k - 1]) @ truth[k], rng)
            session.add_between(k - 1, k, T, ODOMETRY)
            factors.append(_between(k - 1, k, T))
        fix = transform_points(truth[k], arm[None])[0] + rng.normal(0, 0.02, 3)
        session.add_position(k, fix, gnss, point=arm)
        factors.append(gtsam.GPSFactorArm(gtsam.symbol("x", k), fix, arm, gtsam.noiseModel.Gaussian.Information(gnss)))
    poses = session.poses
    np.testing.assert_allclose(poses, _batch(len(truth), factors, truth, anchor=False), rtol=0, atol=1e-6)
    assert np.abs(poses[:, :3, 3] - truth[:, :3, 3]).max() < 0.2  # in the GNSS world, not the first node's


def test_add_factor_takes_any_gtsam_factor_and_keeps_it_through_the_robust_stage(scene):
    """A raw gtsam factor (a translation prior) on a node; then a node whose two edges disagree with no majority,
    so that the robust stage runs and ISAM2 restarts: the factor is still there, as a batch solve over the kept
    edges and it shows."""
    import gtsam

    session = _graph_session(scene, nodes=3)
    pull = session.poses[2][:3, 3] + [0.3, 0.0, 0.0]
    factor = gtsam.PoseTranslationPrior3D(session.key("2"), pull, gtsam.noiseModel.Isotropic.Sigma(3, 0.05))
    session.add_factor(factor)
    moved = session.poses[2][:3, 3]
    assert 0.05 < moved[0] - (pull[0] - 0.3) < 0.3
    wrong = _truth_edge(scene, 0, 3) @ make_T(Rotation.from_euler("z", 30, degrees=True).as_matrix(), np.zeros(3))
    session.add_node("3", [(0, wrong, 1.0, INFO), (1, _truth_edge(scene, 1, 3), 1.0, INFO)])
    assert session.robust_runs == 1
    kept = [e for e in session.edges if e.kept]
    factors = [_between(e.i, e.j, e.T, e.information) for e in kept] + [factor]
    np.testing.assert_allclose(session.poses, _batch(4, factors, session.poses), rtol=0, atol=1e-6)
    assert session.poses[2][0, 3] - _batch(4, factors[:-1], session.poses)[2][0, 3] > 0.05  # without it: back


def test_the_caller_s_factors_are_checked_and_a_refused_one_leaves_the_session_as_it_was(scene):
    import gtsam

    session = _graph_session(scene, nodes=2)
    session.add_node("waits", [])  # not placed: no edge yet
    before = _state(session)
    noise = gtsam.noiseModel.Isotropic.Sigma(6, 0.1)
    assert "not a node's key" in _refused(
        session.add_factor, gtsam.PriorFactorPose3(gtsam.symbol("y", 0), gtsam.Pose3(), noise)
    )
    assert "not placed" in _refused(session.add_factor, gtsam.PriorFactorPose3(session.key(2), gtsam.Pose3(), noise))
    _refused(session.add_factor, "a factor")
    _refused(session.add_between, 0, 0, np.eye(4), INFO)
    _refused(session.add_between, 0, "nobody", np.eye(4), INFO)
    _refused(session.add_between, 0, 1, np.diag([2.0, 2.0, 2.0, 1.0]), INFO)
    _refused(session.add_prior, 1, np.eye(4), np.diag([1.0] * 5 + [-1.0]))
    assert "not placed" in _refused(session.add_position, "waits", np.zeros(3), np.eye(3))
    _refused(session.add_position, 0, np.zeros(2), np.eye(3))
    _refused(session.add_position, 0, np.zeros(3), -np.eye(3))
    _assert_unchanged(session, before)

    free = Session(Config(), voxel=None, anchor=False)  # no anchor: a position alone leaves the rotation free
    free.add_node("0", [])
    assert "cannot take it" in _refused(free.add_position, 0, np.ones(3), np.eye(3))
    assert free._factors == []


def test_the_caller_s_factors_on_georeferenced_scans_are_in_the_input_frames(world):
    """Scans 4 200 km north, registered centred: a prior, an odometry step and a GNSS fix that agree with the
    current poses (input frames) move no point of a scan; a stiff prior 3 cm off puts the scan there."""
    scans = [P + UTM for P in world[:3]]
    session = _fed(scans)
    assert np.abs(session.centre(1) - UTM).max() < 10  # registered centred

    def moved(poses: np.ndarray, before: np.ndarray) -> float:
        return max(
            np.abs(transform_points(T, P) - transform_points(B, P)).max() for T, B, P in zip(poses, before, scans)
        )

    before = session.poses
    session.add_between(0, 1, inv_T(before[0]) @ before[1], ODOMETRY)
    session.add_prior(2, before[2], ODOMETRY)
    antenna = scans[1][0]  # a point of scan 1, in its input frame
    session.add_position(1, transform_points(before[1], antenna[None])[0], np.eye(3) * 1e4, point=antenna)
    assert moved(session.poses, before) < 1e-6
    target = make_T(np.eye(3), np.array([0.03, 0.0, 0.0])) @ before[2]
    session.add_prior(2, target, np.diag([1e12] * 6))
    assert moved(session.poses[2:], target[None]) < 1e-4
