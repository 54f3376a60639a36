"""End to end on generated scenes with known poses (no real data needed)."""

import csv
import json
import re

import numpy as np
import pytest
import rerun as rr

from sghr_gtsam.config import Config
from sghr_gtsam.evaluate import scan_errors
from sghr_gtsam.io.g2o import read_g2o
from sghr_gtsam.io.poses import read_kitti, read_poses
from sghr_gtsam.pipeline import Scan, register, run
from sghr_gtsam.registration.visibility import CONFLICT
from sghr_gtsam.scene import load_scene
from sghr_gtsam.se3 import inv_T
from sghr_gtsam.synthetic import make_scene, write_scene
from sghr_gtsam.types import InputError


@pytest.fixture(scope="module")
def room_run(tmp_path_factory):
    scene = make_scene(kind="room", n_scans=6, seed=0)
    root = tmp_path_factory.mktemp("room")
    write_scene(scene, root / "scene")
    result = run(root / "scene", root / "out", Config(seed=0), log=lambda m: None)
    return scene, result, root / "out"


def test_room_scans_land_on_ground_truth(room_run):
    scene, result, _ = room_run
    gt = scene.poses[[scene.names.index(n) for n in result.names]]
    err = scan_errors(result.names, result.poses, gt)
    assert result.unregistered == []
    assert err.rotation_deg.max() < 1.0, err.rotation_deg
    assert err.translation.max() < 2 * result.voxel, err.translation


