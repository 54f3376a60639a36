"""Readers and writers: exact round trips, one-line InputError on every kind of bad file, atomic
output, and the real ground-truth files read with the documented conventions."""

import os
import tempfile
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from sghr_gtsam.io.atomic import atomic_path, atomic_write
from sghr_gtsam.io.poses import (
    read_gt_info,
    read_gt_log,
    read_gt_overlap,
    read_kitti,
    read_poses,
    write_kitti,
    write_poses,
)
from sghr_gtsam.io.scans import finite_points, left_out, list_scans, load_scan, point_count, write_ply, write_scan
from sghr_gtsam.se3 import inv_T, make_T, project_to_so3
from sghr_gtsam.types import InputError


def _rigid(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return make_T(Rotation.random(n, random_state=seed).as_matrix(), rng.normal(0, 3, (n, 3)))


def _points(n: int = 500, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 2, (n, 3))


def _assert_one_line_input_error(path: Path, *needles: str) -> None:
    with pytest.raises(InputError) as info:
        load_scan(path)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"cannot read scan {path}: ")
    for needle in needles:
        assert needle in message, message


# --- poses ----------------------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
names = st.text(st.characters(min_codepoint=32, max_codepoint=0x2FF), min_size=1).filter(
    lambda s: s.strip() == s and s.splitlines() == [s] and not s.startswith("#")
)


@settings(max_examples=40, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(1, 5), st.just(4), st.just(4)), elements=finite), st.data())
def test_poses_round_trip_exactly(poses, data):
    scan_names = data.draw(st.lists(names, min_size=len(poses), max_size=len(poses)))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "poses.txt"
        write_poses(path, scan_names, poses, comment="two\ncomment lines")
        got_names, got = read_poses(path)
        assert path.read_text().startswith("# two\n# comment lines\n")
        write_kitti(Path(d) / "kitti.txt", poses)
        kitti = read_kitti(Path(d) / "kitti.txt")
    assert got_names == scan_names
    np.testing.assert_array_equal(got, poses)
    np.testing.assert_array_equal(kitti[:, :3], poses[:, :3])
    np.testing.assert_array_equal(kitti[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (len(poses), 1)))


def test_poses_file_with_comments_blank_lines_and_numeric_names(tmp_path):
    path = tmp_path / "p.txt"
    rows = "\n".join(" ".join(map(str, r)) for r in np.eye(4))
    path.write_text(f"# header\n\n0\n{rows}\n# between\n  a b.ply  \n{rows}\n\n")
    got_names, got = read_poses(path)
    assert got_names == ["0", "a b.ply"]
    np.testing.assert_array_equal(got, np.stack([np.eye(4)] * 2))


@pytest.mark.parametrize(
    "text, needle",
    [
        ("", "no entries"),
        ("a\n1 0 0 0\n0 1 0 0\n0 0 1 0\n", "5-line blocks"),
        ("a\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 x 1\n", "line 5: expected 4 numbers"),
        ("a\n1 0 0 0\n0 1 0 0\n0 0 1 0 7\n0 0 0 1\n", "line 4: expected 4 numbers"),
    ],
)
def test_bad_poses_file_is_one_line_input_error(tmp_path, text, needle):
    path = tmp_path / "p.txt"
    path.write_text(text)
    with pytest.raises(InputError, match=needle) as info:
        read_poses(path)
    assert "\n" not in str(info.value)


def test_missing_pose_files_are_input_errors(tmp_path):
    for reader in (read_poses, read_kitti, read_gt_log, read_gt_info, read_gt_overlap):
        with pytest.raises(InputError, match="no such file"):
            reader(tmp_path / "missing.txt")


