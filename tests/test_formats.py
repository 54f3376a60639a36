"""Scan formats read through other libraries (LAS/LAZ with laspy and lazrs, E57 with pye57) and the TUM pose
writer: files written here with those libraries read back to the points they hold; an unreadable file is a
one-line reason in ``skipped``, never silently ignored; TUM and KITTI files follow their formats' rules and
evo (the odometry evaluation tool) reads them to the same trajectory."""

import io
import struct
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.config import Config
from sghr_gtsam.io.poses import read_tum, write_kitti, write_tum
from sghr_gtsam.io.scans import check_memory, list_scans, load_scan, point_count
from sghr_gtsam.scene import load_scene
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
            e57.write_scan_raw(
                {"cartesianX": P[:, 0], "cartesianY": P[:, 1], "cartesianZ": P[:, 2]},
                rotation=np.array([w, x, y, z]),
                translation=np.asarray(t, dtype=float),
            )


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


@pytest.mark.parametrize(
    "name, content, reason",
    [
        ("broken.laz", "truncated", "not a readable LAZ file"),
        ("broken.las", b"LASF" + bytes(60), "not a readable LAS file"),
        ("broken.e57", b"ASTM-E57" + bytes(2000), "not a readable E57 file"),
    ],
)
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


def _las_bytes(P, version="1.2", compress=False) -> bytearray:
    """A LAS (point format 3, scales 0.001) or LAZ file of ``P`` as bytes, to corrupt."""
    header = laspy.LasHeader(point_format=3, version=version)
    header.scales, header.offsets = [1e-3] * 3, P.min(0)
    las = laspy.LasData(header)
    las.x, las.y, las.z = P.T
    buffer = io.BytesIO()
    las.write(buffer, do_compress=compress)
    return bytearray(buffer.getvalue())


def _skipped_reason(tmp_path, name, content) -> str:
    """Why ``load_scene`` skips the file ``name`` holding ``content`` beside two good scans, which it reads."""
    scene = tmp_path / "scene"
    scene.mkdir()
    for k in range(2):
        np.save(scene / f"good_{k}.npy", _points(300, k))
    (scene / name).write_bytes(content)
    scans, skipped = load_scene(scene, Config(), log=lambda message: None)
    assert [s.name for s in scans] == ["good_0.npy", "good_1.npy"] and list(skipped) == [name]
    assert "\n" not in skipped[name]
    return skipped[name]


@pytest.fixture
def laspy_bounded(monkeypatch):
    """laspy refuses to loop over more than 1,000 (E)VLRs, so that a reader that hands it a corrupt header fails
    here at once instead of looping for hours through gigabytes of memory."""
    from laspy.vlrs.vlrlist import VLRList

    read_from = VLRList.read_from.__func__

    def bounded(cls, stream, num_to_read, extended=False):
        if num_to_read > 1000:
            raise RuntimeError(f"laspy asked to read {num_to_read:,} VLRs")
        return read_from(cls, stream, num_to_read, extended)

    monkeypatch.setattr(VLRList, "read_from", classmethod(bounded))


def _put(at, fmt, value):
    """A corruption: ``value`` written as ``fmt`` at byte ``at``."""

    def corrupt(data):
        struct.pack_into(fmt, data, at, value)
        return data

    return corrupt


def _laz_chunks(data):
    table = struct.unpack_from("<q", data, struct.unpack_from("<I", data, 96)[0])[0]
    struct.pack_into("<I", data, table + 4, 0xFFFFFFF0)  # the chunk table: version, number of chunks
    return data


def _laz_chunk_table(data, entries):
    """``data`` with its LAZ chunk table written again by lazrs, holding ``entries`` ((points, bytes) per chunk)."""
    import lazrs

    offset = struct.unpack_from("<I", data, 96)[0]
    out = io.BytesIO(bytes(data[: struct.unpack_from("<q", data, offset)[0]]))
    out.seek(0, io.SEEK_END)
    lazrs.write_chunk_table(out, entries, lazrs.LazVlr(bytes(data[offset - 52 : offset])))  # the laszip VLR is last
    return bytearray(out.getvalue())


def _laz_chunk_bytes(data):
    return _laz_chunk_table(data, [(50000, 2**31)])  # coded as int32: read back as 2**64 - 2**31 bytes


