"""Bad input to the public API is a one-line ``InputError`` (never a deep library error or a silent wrong result),
a writer refuses before it writes, and what a writer writes its reader reads (the hostile API review)."""

import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.evaluate import (
    align_rigid,
    fragment_id,
    registration_recall,
    scan_errors,
    score_run,
    whole_model_errors,
)
from sghr_gtsam.gtsam_api import noise_model, optimize, repolish, sigmas, to_gtsam
from sghr_gtsam.io.g2o import read_g2o, write_g2o
from sghr_gtsam.io.poses import read_kitti, read_poses, read_tum, write_kitti, write_poses, write_tum
from sghr_gtsam.se3 import inv_T, make_T, relative_errors
from sghr_gtsam.types import InputError, PoseGraph


def _rigid(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_T(Rotation.random(n, random_state=seed).as_matrix(), rng.uniform(-2, 2, (n, 3)))


def _ring(n: int = 4, seed: int = 0) -> tuple[PoseGraph, np.ndarray]:
    """Exact edges k → k+1 around a ring and one chord, each with information diag(100, ..., 100)."""
    truth = _rigid(n, seed)
    i = np.r_[np.arange(n), 0]
    j = np.r_[(np.arange(n) + 1) % n, n // 2]
    T = np.stack([inv_T(truth[a]) @ truth[b] for a, b in zip(i, j)])
    return PoseGraph(n, i, j, T, np.ones(len(i)), np.repeat(100.0 * np.eye(6)[None], len(i), 0)), truth


def _refused(match: str, fn, *args, **kwargs) -> None:
    with pytest.raises(InputError, match=match) as info:
        fn(*args, **kwargs)
    assert "\n" not in str(info.value)


# --- 1. g2o: an edge-only file (a run's graph_rejected.g2o) reads back ---------------------------------------------


def test_review_example_edge_only_file_reads():
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "r.g2o"
        write_g2o(path, [0, 1], None, PoseGraph(2, np.array([0]), np.array([1]), np.eye(4)[None], np.ones(1)))
        ids, poses, graph = read_g2o(path)
        assert ids == [0, 1] and poses is None
        assert graph.i.tolist() == [0] and graph.j.tolist() == [1]
        np.testing.assert_array_equal(graph.information[0], np.eye(6))
        # `sync` (positive_definite) optimizes vertices: a file without them is refused as before
        _refused("no VERTEX_SE3:QUAT lines", read_g2o, path, positive_definite=True)


@settings(max_examples=30, deadline=None)
@given(st.integers(2, 8), st.data())
def test_run_like_rejected_graph_round_trips(n, data):
    """graph_rejected.g2o as a run writes it: every scan an id, edges between some of them, a failed registration's
    zero information among measured ones; read back: the ids the edges name, the same edges and values."""
    pairs = [(a, b) for a in range(n) for b in range(n) if a != b]
    chosen = data.draw(st.lists(st.sampled_from(pairs), max_size=6))
    failed = data.draw(st.lists(st.booleans(), min_size=len(chosen), max_size=len(chosen)))
    seed = data.draw(st.integers(0, 2**31 - 1))
    E = len(chosen)
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(E, 6, 6))
    info = np.where(np.array(failed, bool)[:, None, None], 0.0, A @ np.swapaxes(A, 1, 2) + np.eye(6))
    i = np.array([a for a, _ in chosen], dtype=int)
    j = np.array([b for _, b in chosen], dtype=int)
    graph = PoseGraph(n, i, j, _rigid(E, seed), np.ones(E), info)
    scans = list(range(10, 10 + n))
    with tempfile.TemporaryDirectory() as d:
        write_g2o(Path(d) / "graph_rejected.g2o", scans, None, graph)
        ids, poses, back = read_g2o(Path(d) / "graph_rejected.g2o")
    assert poses is None and ids == sorted({scans[k] for k in (*i, *j)})
    assert back.n == len(ids) and back.num_edges == E
    assert [(ids[a], ids[b]) for a, b in zip(back.i, back.j)] == [(scans[a], scans[b]) for a, b in chosen]
    np.testing.assert_allclose(back.T.reshape(E, 4, 4), graph.T, atol=1e-12)
    np.testing.assert_array_equal(back.information, info)


# --- 2. writers refuse what their readers reject, before writing ----------------------------------------------------


@pytest.mark.parametrize(
    "case, ids, i, j, match",
    [
        ("duplicate ids", [3, 3], [0], [1], "duplicate vertex ids"),
        ("string id", ["a", 1], [0], [1], "ids must be integers"),
        ("float id", [0.0, 1], [0], [1], "ids must be integers"),
        ("edge index out of range", [0, 1], [0], [2], "not two different nodes"),
        ("negative edge index", [0, 1], [-1], [1], "not two different nodes"),
        ("self-loop", [0, 1], [1], [1], "not two different nodes"),
    ],
)
def test_write_g2o_refuses_what_read_g2o_rejects(tmp_path, case, ids, i, j, match):
    graph = PoseGraph(2, np.array(i), np.array(j), np.eye(4)[None], np.ones(1))
    _refused(match, write_g2o, tmp_path / "g.g2o", ids, np.stack([np.eye(4)] * 2), graph)
    assert not (tmp_path / "g.g2o").exists()


def test_write_g2o_refuses_bad_values(tmp_path):
    graph = PoseGraph(2, np.array([0]), np.array([1]), np.eye(4)[None], np.ones(1), np.eye(6)[None])
    poses = np.stack([np.eye(4)] * 2)
    sheared = np.eye(4)
    sheared[0, 1] = 0.5
    for bad, match in (
        (replace(graph, T=2 * np.eye(4)[None]), "edge 0 is not a rigid transform"),
        (replace(graph, T=sheared[None]), "edge 0 is not a rigid transform"),
        (replace(graph, information=-np.eye(6)[None]), "not positive semi-definite"),
        (replace(graph, information=np.triu(np.ones((6, 6)))[None]), "not symmetric"),
    ):
        _refused(match, write_g2o, tmp_path / "g.g2o", [0, 1], poses, bad)
    nan = np.stack([np.eye(4), np.full((4, 4), np.nan)])
    _refused("pose 1 is not finite", write_g2o, tmp_path / "g.g2o", [0, 1], nan, graph)
    assert list(tmp_path.iterdir()) == []


def test_empty_pose_files_are_refused_by_writer_and_reader_alike(tmp_path):
    for write, args in (
        (write_poses, ([], np.zeros((0, 4, 4)))),
        (write_kitti, (np.zeros((0, 4, 4)),)),
        (write_tum, (np.zeros((0, 4, 4)), [])),
    ):
        _refused("non-empty", write, tmp_path / "p.txt", *args)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "p.txt").write_text("")
    for read in (read_poses, read_kitti, read_tum):
        _refused("no entries", read, tmp_path / "p.txt")