def test_bad_kitti_and_gt_files(tmp_path):
    (tmp_path / "k.txt").write_text("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(InputError, match="expected 12 numbers"):
        read_kitti(tmp_path / "k.txt")
    (tmp_path / "gt.log").write_text("0 x 60\n" + "1 0 0 0\n" * 4)
    with pytest.raises(InputError, match="expected 'i j"):
        read_gt_log(tmp_path / "gt.log")
    (tmp_path / "o.log").write_text("0,1\n")
    with pytest.raises(InputError, match="expected 3 numbers"):
        read_gt_overlap(tmp_path / "o.log")


def test_writers_reject_mismatched_input(tmp_path):
    with pytest.raises(ValueError):
        write_poses(tmp_path / "p.txt", ["a"], _rigid(2))
    with pytest.raises(ValueError):
        write_poses(tmp_path / "p.txt", ["# looks like a comment"], _rigid(1))
    with pytest.raises(ValueError):
        write_kitti(tmp_path / "k.txt", np.zeros((2, 3, 4)))
    assert list(tmp_path.iterdir()) == []


# --- scans: round trips ---------------------------------------------------------------------------


@pytest.mark.parametrize("suffix", [".ply", ".xyz", ".txt", ".npy", ".npz"])
def test_scan_formats_round_trip_exactly(tmp_path, suffix):
    P = _points()
    path = tmp_path / f"scan{suffix}"
    write_scan(path, P)
    got = load_scan(path)
    assert got.dtype == np.float64 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, P)


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".npy", ".npz", ".xyz"])
def test_point_count_reads_the_header_before_the_points(tmp_path, suffix):
    """``point_count`` (the memory check's count) is the header's (text: estimated from the first lines' length,
    here within 5 %); a header it cannot read counts 0, left to the reader to refuse."""
    P = _points(3000)
    write_scan(tmp_path / f"scan{suffix}", P)
    np.savez_compressed(tmp_path / "packed.npz", points=P)
    count = point_count(tmp_path / f"scan{suffix}")
    assert count == 3000 if suffix != ".xyz" else abs(count - 3000) < 150
    assert point_count(tmp_path / "packed.npz") == 3000
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex many\nend_header\n")
    assert point_count(tmp_path / "bad.ply") == 0


def test_pcd_round_trip_in_float32(tmp_path):
    P = _points()
    write_scan(tmp_path / "scan.pcd", P)
    np.testing.assert_allclose(load_scan(tmp_path / "scan.pcd"), P, rtol=1e-6, atol=1e-6)


def test_write_ply_is_binary_and_keeps_colours(tmp_path):
    P = _points(50)
    colors = np.random.default_rng(1).integers(0, 256, (50, 3)).astype(np.uint8)
    write_ply(tmp_path / "c.ply", P, colors)
    assert b"format binary_little_endian" in (tmp_path / "c.ply").read_bytes()[:200]
    cloud = o3d.io.read_point_cloud(str(tmp_path / "c.ply"))
    np.testing.assert_array_equal(np.asarray(cloud.points), P)
    np.testing.assert_allclose(np.asarray(cloud.colors) * 255, colors, atol=0.5)
    with pytest.raises(ValueError):
        write_ply(tmp_path / "bad.ply", P, colors[:10])


def test_text_scans_allow_comments_commas_and_extra_columns(tmp_path):
    path = tmp_path / "scan.xyz"
    path.write_text("# x y z nx ny nz\n1 2 3 0 0 1\n\n4,5,6,0,1,0  # inline\n 7\t8 9 0 0 0\n")
    np.testing.assert_array_equal(load_scan(path), [[1, 2, 3], [4, 5, 6], [7, 8, 9]])


def test_numpy_scans_extra_columns_int_dtype_and_npz_keys(tmp_path):
    np.save(tmp_path / "a.npy", np.arange(12).reshape(2, 6))
    np.testing.assert_array_equal(load_scan(tmp_path / "a.npy"), [[0, 1, 2], [6, 7, 8]])
    assert load_scan(tmp_path / "a.npy").dtype == np.float64
    P, Q = _points(5), _points(7, seed=1)
    np.savez(tmp_path / "first.npz", normals=P, other=Q)
    np.testing.assert_array_equal(load_scan(tmp_path / "first.npz"), P)
    np.savez(tmp_path / "keyed.npz", normals=P, points=Q)
    np.testing.assert_array_equal(load_scan(tmp_path / "keyed.npz"), Q)