def _laz_streamed(data):
    """``data`` as a streaming writer leaves a LAZ: -1 where the chunk table's offset goes, the offset appended."""
    offset = struct.unpack_from("<I", data, 96)[0]
    table = struct.unpack_from("<q", data, offset)[0]
    struct.pack_into("<q", data, offset, -1)
    return data + struct.pack("<q", table)


def _laz_without_table(data):
    return _put(struct.unpack_from("<I", data, 96)[0], "<q", -1)(data)  # nothing appended: no table to be found


# name -> (LAS version, suffix, corruption of the file's bytes, words of the reason)
LAS_CORRUPTIONS = {
    "VLR count": ("1.2", ".las", _put(100, "<I", 0xFFFFFFF0), "corrupt header: 4,294,967,280 VLRs declared in 0"),
    "VLR count of a LAZ": ("1.2", ".laz", _put(100, "<I", 0xFFFFFFF0), "corrupt header: 4,294,967,280 VLRs"),
    "EVLR count": ("1.4", ".las", _put(243, "<I", 0xFFFFFFF0), "corrupt header: 4,294,967,280 EVLRs declared"),
    "header size below LAS's": ("1.2", ".las", _put(94, "<H", 100), "corrupt header: a header size of 100 bytes"),
    "point data past the end": ("1.2", ".las", _put(96, "<I", 2**32 - 1), "corrupt header: point data at byte"),
    "LASF and random bytes": (
        "1.2",
        ".las",
        lambda data: b"LASF" + np.random.default_rng(3).bytes(400),
        "corrupt header",
    ),
    "chunk count of a LAZ": ("1.2", ".laz", _laz_chunks, "corrupt chunk table: 4,294,967,280 chunks"),
    "chunk sizes of a LAZ": (
        "1.2",
        ".laz",
        _laz_chunk_bytes,
        "corrupt chunk table: chunks of 18,446,744,071,562,067,968 bytes declared in",
    ),
    "point count of a LAZ": (
        "1.2",
        ".laz",
        _put(107, "<I", 10**9),
        "corrupt header: 1,000,000,000 points declared where the chunk table holds at most 50,000",
    ),
    "point count of a streamed LAZ": (
        "1.2",
        ".laz",
        lambda data: _put(107, "<I", 10**9)(_laz_streamed(data)),
        "corrupt header: 1,000,000,000 points declared where the chunk table holds at most 50,000",
    ),
    "LAZ without a chunk table": (
        "1.2",
        ".laz",
        lambda data: _put(107, "<I", 10**9)(_laz_without_table(data)),
        "corrupt chunk table: its offset ",
    ),
    "scale factor": (
        "1.2",
        ".las",
        _put(131, "<d", 1e300),
        "corrupt header: x scale 1e+300 and offset -49.981 put coordinates past ±3.9e+153",
    ),
    "scale not a number": ("1.4", ".las", _put(147, "<d", float("nan")), "corrupt header: z scale nan and offset"),
    "offset infinite": (
        "1.2",
        ".las",
        _put(155, "<d", float("inf")),
        "corrupt header: x scale 0.001 and offset inf are not finite",
    ),
}


@pytest.mark.parametrize("case", list(LAS_CORRUPTIONS))
def test_corrupt_las_header_is_skipped_before_laspy_reads_it(tmp_path, laspy_bounded, case):
    """Counts and sizes a LAS/LAZ header declares beyond what the file holds: skipped with the first that does
    not fit, instead of laspy looping over 4 billion VLRs (a hung run), lazrs aborting the process or panicking (a
    chunk past the data), the memory check ending the run (points the chunks cannot hold) or numpy's overflow
    warning on the terminal (coordinates past float64's range)."""
    version, suffix, corrupt, reason = LAS_CORRUPTIONS[case]
    content = corrupt(_las_bytes(_points(3000), version, compress=suffix == ".laz"))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        found = _skipped_reason(tmp_path, f"bad{suffix}", content)
    assert f"not a readable {suffix[1:].upper()} file ({reason}" in found, found
    assert point_count(tmp_path / "scene" / f"bad{suffix}") == 0  # left to the reader to refuse


