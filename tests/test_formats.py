"""Scan formats read through other libraries (LAS/LAZ with laspy and lazrs, E57 with pye57) and the TUM pose
writer: files written here with those libraries read back to the points they hold; an unreadable file is a
one-line reason in ``skipped``, never silently ignored; TUM and KITTI files follow their formats' rules and
evo (the odometry evaluation tool) reads them to the same trajectory."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.config import Config
from sghr_gtsam.io.poses import read_tum, write_kitti, write_tum
from sghr_gtsam.io.scans import list_scans, load_scan
from sghr_gtsam.pipeline import load_scene
from sghr_gtsam.se3 import make_T
from sghr_gtsam.types import InputError

laspy = pytest.importorskip("laspy")
pye57 = pytest.importorskip("pye57")


def _points(n=400, seed=0):
    return np.random.default_rng(seed).uniform(-50, 50, (n, 3))


def _write_las(path, P, scale=1e-4):
    header = laspy.LasHeader(point_format=3, version="1.4")
    header.scales, header.offsets = [scale] * 3, P.min(0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = P.T
    las.write(path)


def _write_e57(path, parts):
    """``parts``: (points, rotation (3, 3), translation (3,)) per point set."""
    with pye57.E57(str(path), mode="w") as e57:
        for P, R, t in parts:
            w, x, y, z = np.roll(Rotation.from_matrix(R).as_quat(), 1)  # E57 stores w x y z
            e57.write_scan_raw({"cartesianX": P[:, 0], "cartesianY": P[:, 1], "cartesianZ": P[:, 2]},
                               rotation=np.array([w, x, y, z]), translation=np.asarray(t, dtype=float))


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_and_laz_read_back_to_their_scale(tmp_path, suffix):
    P = _points()
    _write_las(tmp_path / f"scan{suffix}", P)
    Q = load_scan(tmp_path / f"scan{suffix}")
    assert Q.shape == P.shape and Q.dtype == np.float64
    assert np.abs(Q - P).max() <= 0.5e-4 + 1e-9  # LAS stores integers at the header's scale


def test_laz_is_compressed(tmp_path):
    P = _points(5000)
    _write_las(tmp_path / "a.las", P)
    _write_las(tmp_path / "a.laz", P)
    assert (tmp_path / "a.laz").stat().st_size < 0.8 * (tmp_path / "a.las").stat().st_size
    np.testing.assert_array_equal(load_scan(tmp_path / "a.laz"), load_scan(tmp_path / "a.las"))


def test_e57_point_sets_are_moved_by_their_poses_into_one_scan(tmp_path):
    """Two point sets with their own poses: one scan, each set at R p + t."""
    P1, P2 = _points(300, 1), _points(200, 2)
    R1, t1 = Rotation.from_euler("z", 90, degrees=True).as_matrix(), np.array([1.0, 2.0, 3.0])
    R2, t2 = Rotation.from_euler("xyz", [10, -20, 30], degrees=True).as_matrix(), np.array([-5.0, 0.0, 0.5])
    _write_e57(tmp_path / "site.e57", [(P1, R1, t1), (P2, R2, t2)])
    Q = load_scan(tmp_path / "site.e57")
    expected = np.concatenate([P1 @ R1.T + t1, P2 @ R2.T + t2])
    np.testing.assert_allclose(Q, expected, atol=1e-5)  # pye57 writes the coordinates as float32


@pytest.mark.parametrize("name, content, reason", [
    ("broken.laz", "truncated", "not a readable LAZ file"),
    ("broken.las", b"LASF" + bytes(60), "not a readable LAS file"),
    ("broken.e57", b"ASTM-E57" + bytes(2000), "not a readable E57 file"),
])
def test_unreadable_files_are_skipped_with_their_reason(tmp_path, name, content, reason):
    scene = tmp_path / "scene"
    scene.mkdir()
    for k in range(2):
        _write_las(scene / f"good_{k}.las", _points(300, k))
    if content == "truncated":
        _write_las(tmp_path / "whole.laz", _points(3000))
        content = (tmp_path / "whole.laz").read_bytes()[:900]
    (scene / name).write_bytes(content)
    assert name in [p.name for p in list_scans(scene)]  # listed as a scan, not ignored
    with pytest.raises(InputError) as error:
        load_scan(scene / name)
    assert reason in str(error.value) and "\n" not in str(error.value)
    messages = []
    scans, skipped = load_scene(scene, Config(), log=messages.append)
    assert [s.name for s in scans] == ["good_0.las", "good_1.las"]
    assert list(skipped) == [name] and reason in skipped[name]
    assert any(m.startswith(f"skipped {name}: ") for m in messages)


def _random_poses(n, seed):
    rng = np.random.default_rng(seed)
    return make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.uniform(-100, 100, (n, 3)))


def test_tum_and_kitti_follow_their_format_rules(tmp_path):
    """TUM: 8 numbers a line, increasing timestamps, a unit quaternion x y z w last (qw >= 0 here) that is the
    rotation; KITTI: 12 numbers a line, the 3x4 [R | t] row by row."""
    poses = _random_poses(7, 0)
    stamps = [0, 1, 2, 4, 5, 8, 9]  # scan indices, with unregistered scans left out
    write_tum(tmp_path / "t.txt", poses, stamps)
    write_kitti(tmp_path / "k.txt", poses)
    rows = [line.split() for line in (tmp_path / "t.txt").read_text().splitlines()]
    assert all(len(r) == 8 for r in rows) and len(rows) == 7
    tum = np.array(rows, dtype=float)
    assert tum[:, 0].tolist() == stamps
    np.testing.assert_allclose(np.linalg.norm(tum[:, 4:], axis=1), 1.0, atol=1e-12)
    assert np.all(tum[:, 7] >= 0)
    np.testing.assert_allclose(Rotation.from_quat(tum[:, 4:]).as_matrix(), poses[:, :3, :3], atol=1e-12)
    np.testing.assert_allclose(tum[:, 1:4], poses[:, :3, 3], atol=1e-12)
    kitti = np.array([line.split() for line in (tmp_path / "k.txt").read_text().splitlines()], dtype=float)
    assert kitti.shape == (7, 12)
    np.testing.assert_array_equal(kitti.reshape(-1, 3, 4), poses[:, :3, :])


@settings(max_examples=30, deadline=None)
@given(st.integers(1, 30), st.integers(0, 2**31 - 1))
def test_tum_round_trip(n, seed):
    import tempfile
    from pathlib import Path

    poses = _random_poses(n, seed)
    with tempfile.TemporaryDirectory() as d:
        write_tum(Path(d) / "t.txt", poses, np.arange(n) * 0.5)
        stamps, back = read_tum(Path(d) / "t.txt")
    np.testing.assert_array_equal(stamps, np.arange(n) * 0.5)
    np.testing.assert_allclose(back, poses, atol=1e-12)


def test_tum_writer_and_reader_reject_bad_input(tmp_path):
    poses = _random_poses(3, 1)
    for stamps in ([0, 1], [0, 2, 1], [0, 0, 1]):
        with pytest.raises(ValueError, match="increasing timestamps"):
            write_tum(tmp_path / "t.txt", poses, stamps)
    (tmp_path / "bad.txt").write_text("0 1 2 3 0 0 0 2\n")
    with pytest.raises(InputError, match="quaternion of length 2"):
        read_tum(tmp_path / "bad.txt")
    (tmp_path / "short.txt").write_text("0 1 2 3 0 0 1\n")
    with pytest.raises(InputError, match="expected 8 numbers"):
        read_tum(tmp_path / "short.txt")


def test_evo_reads_tum_and_kitti_to_the_same_trajectory(tmp_path):
    """evo's own readers (what evo_traj / evo_ape call) load both files; APE between them is zero and against
    a shifted copy it is the shift."""
    file_interface = pytest.importorskip("evo.tools.file_interface", reason="evo is a test extra (pip install -e '.[test]')")
    from evo.core import metrics, sync

    poses = _random_poses(6, 2)
    write_tum(tmp_path / "poses_tum.txt", poses, np.arange(6))
    write_kitti(tmp_path / "poses_kitti.txt", poses)
    tum = file_interface.read_tum_trajectory_file(str(tmp_path / "poses_tum.txt"))
    kitti = file_interface.read_kitti_poses_file(str(tmp_path / "poses_kitti.txt"))
    np.testing.assert_array_equal(tum.timestamps, np.arange(6))
    np.testing.assert_allclose(np.array(tum.poses_se3), poses, atol=1e-12)
    np.testing.assert_allclose(np.array(kitti.poses_se3), poses, atol=1e-12)
    shifted = poses.copy()
    shifted[:, :3, 3] += [0.3, 0.0, 0.4]
    write_tum(tmp_path / "shifted.txt", shifted, np.arange(6))
    ref, est = sync.associate_trajectories(tum, file_interface.read_tum_trajectory_file(str(tmp_path / "shifted.txt")))
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, est))
    assert ape.get_statistic(metrics.StatisticsType.max) == pytest.approx(0.5)