def test_non_finite_rows_are_returned_then_dropped_and_counted(tmp_path):
    P = _points(10)
    P[2, 0], P[5, 1], P[7, 2] = np.nan, np.inf, -np.inf
    for suffix in (".ply", ".npy", ".xyz"):
        write_scan(tmp_path / f"n{suffix}", P)
        got = load_scan(tmp_path / f"n{suffix}")
        assert got.shape == (10, 3) and np.isnan(got[2, 0]) and np.isinf(got[5, 1])
        kept, dropped = finite_points(got)
        assert dropped == 3
        np.testing.assert_array_equal(kept, P[[0, 1, 3, 4, 6, 8, 9]])


# --- scans: bad files -----------------------------------------------------------------------------


def _truncated_binary_ply(tmp_path: Path) -> Path:
    write_ply(tmp_path / "full.ply", _points(1000))
    data = (tmp_path / "full.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    return tmp_path / "cut.ply"


def _truncated_ascii_ply(tmp_path: Path) -> Path:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_points(1000)))
    o3d.io.write_point_cloud(str(tmp_path / "full_ascii.ply"), cloud, write_ascii=True)
    text = (tmp_path / "full_ascii.ply").read_text()
    (tmp_path / "cut_ascii.ply").write_text(text[: len(text) * 2 // 3])
    return tmp_path / "cut_ascii.ply"


def _truncated_pcd(tmp_path: Path) -> Path:
    write_scan(tmp_path / "full.pcd", _points(1000))
    data = (tmp_path / "full.pcd").read_bytes()
    (tmp_path / "cut.pcd").write_bytes(data[: len(data) - 100])
    return tmp_path / "cut.pcd"


def _write(name: str, content: bytes | str):
    def make(tmp_path: Path) -> Path:
        path = tmp_path / name
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
        return path

    return make


def _save_npy(name: str, array: np.ndarray):
    def make(tmp_path: Path) -> Path:
        np.save(tmp_path / name, array)
        return tmp_path / name

    return make


def _npz_labelled_npy(tmp_path: Path) -> Path:
    with open(tmp_path / "zip.npy", "wb") as f:
        np.savez(f, points=_points(5))
    return tmp_path / "zip.npy"


BAD_SCANS = {
    "empty ply": (_write("e.ply", b""), "empty file"),
    "empty npy": (_write("e.npy", b""), "empty file"),
    "empty xyz": (_write("e.xyz", b""), "empty file"),
    "truncated binary ply": (_truncated_binary_ply, "truncated PLY"),
    "truncated ascii ply": (_truncated_ascii_ply, "truncated"),
    "ply header only": (_write("h.ply", "ply\nformat binary_little_endian 1.0\nelement vertex 1000\n"), "end_header"),
    "garbage text labelled ply": (_write("g.ply", "hello world\nthis is not a ply\n"), "not a PLY file"),
    "ply without vertices": (_write("f.ply", "ply\nformat ascii 1.0\nelement face 0\nend_header\n"), "no vertex"),
    "ply with unknown type": (
        _write("t.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n1\n"),
        "malformed PLY header",
    ),
    "ply with zero vertices": (
        _write(
            "z.ply",
            "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n",
        ),
        "no points",
    ),
    "garbage pcd": (_write("g.pcd", "garbage\n"), "not a PCD file"),
    "truncated pcd": (_truncated_pcd, "truncated PCD"),
    "binary labelled txt": (_write("b.txt", bytes(range(256))), "not a text file"),
    "text with two columns": (_write("two.xyz", "1 2 3\n3 4\n"), "expected x y z numbers"),
    "text with words": (_write("w.txt", "1 2 3\nx y z\n"), "line 2: expected x y z numbers, got 'x y z'"),
    "text with comments only": (_write("c.xyz", "# nothing\n\n"), "no points"),
    "npy with two columns": (_save_npy("two.npy", np.zeros((10, 2))), "shape (10, 2)"),
    "npy 1-d": (_save_npy("flat.npy", np.zeros(30)), "shape (30,)"),
    "npy 3-d": (_save_npy("cube.npy", np.zeros((2, 3, 3))), "shape (2, 3, 3)"),
    "npy strings": (_save_npy("s.npy", np.array([["a", "b", "c"]])), "non-numeric"),
    "npy of objects": (_save_npy("o.npy", np.array([[None, 1, 2]], dtype=object)), "allow_pickle"),
    "npy with no rows": (_save_npy("none.npy", np.zeros((0, 3))), "no points"),
    "npy garbage": (_write("g.npy", b"\x93NUMPY garbage"), "cannot read scan"),
    "npz labelled npy": (_npz_labelled_npy, ".npz archive"),
    "corrupt npz": (_write("c.npz", b"PK\x03\x04 not really a zip"), "cannot read scan"),
    "unknown suffix": (_write("scan.dxf", b"whatever"), "unknown scan format"),
}


@pytest.mark.parametrize("case", list(BAD_SCANS))
def test_bad_scan_is_one_line_input_error(tmp_path, case):
    make, needle = BAD_SCANS[case]
    _assert_one_line_input_error(make(tmp_path), needle)


def test_missing_file_and_folder_named_like_a_scan(tmp_path):
    _assert_one_line_input_error(tmp_path / "missing.ply", "no such file")
    (tmp_path / "dir.ply").mkdir()
    _assert_one_line_input_error(tmp_path / "dir.ply", "not a file")


# --- listing --------------------------------------------------------------------------------------


def test_list_scans_natural_order_and_non_scans_skipped(tmp_path):
    for name in ["s10.ply", "s2.npy", "s1.xyz", "S3.TXT", "b.npz", "c.pcd"]:
        (tmp_path / name).write_text("x")
    for name in [
        "gt_poses.txt",
        "poses.txt",
        "poses_kitti.txt",
        "0.pose.txt",
        "overlap.txt",
        "README.txt",
        "gt.log",
        "bun.conf",
        "edges.csv",
        ".s0.ply.tmp.ply",
        "notes.md",
    ]:
        (tmp_path / name).write_text("x")
    (tmp_path / "sub.ply").mkdir()
    assert [p.name for p in list_scans(tmp_path)] == ["b.npz", "c.pcd", "s1.xyz", "s2.npy", "S3.TXT", "s10.ply"]
    assert left_out(tmp_path) == [
        "0.pose.txt",
        "README.txt",
        "gt_poses.txt",
        "overlap.txt",
        "poses.txt",
        "poses_kitti.txt",
    ]


def test_scans_whose_names_hold_a_non_scan_word_inside_another_word_are_listed(tmp_path):
    """``*pose*.txt`` left ``exposed_wall_03.txt`` (and "composed", "purpose", ``license_plates.ply``) out of the
    run without a word."""
    for name in ["exposed_wall_03.txt", "composed.txt", "purpose.txt", "license_plates.ply", "trajan.txt"]:
        (tmp_path / name).write_text("x")
    assert sorted(p.name for p in list_scans(tmp_path)) == [
        "composed.txt",
        "exposed_wall_03.txt",
        "license_plates.ply",
        "purpose.txt",
        "trajan.txt",
    ]
    assert left_out(tmp_path) == []


def test_list_scans_missing_empty_or_scanless_folder(tmp_path):
    for folder, needle in [(tmp_path / "nowhere", "does not exist"), (tmp_path, "no scans in")]:
        with pytest.raises(InputError, match=needle) as info:
            list_scans(folder)
        assert "\n" not in str(info.value)
    (tmp_path / "gt_poses.txt").write_text("x")
    with pytest.raises(InputError, match="no scans in"):
        list_scans(tmp_path)
    with pytest.raises(InputError, match="is not a folder"):
        list_scans(tmp_path / "gt_poses.txt")


# --- atomic output --------------------------------------------------------------------------------


def test_atomic_write_leaves_nothing_on_exception(tmp_path):
    path = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_write(path) as f:
            f.write("half")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_keeps_the_old_file_on_exception_and_replaces_it_on_success(tmp_path):
    path = tmp_path / "out.bin"
    path.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_write(path, "wb") as f:
            f.write(b"new")
            raise RuntimeError("boom")
    assert path.read_bytes() == b"old"
    with atomic_write(path, "wb") as f:
        f.write(b"new")
    assert path.read_bytes() == b"new"
    assert [p.name for p in tmp_path.iterdir()] == ["out.bin"]
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_atomic_write_text_options(tmp_path):
    with atomic_write(tmp_path / "t.csv", newline="") as f:
        f.write("a\r\nb\n")
    assert (tmp_path / "t.csv").read_bytes() == b"a\r\nb\n"
    with pytest.raises(ValueError):
        with atomic_write(tmp_path / "t.csv", "a"):
            pass


def test_atomic_path_keeps_the_suffix_for_writers_that_dispatch_on_it(tmp_path):
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_points(20)))
    with atomic_path(tmp_path / "cloud.pcd") as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".pcd" and tmp.name.startswith(".")
        assert o3d.io.write_point_cloud(str(tmp), cloud)
        assert not (tmp_path / "cloud.pcd").exists()
    assert (tmp_path / "cloud.pcd").read_bytes().startswith(b"# .PCD")
    with pytest.raises(RuntimeError):
        with atomic_path(tmp_path / "other.ply") as tmp:
            o3d.io.write_point_cloud(str(tmp), cloud)
            raise RuntimeError("boom")
    assert [p.name for p in tmp_path.iterdir()] == ["cloud.pcd"]