def test_a_streamed_laz_reads(tmp_path):
    """A LAZ whose chunk table's offset is appended at the end (-1 in its place: a streaming writer's) reads."""
    P = _points(3000)
    (tmp_path / "streamed.laz").write_bytes(_laz_streamed(_las_bytes(P, "1.2", compress=True)))
    np.testing.assert_allclose(load_scan(tmp_path / "streamed.laz"), P, atol=0.5e-3)
    assert point_count(tmp_path / "streamed.laz") == 3000


@pytest.mark.parametrize("version, at, fmt", [("1.2", 107, "<I"), ("1.4", 247, "<Q")])
def test_las_overstating_its_point_count_is_skipped_not_a_memory_error(tmp_path, version, at, fmt):
    """A 100 KB LAS that declares 1e9 points is a corrupt file, skipped; the memory check does not take it for a
    scan of 112 GB that ends the run."""
    content = _put(at, fmt, 10**9)(_las_bytes(_points(3000), version))
    reason = _skipped_reason(tmp_path, "s3.las", content)
    assert (
        f"1,000,000,000 points of 34 bytes declared in {len(content) - (375 if version == '1.4' else 227):,} "
        "bytes of point data" in reason
    ), reason
    check_memory(tmp_path / "scene" / "s3.las")


def _variable_chunks(data, P):
    """The LAZ ``data`` of the points ``P`` compressed again in chunks of variable size (1,000 points, then the
    rest), which its chunk table counts one by one."""
    import lazrs

    offset = struct.unpack_from("<I", data, 96)[0]
    struct.pack_into("<I", data, offset - 52 + 12, 0xFFFFFFFF)  # the laszip VLR's chunk size: variable
    las = _las_bytes(P)
    records = bytes(las[struct.unpack_from("<I", las, 96)[0] :])
    out = io.BytesIO(bytes(data[:offset]))
    out.seek(0, io.SEEK_END)
    compressor = lazrs.LasZipCompressor(out, lazrs.LazVlr(bytes(data[offset - 52 : offset])))
    compressor.compress_chunks([records[: 1000 * 34], records[1000 * 34 :]])
    compressor.done()
    return bytearray(out.getvalue())


@pytest.mark.parametrize("variable", [False, True], ids=["fixed chunks", "variable chunks"])
@pytest.mark.parametrize("version, at, fmt", [("1.2", 107, "<I"), ("1.4", 247, "<Q")])
def test_laz_overstating_its_point_count_is_skipped_not_a_memory_error(tmp_path, version, at, fmt, variable):
    """The same for a LAZ, whose compressed size bounds no count: its chunk table does (each chunk's points, or the
    chunk size for chunks of a fixed size). It ended the run as "reading it needs about 111.8 GB"."""
    P = _points(3000)
    data = _las_bytes(P, version, compress=True)
    data = _variable_chunks(data, P) if variable else data
    (tmp_path / "whole.laz").write_bytes(data)
    np.testing.assert_allclose(load_scan(tmp_path / "whole.laz"), P, atol=0.5e-3)
    reason = _skipped_reason(tmp_path, "s3.laz", _put(at, fmt, 10**9)(data))
    assert (
        f"corrupt header: 1,000,000,000 points declared where the chunk table holds at most "
        f"{3000 if variable else 50000:,}" in reason
    ), reason
    check_memory(tmp_path / "scene" / "s3.laz")