# --- 3. io.poses ---------------------------------------------------------------------------------------------------


def test_write_tum_refuses_poses_it_cannot_write_as_a_quaternion(tmp_path):
    poses = _rigid(3, 1)
    nan = poses.copy()
    nan[1, 0, 0] = np.nan
    scaled = poses.copy()
    scaled[2, :3, :3] *= 2.0  # read back as a rotation it would differ by up to 1
    mirrored = poses.copy()
    mirrored[0, :3, 0] *= -1.0
    for bad, match in (
        (nan, "TUM pose 1 is not finite"),
        (scaled, "TUM pose 2 is not a rigid"),
        (mirrored, "TUM pose 0 is not a rigid"),
    ):
        _refused(match, write_tum, tmp_path / "t.txt", bad, [0, 1, 2])
    _refused("finite increasing timestamps", write_tum, tmp_path / "t.txt", poses, [0, np.nan, 2])
    _refused("finite increasing timestamps", write_tum, tmp_path / "t.txt", poses, [0, 1, np.inf])
    assert list(tmp_path.iterdir()) == []


def test_write_poses_refuses_names_that_are_not_strings(tmp_path):
    _refused("is not a string", write_poses, tmp_path / "p.txt", [0, 1], _rigid(2, 0))
    _refused("2 names for 3 poses", write_poses, tmp_path / "p.txt", ["a", "b"], _rigid(3, 0))
    assert list(tmp_path.iterdir()) == []


# --- 4. evaluate ---------------------------------------------------------------------------------------------------


def test_fragment_id_ignores_the_digits_of_the_suffix():
    """``.e57`` is a scan format: its digits are no fragment number (recall was scored against fragment 57)."""
    names = ["cloud_bin_3.e57", "cloud_bin_21.ply", "cloud_bin_4.las", "cloud_bin_7", "scan.e57"]
    assert [fragment_id(n) for n in names] == [3, 21, 4, 7, None]


def test_scan_errors_refuses_mismatched_input():
    poses = _rigid(3, 2)
    _refused("3 names, poses", scan_errors, ["a", "b", "c"], poses, poses[:2])
    _refused("2 names, poses", scan_errors, ["a", "b"], poses, poses)  # names would disagree with the arrays
    _refused("reference scan 5", scan_errors, ["a", "b", "c"], poses, poses, reference=5)


def test_score_run_refuses_mismatched_names_and_poses():
    poses = _rigid(4, 3)
    names = ["a", "b", "c", "d"]
    _refused("3 names for 4 poses", score_run, names[:3], poses, names, poses)
    _refused("3 GT names for 4 GT poses", score_run, names, poses, names[:3], poses)


def test_alignments_refuse_nan():
    poses = _rigid(4, 4)
    bad = poses.copy()
    bad[2, 0, 3] = np.nan
    _refused("finite poses", whole_model_errors, list("abcd"), bad, poses)
    _refused("finite poses", whole_model_errors, list("abcd"), poses, bad, align="poses")
    _refused("not finite", align_rigid, bad[:, :3, 3], poses[:, :3, 3])