# --- real data ------------------------------------------------------------------------------------


@pytest.mark.data
def test_kitchen_gt_log_matches_the_absolute_poses(data_dir):
    gt = data_dir / "kitchen" / "gt"
    log = read_gt_log(gt / "gt.log")
    names, poses = read_poses(gt / "gt_poses.txt")
    index = [int(Path(n).stem.split("_")[-1]) for n in names]
    compared = 0
    for a, i in enumerate(index):
        for b, j in enumerate(index):
            if (i, j) in log:
                T_ij = log[(i, j)].copy()
                T_ij[:3, :3] = project_to_so3(T_ij[:3, :3])
                np.testing.assert_allclose(T_ij, inv_T(poses[a]) @ poses[b], atol=1e-3)
                compared += 1
    assert compared >= 15
    assert len(log) == 506 and all(i < j for i, j in log)


@pytest.mark.data
def test_kitchen_gt_info_and_overlap(data_dir):
    gt = data_dir / "kitchen" / "gt"
    info = read_gt_info(gt / "gt.info")
    assert info.keys() == read_gt_log(gt / "gt.log").keys()
    for M in info.values():
        np.testing.assert_allclose(M, M.T, rtol=1e-6, atol=1e-6)
        assert np.linalg.eigvalsh(M).min() > -1e-6 * np.abs(M).max()
    assert info[(0, 1)][0, 0] == 5000.0
    overlap = read_gt_overlap(gt / "gt_overlap.log")
    assert len(overlap) == 60 * 59 // 2 and overlap[(0, 1)] == 0.8017
    assert all(0.0 <= v <= 1.0 for v in overlap.values())
    assert len(read_gt_log(gt / "gtLo.log")) == len(read_gt_info(gt / "gtLo.info")) > 0