LAS_FIELDS = {
    "header size": (94, "<H"), "offset to point data": (96, "<I"), "number of VLRs": (100, "<I"),
    "point format": (104, "<B"), "record length": (105, "<H"), "legacy point count": (107, "<I"),
    "start of first EVLR": (235, "<Q"), "number of EVLRs": (243, "<I"), "point count": (247, "<Q"),
}  # fmt: skip


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(version=st.sampled_from(["1.2", "1.4"]), data=st.data())
def test_any_las_header_field_is_read_or_refused_in_one_line(laspy_bounded, version, data):
    """Any value in any field the header check reads: the file reads, or is refused in one line; and the memory
    check's count never exceeds what the file can hold (records of at least 20 bytes)."""
    field = data.draw(st.sampled_from([f for f, (at, _) in LAS_FIELDS.items() if version == "1.4" or at < 227]))
    at, fmt = LAS_FIELDS[field]
    value = data.draw(st.integers(0, 256 ** struct.calcsize(fmt) - 1), label=field)
    content = _put(at, fmt, value)(_las_bytes(_points(50), version))
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scan.las"
        path.write_bytes(content)
        assert point_count(path) * 20 <= len(content)
        try:
            assert load_scan(path).shape[1] == 3
        except InputError as error:
            assert "\n" not in str(error)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(*[st.floats(-1e4, 1e4)] * 3), min_size=1, max_size=20),
    st.booleans(),
    st.sampled_from([" ", "\t", "  "]),
)
def test_decimal_commas_are_refused_naming_the_line(rows, comment, gap):
    """x y z written with decimal commas (a European-locale export): refused naming the line, where reading the
    commas as separators gave x_int, x_frac, y_int as the coordinates."""
    text = "# exported\n" * comment + "".join(
        gap.join(f"{v:.6f}".replace(".", ",") for v in row) + "\n" for row in rows
    )
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scan.xyz"
        path.write_text(text)
        with pytest.raises(
            InputError, match=f"scan.xyz: line {1 + comment}: decimal commas .* are not read: convert them to points$"
        ):
            load_scan(path)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(*[st.floats(allow_nan=False, allow_infinity=False)] * 3), min_size=1, max_size=20),
    st.sampled_from([",", ", "]),
)
def test_comma_separated_text_reads_exactly(rows, separator):
    P = np.array(rows, dtype=np.float64)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scan.txt"
        path.write_text("".join(separator.join(map(repr, row)) + "\n" for row in P.tolist()))
        np.testing.assert_array_equal(load_scan(path), P)


@pytest.mark.parametrize("first", ["-3.011641 -1.440960 1.749830", "1 -1,440960 1,749830", "0 0 0"])
def test_decimal_commas_after_the_first_line_are_refused_naming_the_line(tmp_path, first):
    """Only the first data line was tested: a file whose first line has dots (or an integer) and the rest decimal
    commas was read as x_int, x_frac, y_int from line 2 on, without a word."""
    path = tmp_path / "scan.xyz"
    path.write_text(first + "\n" + "-2,965948 -1,467908 1,752290\n" * 5)
    line = 1 if "," in first else 2
    with pytest.raises(InputError, match=f"scan.xyz: line {line}: decimal commas"):
        load_scan(path)


@pytest.mark.parametrize("header", ["x y z intensity", "//X Y Z R G B", "X,Y,Z", "6"])
@pytest.mark.parametrize("separator", [" ", ",", ";"])
def test_text_with_a_header_line_or_semicolons_reads(tmp_path, header, separator):
    """Column names (CloudCompare's ``//X Y Z``), a point count first (``.pts``) and semicolon-separated columns were
    refused whole with numpy's "could not convert string 'x' to float64 at row 0"."""
    P = _points(6)
    path = tmp_path / "scan.txt"
    path.write_text(header + "\n" + "".join(separator.join(map(repr, row)) + " 0.5\n" for row in P.tolist()))
    np.testing.assert_array_equal(load_scan(path), P)


def test_a_data_line_with_a_typo_is_no_header(tmp_path):
    path = tmp_path / "scan.txt"
    path.write_text("1.0 2.0 3.O\n" + "1.0 2.0 3.0\n" * 5)
    with pytest.raises(InputError, match="line 1: expected x y z numbers, got '1.0 2.0 3.O'"):
        load_scan(path)


@pytest.mark.parametrize(
    "text, line",
    [
        ("x y z\n1 2 3\n# c\n\n4 5 6 7\n1 2 a\n", "line 6: "),
        ("1 2 3\n4 5\n", "line 2: "),
        ("1,2,3\n4,5,6\n7;x;9\n", "line 3: "),
    ],
)
def test_a_bad_line_is_named_by_its_line_in_the_file(tmp_path, text, line):
    """numpy named the row from 0 among data rows only ("row 2" for line 6 above)."""
    (tmp_path / "scan.txt").write_text(text)
    with pytest.raises(InputError, match=line + "expected x y z numbers"):
        load_scan(tmp_path / "scan.txt")