def test_registration_recall_names_a_missing_info_entry():
    poses = _rigid(4, 5)
    log = {(0, 2): inv_T(poses[0]) @ poses[2], (1, 3): inv_T(poses[1]) @ poses[3]}
    _refused(
        r"no entry for the gt.log pair \(1, 3\)", registration_recall, [0, 1, 2, 3], poses, log, {(0, 2): np.eye(6)}
    )
    assert registration_recall([0, 1, 2, 3], poses, log, {p: np.eye(6) for p in log}).recall == 1.0


# --- 5. gtsam_api --------------------------------------------------------------------------------------------------


def test_to_gtsam_refuses_bad_graphs():
    graph, truth = _ring()
    nan_info = graph.information.copy()
    nan_info[1, 2, 2] = np.nan
    T = graph.T.copy()
    T[0, :3, :3] *= 1.5
    bad_j = graph.j.copy()
    bad_j[0] = 9
    cases = [
        (replace(graph, information=nan_info), truth, "edge 1: information is not finite"),
        (replace(graph, information=-graph.information), truth, "not positive semi-definite"),
        (replace(graph, information=np.repeat(np.eye(3)[None], graph.num_edges, 0)), truth, r"shape \(5, 6, 6\)"),
        (replace(graph, T=T), truth, "T is not a rigid transform"),
        (replace(graph, j=graph.i.copy()), truth, "to itself"),
        (replace(graph, j=bad_j), truth, "out of range"),
        (replace(graph, j=-graph.j), truth, "out of range"),
        (graph, np.where(np.arange(4)[:, None, None] == 2, np.nan, truth), "pose 2 is not finite"),
        (graph, truth * np.array([1, 1, 2, 1])[None, :, None], "pose 0 is not a rigid transform"),
    ]
    for g, poses, match in cases:
        _refused(match, to_gtsam, g, poses)


def test_to_gtsam_refuses_bad_masks_and_keys():
    graph, truth = _ring()
    _refused("boolean mask of shape", to_gtsam, graph, truth, edges=np.ones(3, bool))
    _refused("boolean mask of shape", to_gtsam, graph, truth, edges=np.array([0, 1, 2, 3, 4]))
    _refused("3 given for 4 nodes", to_gtsam, graph, truth, keys=[10, 11, 12])
    _refused("same key", to_gtsam, graph, truth, keys=[10, 11, 11, 12])
    _refused("same key", to_gtsam, graph, truth, keys=lambda k: 7)
    _refused("integers", to_gtsam, graph, truth, keys=lambda k: -1 - k)


def test_a_zero_information_edge_is_accepted_and_a_nan_one_no_longer_returns_the_start():
    """Zero information (a failed registration) is semi-definite: a factor without pull. NaN information was
    accepted and LM returned the initial poses as if optimal."""
    graph, truth = _ring()
    info = graph.information.copy()
    info[0] = 0.0
    factors, values = to_gtsam(replace(graph, information=info), truth)
    assert factors.size() == graph.num_edges and factors.error(values) == pytest.approx(0.0, abs=1e-9)
    info[0] = np.nan
    _refused("information is not finite", to_gtsam, replace(graph, information=info), truth)


def test_noise_model_and_sigmas_refuse_wrong_shapes():
    _refused(r"shape \(6, 6\)", noise_model, np.eye(3))
    _refused("not positive semi-definite", noise_model, -np.eye(6))
    _refused(r"\(N, 6, 6\)", sigmas, np.eye(6))
    rot, trans = sigmas(np.eye(6)[None] * 4.0)
    assert rot[0] == pytest.approx(np.degrees(2.0)) and trans[0] == pytest.approx(2.0)


def test_repolish_refuses_a_graph_without_edges_and_bad_components():
    graph, truth = _ring()
    empty = PoseGraph(4, np.zeros(0, int), np.zeros(0, int), np.zeros((0, 4, 4)), np.zeros(0), np.zeros((0, 6, 6)))
    _refused("no edges", repolish, empty, truth, np.zeros(0, bool), np.zeros(4, int))
    _refused(r"component must have shape \(4,\)", repolish, graph, truth, np.ones(5, bool), np.zeros(3, int))
    start = truth @ make_T(np.eye(3), np.full(3, 0.05))[None]
    poses = repolish(graph, start, np.ones(5, bool), np.zeros(4, int))
    rot, trans = relative_errors(inv_T(poses[0])[None] @ poses, inv_T(truth[0])[None] @ truth)
    assert rot.max() < 1e-6 and trans.max() < 1e-6


def test_optimize_refuses_factors_without_values():
    graph, truth = _ring()
    factors, values = to_gtsam(graph, truth)
    _, fewer = to_gtsam(graph, truth, edges=np.array([True, False, False, False, False]))
    _refused("have no value", optimize, factors, fewer)
    _refused("not a factor index", optimize, factors, values, kernel="tls", known_inliers=[99])