@pytest.mark.data
def test_scan_order_matches_the_ground_truth_files(data_dir):
    for folder, gt in [("kitchen", "kitchen/gt/gt_poses.txt"), ("bunny", "bunny/gt_poses.txt")]:
        names, poses = read_poses(data_dir / gt)
        scans = [p.name for p in list_scans(data_dir / folder)]
        assert sorted(scans) == sorted(names)
        R = poses[:, :3, :3]
        np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-6)
    kitchen = [p.name for p in list_scans(data_dir / "kitchen")]
    assert kitchen == read_poses(data_dir / "kitchen/gt/gt_poses.txt")[0]  # natural order: 6 before 21


@pytest.mark.data
def test_bunny_ascii_ply_with_range_grid_loads(data_dir):
    for path in list_scans(data_dir / "bunny"):
        P = load_scan(path)
        assert 30_000 <= len(P) <= 41_000 and np.isfinite(P).all()
        assert np.abs(P).max() < 0.2  # metres: the bunny is ~15 cm
    first = (data_dir / "bunny" / "bun000.ply").read_text().splitlines()
    assert first[0] == "ply" and "element range_grid 204800" in first


@pytest.mark.data
def test_truncated_real_scans_are_rejected(data_dir, tmp_path):
    text = (data_dir / "bunny" / "bun000.ply").read_bytes()
    (tmp_path / "bun.ply").write_bytes(text[: len(text) // 10])
    _assert_one_line_input_error(tmp_path / "bun.ply", "truncated PLY")
    binary = (data_dir / "kitchen" / "cloud_bin_6.ply").read_bytes()
    (tmp_path / "k.ply").write_bytes(binary[:-12])
    _assert_one_line_input_error(tmp_path / "k.ply", "truncated PLY")
    assert len(load_scan(data_dir / "kitchen" / "cloud_bin_6.ply")) == 15953


@pytest.mark.data
def test_derived_poses_keep_nan_for_unreachable_fragments(data_dir):
    names, poses = read_poses(
        data_dir / "3dmatch-test-gt/derived_abs_poses/sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika.txt"
    )
    unreachable = np.isnan(poses).any(axis=(1, 2))
    assert unreachable.sum() == 1 and names[0] == "0"
    np.testing.assert_array_equal(poses[0], np.eye(4))


def test_g2o_edges_only_file_names_its_vertices_by_id(tmp_path):
    """``write_g2o`` without poses (graph_rejected.g2o): edge lines only, node k written as ids[k], the
    transform and information kept exactly."""
    from sghr_gtsam.io.g2o import read_g2o, write_g2o
    from sghr_gtsam.types import PoseGraph

    T = _rigid(2, seed=4)
    info = np.stack([np.diag(np.arange(1.0, 7.0)), 3.0 * np.eye(6)])
    graph = PoseGraph(n=3, i=np.array([0, 2]), j=np.array([1, 0]), T=T, weight=np.ones(2), information=info)
    write_g2o(tmp_path / "edges.g2o", [7, 8, 9], None, graph)
    lines = (tmp_path / "edges.g2o").read_text().splitlines()
    assert [line.split()[:3] for line in lines] == [["EDGE_SE3:QUAT", "7", "8"], ["EDGE_SE3:QUAT", "9", "7"]]
    # With the vertices prepended it reads back exactly.
    vertices = "".join(f"VERTEX_SE3:QUAT {v} 0 0 0 0 0 0 1\n" for v in (7, 8, 9))
    (tmp_path / "full.g2o").write_text(vertices + "\n".join(lines) + "\n")
    ids, _, back = read_g2o(tmp_path / "full.g2o")
    assert ids == [7, 8, 9]
    np.testing.assert_allclose(back.T, graph.T, atol=1e-12)
    np.testing.assert_array_equal(back.information, info)
    # Alone it reads as the edges between the ids they name, without poses (a run's graph_rejected.g2o).
    ids, poses, alone = read_g2o(tmp_path / "edges.g2o")
    assert ids == [7, 8, 9] and poses is None
    np.testing.assert_array_equal(alone.i, back.i)
    np.testing.assert_array_equal(alone.information, info)


_VERTEX = "VERTEX_SE3:QUAT {} 0 0 0 0 0 0 1\n"


def _edge_line(a, b, diagonal=(1, 1, 1, 1, 1, 1)) -> str:
    info = [diagonal[r] if r == c else 0 for r in range(6) for c in range(r, 6)]
    return f"EDGE_SE3:QUAT {a} {b} 1 0 0 0 0 0 1 " + " ".join(map(repr, info)) + "\n"


def test_g2o_information_in_fine_units_is_positive_definite(tmp_path):
    """A run's own graph.g2o of a scene in micrometres (translation information 1e-8 beside rotation's 1e8) was
    refused by ``sync``: "information matrix is not positive definite", judged on eigenvalues relative to the
    largest entry. Definiteness does not depend on units; a semi-definite matrix is still refused."""
    from sghr_gtsam.io.g2o import read_g2o

    path = tmp_path / "um.g2o"
    path.write_text(_VERTEX.format(0) + _VERTEX.format(1) + _edge_line(0, 1, (1e-8, 1e-8, 1e-8, 1e8, 1e8, 1e8)))
    _, _, graph = read_g2o(path, positive_definite=True)
    np.testing.assert_array_equal(np.diag(graph.information[0]), [1e8] * 3 + [1e-8] * 3)
    path.write_text(_VERTEX.format(0) + _VERTEX.format(1) + _edge_line(0, 1, (1e-8, 1e-8, 0, 1e8, 1e8, 1e8)))
    with pytest.raises(InputError, match="line 3: information matrix is not positive definite"):
        read_g2o(path, positive_definite=True)


@pytest.mark.parametrize("ids", [("-1", "0"), ("0", str(2**64)), ("+1", "0"), ("0_0", "1"), ("\uff11", "0")])
def test_g2o_ids_gtsam_cannot_hold_are_refused(tmp_path, ids):
    """Ids gtsam reads as other keys (-1 as 2**64 - 1, 2**64 + 1 as 1) gave files it loads wrong, and int() took
    "+1", "0_0" and fullwidth digits."""
    from sghr_gtsam.io.g2o import read_g2o

    path = tmp_path / "ids.g2o"
    path.write_text(_VERTEX.format(ids[0]) + _VERTEX.format(ids[1]), encoding="utf-8")
    with pytest.raises(InputError, match=r"line [12]: vertex ids must be whole numbers in \[0, 2\*\*64\)"):
        read_g2o(path)


def test_g2o_with_a_byte_order_mark_a_latin1_comment_or_a_form_feed_reads(tmp_path):
    """gtsam reads them; we refused the first two ("utf-8 codec can't decode byte 0xe9") and split a line at the
    third."""
    from sghr_gtsam.io.g2o import read_g2o

    body = _VERTEX.format(0) + _VERTEX.format(1) + _edge_line(0, 1)
    for name, raw in [
        ("bom", b"\xef\xbb\xbf" + body.encode()),
        ("latin1", b"# caf\xe9\n" + body.encode()),
        ("formfeed", body.replace(" 0 0 0 0 0 1 1", " 0 0 0 0 0\x0c1 1", 1).encode()),
    ]:
        (tmp_path / f"{name}.g2o").write_bytes(raw)
        ids, _, graph = read_g2o(tmp_path / f"{name}.g2o")
        assert ids == [0, 1] and graph.num_edges == 1, name


def test_g2o_from_a_device_is_refused_not_read_forever(tmp_path):
    from sghr_gtsam.io.g2o import read_g2o

    with pytest.raises(InputError, match="cannot read g2o file /dev/zero: not a regular file"):
        read_g2o("/dev/zero")
    with pytest.raises(InputError, match="not a regular file"):
        read_g2o(tmp_path)


# --- a results folder read back; the API prints nothing unless given log= -------------------------------------------


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """A generated object of four scans run through the API, everything it printed caught."""
    import contextlib
    import io

    from sghr_gtsam.config import Config
    from sghr_gtsam.pipeline import run
    from sghr_gtsam.synthetic import make_scene, write_scene

    scene = make_scene(kind="object", n_scans=4, seed=3)
    folder = tmp_path_factory.mktemp("small_run")
    write_scene(scene, folder / "scene")
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed), contextlib.redirect_stderr(printed):
        result = run(folder / "scene", folder / "out", Config(voxel=scene.voxel, workers=1, record=False))
    return result, folder, printed.getvalue()


def test_run_and_register_print_nothing_unless_given_log(small_run):
    import contextlib
    import io

    from sghr_gtsam.config import Config
    from sghr_gtsam.pipeline import load_scene, register

    result, folder, printed = small_run
    assert printed == "" and result.names
    scans, _ = load_scene(folder / "scene", Config(), log=lambda message: None)
    quiet, said = io.StringIO(), []
    with contextlib.redirect_stdout(quiet), contextlib.redirect_stderr(quiet):
        register(scans, Config(voxel=result.voxel, workers=1))
        register(scans, Config(voxel=result.voxel, workers=1), log=said.append)
    assert quiet.getvalue() == "" and any(message.startswith("pairwise:") for message in said)


def test_load_results_reads_a_run_s_folder_back(small_run):
    from sghr_gtsam.gtsam_api import graph_information
    from sghr_gtsam.io.results import load_results
    from sghr_gtsam.registration.edges import edge_status

    result, folder, _ = small_run
    loaded = load_results(folder / "out")
    assert loaded.names == result.names and loaded.unregistered == result.unregistered
    assert loaded.flags == result.flags and loaded.skipped == result.skipped and loaded.voxel == result.voxel
    placed = result.registered
    assert loaded.registered == placed
    np.testing.assert_array_equal(loaded.poses[placed], result.poses[placed])  # poses.txt round-trips exactly
    g, h = result.graph, loaded.graph
    np.testing.assert_array_equal(h.i, g.i)
    np.testing.assert_array_equal(h.j, g.j)
    np.testing.assert_allclose(h.T, g.T, rtol=0, atol=1e-12)
    status = edge_status(result)
    assert edge_status(loaded) == status and "kept" in status
    kept = np.array([s == "kept" for s in status])
    np.testing.assert_allclose(h.information[kept], graph_information(g, kept)[kept], rtol=1e-12)
    np.testing.assert_allclose(h.weight, g.weight, rtol=1e-5)
    np.testing.assert_allclose(loaded.sync.weights, result.sync.weights, rtol=1e-5)
    assert [p.inliers for p in loaded.pairs] == [p.inliers for p in result.pairs]
    np.testing.assert_allclose(loaded.covariances[placed], result.covariances[placed], rtol=1e-12, atol=0)
    assert loaded.timings == {k: round(v, 3) for k, v in result.timings.items()}
    from sghr_gtsam.gtsam_api import to_gtsam

    factors, values = to_gtsam(loaded)  # the same factor graph as the run's own
    reference, _ = to_gtsam(result)
    assert factors.size() == reference.size() > 0
    assert factors.error(values) == pytest.approx(reference.error(to_gtsam(result)[1]), rel=1e-9)
    from sghr_gtsam.plots import summary_figure

    top = summary_figure(loaded).axes[0]  # no grids in a folder: the graph over the scans' origins
    (drawn,) = [c for c in top.collections if c.get_label() == "kept"]
    assert len(drawn.get_segments()) == status.count("kept")


def test_load_results_refuses_a_folder_that_is_not_a_run_s(small_run, tmp_path):
    import json
    import shutil

    from sghr_gtsam.io.results import load_results

    _, folder, _ = small_run
    with pytest.raises(InputError, match="edges.csv"):
        load_results(tmp_path)
    report = json.loads((folder / "out" / "report.json").read_text())
    damaged = [
        ("edges.csv", "i,j\n0,1\n"),
        ("report.json", '{"scans": ["a"'),
        ("poses.txt", "a.ply\n1 2\n"),
        ("graph.g2o", "EDGE_SE3:QUAT 0 1\n"),
        ("report.json", json.dumps({**report, "unregistered": ["nobody.ply"]})),
        ("report.json", json.dumps({**report, "pose_covariances": {report["scans"][0]: {"covariance": [1]}}})),
    ]
    for k, (name, text) in enumerate(damaged):
        copy = tmp_path / f"copy{k}"
        shutil.copytree(folder / "out", copy)
        (copy / name).write_text(text)
        with pytest.raises(InputError) as error:
            load_results(copy)
        assert "\n" not in str(error.value), name