def test_outputs_parse_back_to_the_result(room_run):
    _, result, out = room_run
    names, poses = read_poses(out / "poses.txt")
    assert names == result.names
    np.testing.assert_allclose(poses, result.poses, atol=1e-8)
    assert np.allclose(poses[0], np.eye(4))
    np.testing.assert_allclose(read_kitti(out / "poses_kitti.txt"), result.poses, atol=1e-8)

    ids, g2o_poses, graph = read_g2o(out / "graph.g2o")
    assert ids == list(range(len(result.names)))
    np.testing.assert_allclose(g2o_poses, result.poses, atol=1e-6)
    np.testing.assert_array_equal(graph.i, result.graph.i)
    np.testing.assert_array_equal(graph.j, result.graph.j)
    np.testing.assert_allclose(graph.T, result.graph.T, atol=1e-6)

    with open(out / "edges.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == result.graph.num_edges
    assert {int(r["i"]) for r in rows} | {int(r["j"]) for r in rows} <= set(range(len(result.names)))
    np.testing.assert_allclose([float(r["final_weight"]) for r in rows], result.sync.weights, rtol=1e-5)
    # a generated room's scans are seen from their origins: every pair checked, the contradicted ones weigh nothing
    conflict = np.array([float(r["free_space_conflict"]) for r in rows])
    np.testing.assert_allclose(conflict, result.edge_conflict, atol=1e-4)
    assert all((r["status"] == "contradicted") == (c > CONFLICT) for r, c in zip(rows, conflict))
    assert all(float(r["initial_weight"]) == 0 for r, c in zip(rows, conflict) if c > CONFLICT)

    report = json.loads((out / "report.json").read_text())
    n = len(result.names)
    assert report["pairs_exhaustive"] == n * (n - 1) // 2
    assert report["pairs_registered"] == result.graph.num_edges
    # every scan of a generated room is placed right: one part, each scan verified, no doubt
    assert report["unregistered"] == [] and report["doubts"] == result.verdict.doubts == {}
    assert report["status"] == {name: "verified" for name in result.names}
    assert [p["scans"] for p in report["parts"]] == [result.names] and report["parts"][0]["join"] is None
    # kept edges only: a failed registration's free directions listed a perfect scene as degenerate
    assert report["degenerate_pairs"] == [
        [result.names[i], result.names[j], p.free]
        for i, j, p, r in zip(result.graph.i, result.graph.j, result.pairs, rows)
        if p.free and r["status"] == "kept"
    ]
    assert report["peak_memory_mb"] > 0
    assert {"features", "pairwise", "sync", "total"} <= set(report["seconds"])
    assert Config.from_json(out / "config.json") == Config(seed=0)
    assert (out / "merged.ply").stat().st_size > 1000
    assert not list(out.glob("*.partial")) and not list(out.glob(".*tmp*"))


def test_recording_holds_every_iteration(room_run):
    _, result, out = room_run
    store = rr.chunk.RrdReader(out / "recording.rrd").stream().collect()
    summary = store.summary()
    for name in result.names:
        assert f"/world/scans/{name}" in summary
    assert "/world/edges" in summary and "/metrics/median_residual_deg" in summary
    assert "/residuals" in summary and "/weights" in summary  # every edge a series of one entity
    irls = [r for r in result.sync.history if r.stage == "irls"]
    assert len(irls) == Config().iters
    stages = {r.stage for r in result.sync.history}
    assert {"irls", "lm"} < stages  # the polish's own stages are recorded between them
    line = next(row for row in summary.splitlines() if row.startswith("/metrics/median_residual_deg"))
    rows = int(line.split("rows=")[1].split()[0].rstrip(","))
    # one row per record of every synchronization: the first, then one per front-end round (the result keeps
    # the last one's history)
    assert rows > len(result.sync.history) if result.densify["rounds"] else rows == len(result.sync.history)


def test_result_does_not_depend_on_the_world_frame():
    """Registering the same scans twice with one scan moved gives the same relative poses."""
    scene = make_scene(kind="room", n_scans=4, seed=2)
    scans = [Scan(n, P) for n, P in zip(scene.names, scene.scans)]
    a = register(scans, Config(record=False), log=lambda m: None)
    T = np.eye(4)
    T[:3, 3] = [1.0, -2.0, 0.5]
    moved = [Scan(s.name, s.source @ T[:3, :3].T + T[:3, 3]) if k == 2 else s for k, s in enumerate(scans)]
    b = register(moved, Config(record=False), log=lambda m: None)
    rel_a = inv_T(a.poses[0]) @ a.poses[2]
    rel_b = inv_T(b.poses[0]) @ b.poses[2] @ T
    np.testing.assert_allclose(rel_a, rel_b, atol=5e-3)


def test_identical_scans_are_placed_on_top_of_each_other(tmp_path):
    scene = make_scene(kind="room", n_scans=3, seed=4)
    scans = [Scan(n, P) for n, P in zip(scene.names, scene.scans)]
    scans.append(Scan("copy.npy", scene.scans[1].copy()))
    res = register(scans, Config(record=False), log=lambda m: None)
    rel = inv_T(res.poses[1]) @ res.poses[3]
    np.testing.assert_allclose(rel, np.eye(4), atol=1e-3)


def test_initial_weight_ablations_use_score_or_inliers_alone():
    """``initial_weight``: w⁰ = s·r (SGHR), s alone or r alone (the paper's ablations), same pairs."""
    scene = make_scene(kind="room", n_scans=4, seed=5)
    scans = [Scan(f"s{k}", P) for k, P in enumerate(scene.scans)]
    runs = {w: register(scans, Config(record=False, initial_weight=w), log=lambda m: None) for w in ("s*r", "s", "r")}
    g = runs["s*r"].graph
    s = runs["s*r"].scores[g.i, g.j]
    r = np.array([p.inliers for p in runs["s*r"].pairs], dtype=float)
    assert (r > 0).any()
    np.testing.assert_allclose(runs["r"].graph.weight, np.where(r >= Config().inlier_bar, r, 0.0))
    np.testing.assert_allclose(runs["s"].graph.weight, np.where(r >= Config().inlier_bar, s, 0.0))
    np.testing.assert_allclose(g.weight, runs["s"].graph.weight * runs["r"].graph.weight)


# --- what the API refuses or skips before any work (a hostile review) ---------------------------------


def _room_scans(n: int = 4) -> list[Scan]:
    scene = make_scene(kind="room", n_scans=n, seed=1)
    return [Scan(name, P) for name, P in zip(scene.names, scene.scans)]


@pytest.mark.parametrize(
    "names, message",
    [
        (["a", "b", "c", "a"], "two scans are named 'a'"),
        (["a", "", "c", "d"], "scan name '' cannot be written on its own line"),
        (["a", "b\nc", "d", "e"], r"scan name 'b\nc' cannot be written on its own line"),
        (["a", "#b", "c", "d"], "scan name '#b' cannot be written on its own line"),
        (["a", "b", " c", "d"], "scan name ' c' cannot be written on its own line"),
        (["a", "b", "c", "d\t"], r"scan name 'd\t' cannot be written on its own line"),
    ],
)
def test_register_refuses_names_results_cannot_be_matched_by(names, message):
    """Duplicate names were accepted: the first scan lost its pose in every output and two others were flagged. A
    name starting with '#' or a space, or ending with one, passed and was refused only by the pose file's writer,
    once the run was done (``io.poses.unwritable_name``, the one rule for both)."""
    scans = [Scan(name, s.source) for name, s in zip(names, _room_scans())]
    with pytest.raises(InputError, match=re.escape(message)):
        register(scans, Config(workers=1, record=False), log=lambda m: None)


def test_scan_files_whose_names_a_pose_file_cannot_hold_are_skipped(tmp_path):
    """A scan file named '#…' or ' …' was registered, and the run ended when its results were written ("pose name
    ' scan_01.ply' cannot be written on its own line"); such a file is now skipped with its reason."""
    scene = make_scene(kind="room", n_scans=4, seed=1)
    write_scene(scene, tmp_path)
    (tmp_path / "scan_00.ply").rename(tmp_path / "#scan_00.ply")
    (tmp_path / "scan_01.ply").rename(tmp_path / " scan_01.ply")
    scans, skipped = load_scene(tmp_path, Config(), log=lambda m: None)
    assert [s.name for s in scans] == ["scan_02.ply", "scan_03.ply"]
    assert skipped == {
        name: f"its name {name!r} cannot be written on its own line in the pose files: rename it"
        for name in ("#scan_00.ply", " scan_01.ply")
    }


def test_noise_scans_that_set_the_automatic_voxel_are_named_when_nothing_registers():
    """Two room scans and three small clouds of noise: the median scan, hence the voxel, is noise's, 1/10 of the
    rooms', and no pair registers. The message said only "do the scans overlap?"."""
    scene = make_scene(kind="room", n_scans=2, seed=1)
    rng = np.random.default_rng(0)
    noise = [Scan(f"noise_{k}.npy", rng.uniform(-0.22, 0.22, (2000, 3)) + scene.scans[0].mean(0)) for k in range(3)]
    scans = [Scan(name, P) for name, P in zip(scene.names, scene.scans)] + noise
    with pytest.raises(
        InputError,
        match=r"\(do the scans overlap\? is the voxel 0.007\d+ right\? it is 1/100 of the "
        r"median scan's extent \(0.7\d+\), and scan_00.ply \((9.9|10)x\), "
        r"scan_01.ply \((9.9|10)x\) differ from it by more than 3x: ",
    ):
        register(scans, Config(workers=1, record=False), log=lambda m: None)


def test_a_featureless_scan_leaves_the_other_edges_their_information():
    """A flat scan matches nothing (fewer than 3 matches: a pair without information). It took the information of
    every edge with it: synchronization without it, graph.g2o with the uncalibrated default (370 on every axis)."""
    scene = make_scene(kind="room", n_scans=4, seed=1)
    scans = [Scan(name, P) for name, P in zip(scene.names, scene.scans)]
    rng = np.random.default_rng(0)
    scans.append(Scan("plane.npy", np.c_[rng.uniform(-1, 1, (5000, 2)), np.zeros(5000)] + scene.scans[0].mean(0)))
    result = register(scans, Config(workers=1, record=False), log=lambda m: None)
    assert result.unregistered == ["plane.npy"]
    measured = [e for e, p in enumerate(result.pairs) if p.information is not None]
    assert result.graph.information is not None and len(measured) < len(result.pairs)
    assert np.array_equal(result.graph.information[measured], np.stack([result.pairs[e].information for e in measured]))
    assert (np.linalg.eigvalsh(result.graph.information)[:, 0] > 0).all()
    assert scan_errors(result.names[:4], result.poses[:4], scene.poses).within(1.0, 0.02).all()


def test_noise_scans_whose_registrations_measure_few_directions_do_not_stop_the_run():
    """Clouds of noise registered onto a room wall: a failed registration whose close points fix only 4 of the 6
    directions. Its singular information ended the run ("edge 4: information is not positive definite")."""
    scene = make_scene(kind="room", n_scans=2, seed=1)
    rng = np.random.default_rng(0)
    noise = [Scan(f"noise_{k}.npy", rng.uniform(-0.7, 0.7, (2000, 3)) + scene.scans[0].mean(0)) for k in range(3)]
    scans = [Scan(name, P) for name, P in zip(scene.names, scene.scans)] + noise
    result = register(scans, Config(workers=1, record=False), log=lambda m: None)
    assert result.unregistered == [s.name for s in noise]
    assert (np.linalg.eigvalsh(result.graph.information)[:, 0] > 0).all()
    assert scan_errors(result.names[:2], result.poses[:2], scene.poses).within(1.0, 0.02).all()


def test_a_voxel_too_small_for_any_scan_is_named_not_the_scans():
    """``--voxel 1e-300``: every scan was skipped as "its points span 4.82e+300 voxels …: a stray point far away?"."""
    scene = make_scene(kind="room", n_scans=3, seed=1)
    with pytest.raises(InputError, match=r"^voxel 1e-300 is too small: the median scan's diagonal spans \S+ voxels"):
        register(
            [Scan(n, P) for n, P in zip(scene.names, scene.scans)],
            Config(workers=1, record=False, voxel=1e-300),
            log=lambda m: None,
        )


def test_degenerate_pairs_lists_only_the_edges_the_result_rests_on(tmp_path):
    """A 9-scan building every scan of which is right: report.json listed 14 "degenerate pairs", every one a failed,
    contradicted or rejected registration (a wrong transform leaves directions free)."""
    scene = make_scene("building", 9, seed=0)
    write_scene(scene, tmp_path / "scene")
    result = run(tmp_path / "scene", tmp_path / "out", Config(record=False, workers=1), log=lambda m: None)
    with open(tmp_path / "out" / "edges.csv") as f:
        status = [r["status"] for r in csv.DictReader(f)]
    assert any(p.free > 0 and s != "kept" for p, s in zip(result.pairs, status))  # what the listing leaves out
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["degenerate_pairs"] == [
        [result.names[i], result.names[j], p.free]
        for i, j, p, s in zip(result.graph.i, result.graph.j, result.pairs, status)
        if p.free and s == "kept"
    ]


def test_register_skips_a_scan_under_min_points_and_subsets_given_scores():
    """``min_points`` was checked only when scans were read from a folder; scores given for every scan could not
    be used once one was skipped ("must be a 3x3 matrix")."""
    scene = make_scene(kind="room", n_scans=4, seed=1)
    scans = [Scan(name, P) for name, P in zip(scene.names, scene.scans)]
    scans[3] = Scan("sparse", scene.scans[3][::300])
    scores = np.full((4, 4), 0.5)
    result = register(scans, Config(workers=1, record=False, min_points=1000), log=lambda m: None, scores=scores)
    assert result.skipped == {"sparse": f"only {len(scene.scans[3][::300])} finite points (< 1000)"}
    assert result.names == scene.names[:3] and not result.unregistered
    errors = scan_errors(result.names, result.poses, scene.poses[:3])
    assert errors.within(2.0, 0.05).all(), errors


def test_config_refuses_a_misspelt_setting_and_a_seed_open3d_cannot_take():
    config = Config()
    with pytest.raises(AttributeError, match="no setting 'voxle'"):
        config.voxle = 0.1
    with pytest.raises(InputError, match="seed must be an integer in"):
        Config(seed=2**31, matcher="ransac").validate()


def test_config_takes_numpy_scalars_as_python_numbers_and_reads_odd_json_in_one_line(tmp_path):
    """``k=np.int64(3)`` was refused ("k must be int") and a numpy float32 broke ``to_json``; a config file nested
    50,000 deep or holding a 5,000-digit number raised RecursionError / ValueError."""
    config = Config(k=np.int64(3), voxel=np.float32(0.5), record=np.bool_(False)).validate()
    assert json.loads(config.to_json())["k"] == 3 and type(config.voxel) is float
    for name, text in (("deep.json", "[" * 50_000 + "]" * 50_000), ("long.json", '{"k": ' + "9" * 5000 + "}")):
        (tmp_path / name).write_text(text)
        with pytest.raises(InputError, match=f"cannot read config .*{name}"):
            Config.from_json(tmp_path / name)


def test_result_does_not_depend_on_how_scans_are_named_or_listed():
    """The same scans listed in reverse order under other names: the same pairs registered the same way round, the
    same relative poses and the same status of every scan (the stages take the scans in an order of their content,
    ``pipeline._content_order``)."""
    scene = make_scene(kind="room", n_scans=6, seed=3)
    scans = [Scan(n, P) for n, P in zip(scene.names, scene.scans)]
    a = register(scans, Config(record=False), log=lambda m: None)
    renamed = [Scan(f"z{5 - k}", s.source) for k, s in enumerate(scans)][::-1]
    b = register(renamed, Config(record=False), log=lambda m: None)
    to_a = {f"z{5 - k}": k for k in range(6)}  # b's name -> the scan's index in a
    back = np.array([to_a[n] for n in b.names])
    pairs_a = {(int(i), int(j)) for i, j in zip(a.graph.i, a.graph.j)}
    pairs_b = {(int(back[i]), int(back[j])) for i, j in zip(b.graph.i, b.graph.j)}
    assert pairs_a == pairs_b
    for k in range(1, 6):
        rel_a = inv_T(a.poses[0]) @ a.poses[k]
        rel_b = inv_T(b.poses[np.flatnonzero(back == 0)[0]]) @ b.poses[np.flatnonzero(back == k)[0]]
        np.testing.assert_allclose(rel_a, rel_b, atol=1e-6)
    assert {a.names[to_a[n]]: status for n, status in b.verdict.status.items()} == a.verdict.status