def test_text_with_a_byte_order_mark_reads(tmp_path):
    """Windows tools write a UTF-8 byte-order mark; it was read as part of the first number and the file refused."""
    P = _points(50)
    rows = "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in P.tolist())
    (tmp_path / "scan.xyz").write_bytes(b"\xef\xbb\xbf" + rows.encode())
    np.testing.assert_array_equal(load_scan(tmp_path / "scan.xyz"), P)


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_with_a_blank_header_line_reads(tmp_path, fmt):
    """open3d reads a PLY whose header has a blank line; this reader refused it as a malformed header line."""
    P = _points(50).astype(np.float32).astype(np.float64)
    header = f"ply\nformat {fmt} 1.0\n\nelement vertex 50\nproperty float x\nproperty float y\nproperty float z\n"
    data = (
        "".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in P.tolist()).encode()
        if fmt == "ascii"
        else P.astype("<f4").tobytes()
    )
    (tmp_path / "scan.ply").write_bytes(header.encode() + b"end_header\n" + data)
    np.testing.assert_array_equal(load_scan(tmp_path / "scan.ply"), P)


@pytest.mark.parametrize(
    "name, content, reason",
    [
        ("json.npy", lambda: b'{"points": [[1, 2, 3]]}', "not a NumPy array file (no .npy header; pickled data is not"),
        ("las.npy", lambda: bytes(_las_bytes(_points(300))), "not a NumPy array file"),
        ("json.npz", lambda: b'{"points": [[1, 2, 3]]}', "not a NumPy .npz archive (not a zip file; pickled data is"),
        ("array.npz", lambda: _npy_bytes(_points(300)), "file is an .npy array, not an .npz archive"),
    ],
)
def test_file_named_npy_or_npz_that_is_not_one_is_named_so(tmp_path, name, content, reason):
    """Not numpy's advice to load the file unsafely with allow_pickle=True (which it gives for any file that is
    not an .npy or .npz)."""
    found = _skipped_reason(tmp_path, name, content())
    assert reason in found and "allow_pickle" not in found, found


def _npy_bytes(array) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


@pytest.mark.parametrize("suffix", [".npy", ".npz"])
def test_transposed_array_is_refused_naming_its_shape(tmp_path, suffix):
    """A (3, N) array is no 3 points (reported as "only 3 finite points" before): its shape, and why."""
    buffer = io.BytesIO()
    np.save(buffer, _points(500).T) if suffix == ".npy" else np.savez(buffer, points=_points(500).T)
    reason = _skipped_reason(tmp_path, f"scan{suffix}", buffer.getvalue())
    assert "array has shape (3, 500): it looks transposed (expected (N, 3))" in reason, reason


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
    file_interface = pytest.importorskip(
        "evo.tools.file_interface", reason="evo is a test extra (pip install -e '.[test]')"
    )
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


def test_coordinates_past_float64_geometry_are_dropped_as_not_finite(tmp_path):
    """An ``.npy`` at 1e200: the scan's statistics squared past float64 (numpy's overflow warning on the terminal),
    then the scan was skipped as "its extent inf is infx the median scan's"; one such point among good ones made
    the extent inf the same way."""
    stray = _points(300, 2)
    stray[7] = [1e200, 0.0, 0.0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        reason = _skipped_reason(tmp_path, "far.npy", _npy_bytes(np.full((300, 3), 1e200)))
        assert reason == "only 0 finite points (< 100)", reason
        np.save(tmp_path / "scene" / "stray.npy", stray)
        logged = []
        scans, skipped = load_scene(tmp_path / "scene", Config(), log=logged.append)
    assert (
        "stray.npy" in [s.name for s in scans] and next(s for s in scans if s.name == "stray.npy").stats.points == 299
    )
    assert "stray.npy: dropped 1 points not finite or past ±3.9e+153" in logged, logged


def test_files_left_out_by_their_names_are_named(tmp_path):
    """``exposed_wall_03.txt`` was left out silently (``*pose*.txt``); a file left out by a whole word is now named."""
    scene = tmp_path / "scene"
    scene.mkdir()
    for k in range(2):
        np.save(scene / f"good_{k}.npy", _points(300, k))
    np.savetxt(scene / "exposed_wall_03.txt", _points(300, 2))
    (scene / "gt_poses.txt").write_text("# poses\n")
    logged = []
    scans, skipped = load_scene(scene, Config(), log=logged.append)
    assert [s.name for s in scans] == ["exposed_wall_03.txt", "good_0.npy", "good_1.npy"] and not skipped
    assert logged == ["not a scan, by its name: gt_poses.txt (poses, a trajectory, overlaps or a readme)"], logged
