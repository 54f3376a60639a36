"""Reading and writing scans (point clouds as (N, 3) float64 arrays).

Every failure to read a scan becomes a one-line ``InputError("cannot read scan X: reason")``.
PLY and PCD are read here with every count and size their header declares checked against the data (open3d,
which reports none of it, only for the layouts whose size is known only after parsing); a LAS/LAZ header's counts
are checked against the file's size before laspy, which trusts them, reads it.
"""

from __future__ import annotations

import os
import re
import stat
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from sghr_gtsam.errors import InputError, one_line
from sghr_gtsam.io.atomic import atomic_path, atomic_write

SCAN_SUFFIXES = (".ply", ".pcd", ".xyz", ".txt", ".npy", ".npz", ".las", ".laz", ".e57")

NON_SCAN_WORDS = frozenset({"pose", "poses", "traj", "trajectory", "overlap", "overlaps", "readme", "license"})
"""``.txt`` is also a scan format, so a ``.txt`` file whose name holds one of these words (its letter runs,
lower-cased) is no scan: ground truth and outputs such as ``gt_poses.txt``, ``poses_kitti.txt``, ``0.pose.txt``,
``overlap.txt``, and READMEs. Whole words: ``exposed_wall.txt`` is a scan (substrings left it out silently).
``.log`` / ``.conf`` / ``.info`` files are never scans (not in ``SCAN_SUFFIXES``)."""


def _natural_key(path: Path) -> tuple[list[str | int], str]:
    """``scan_2`` before ``scan_10``: digit runs compare as numbers, case is ignored, and the exact
    name breaks ties (so the order never depends on the file system's listing order)."""
    parts = re.split(r"(\d+)", path.name)  # text, digits, text, ...: types match position by position
    return [int(part) if k % 2 else part.lower() for k, part in enumerate(parts)], path.name


def _named_not_scan(path: Path) -> bool:
    return path.suffix.lower() == ".txt" and not NON_SCAN_WORDS.isdisjoint(re.findall("[a-z]+", path.stem.lower()))


def _scan_like(path: Path) -> bool:
    """Anything but a folder (a file; a pipe, device, socket or a symbolic link that does not lead to a file:
    listed, so that it is skipped with a reason instead of silently) with a scan suffix, not hidden (atomic_write's
    temporaries are)."""
    return path.suffix.lower() in SCAN_SUFFIXES and not path.name.startswith(".") and not path.is_dir()


_KINDS = (
    (stat.S_ISFIFO, "a named pipe (FIFO)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISDIR, "a folder, not a file"),
)


def not_regular(path: str | Path) -> str | None:
    """Why ``path`` is not a regular file to read (its symbolic links followed), or None: a pipe, a device or a
    socket would block a reader for ever or never end (``/dev/zero``), so nothing opens them."""
    path = Path(path)
    try:
        mode = os.stat(path).st_mode
    except OSError:
        return (
            "a symbolic link that leads nowhere (broken or a loop)"
            if path.is_symlink()
            else "no such file"
            if not os.path.lexists(path)
            else "cannot be read"
        )
    if stat.S_ISREG(mode):
        return None
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    return f"a symbolic link to {kind} ({os.path.realpath(path)})" if path.is_symlink() else kind


def left_out(folder: str | Path) -> list[str]:
    """The names of ``folder``'s files with a scan suffix that ``list_scans`` leaves out by their names
    (``NON_SCAN_WORDS``), for the run to say so."""
    return sorted(p.name for p in Path(folder).iterdir() if _scan_like(p) and _named_not_scan(p))


def list_scans(folder: str | Path) -> list[Path]:
    """Scan files in ``folder`` (not recursive), in natural file-name order (``cloud_bin_2`` before
    ``cloud_bin_10``); the order defines the scan indices; ``.txt`` files named as poses, trajectories, overlaps or
    READMEs are left out (``left_out``). Raises ``InputError`` when the folder does not exist or holds no scans."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"scan folder {folder} does not exist" if not folder.exists() else f"{folder} is not a folder")
    scans = sorted((p for p in folder.iterdir() if _scan_like(p) and not _named_not_scan(p)), key=_natural_key)
    if not scans:
        raise InputError(f"no scans in {folder} (looked for {', '.join(SCAN_SUFFIXES)})")
    return scans


# --- PLY and PCD ---------------------------------------------------------------------------------
# Read here rather than by open3d, which reports nothing: it fills the rows after a non-number of an ASCII file
# with uninitialised memory, pads a truncated file with zeros and reads a file whose header undercounts its data
# short. Every count and size a header declares is checked against the data. open3d remains the fallback for the
# layouts whose size cannot be known before parsing (binary PLY with list properties before or in the vertex
# element, compressed PCD), with its point count compared to the header's.

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2", "ushort": "u2",
    "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
    "double": "f8", "float64": "f8",
}  # fmt: skip
_HEADER_LIMIT = 1 << 20  # a header longer than this is not a point cloud header


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str]]  # (name, numpy type code)
    has_list: bool = False

    def dtype(self, order: str) -> np.dtype:
        return np.dtype([(f"p{k}", order + code) for k, (_, code) in enumerate(self.properties)])


def _read_header(path: Path, end_marker: bytes) -> tuple[list[str], int] | None:
    """Header lines up to and including the line starting with ``end_marker``, and the byte offset
    of the data after it; None when the marker is missing."""
    with open(path, "rb") as f:
        head = f.read(_HEADER_LIMIT)
    lines: list[str] = []
    offset = 0
    for raw in head.splitlines(keepends=True):
        offset += len(raw)
        lines.append(raw.decode("ascii", errors="replace").strip())
        if raw.startswith(end_marker):
            return lines, offset
    return None


def _data_rows(path: Path, offset: int) -> list[bytes]:
    with open(path, "rb") as f:
        f.seek(offset)
        return [row for row in f.read().splitlines() if row.strip()]


def _parse_rows(rows: list[bytes], columns: int, first_line: int) -> np.ndarray:
    """ASCII records of ``columns`` numbers each as a float64 (len(rows), columns) array; ``InputError`` naming the
    first row (counted from ``first_line``) that has another number of values or a value that is not a number."""
    for k, row in enumerate(rows):
        if len(row.split()) != columns:
            raise InputError(f"line {first_line + k}: {len(row.split())} values where the header declares {columns}")
    try:
        return np.array(b" ".join(rows).split(), dtype=np.float64).reshape(len(rows), columns)
    except ValueError:
        for k, row in enumerate(rows):
            try:
                np.array(row.split(), dtype=np.float64)
            except ValueError:
                raise InputError(
                    f"line {first_line + k}: not a number in {row[:60].decode('ascii', 'replace')!r}"
                ) from None
        raise


def _ply_header(path: Path) -> tuple[str, list[_PlyElement], int, int]:
    """Format, elements, byte offset of the data and the header's number of lines."""
    with open(path, "rb") as f:
        if f.read(4).rstrip(b"\r\n") != b"ply":
            raise InputError("not a PLY file (first line is not 'ply')")
    header = _read_header(path, b"end_header")
    if header is None:
        raise InputError("PLY header has no end_header")
    lines, data_offset = header
    fmt = None
    elements: list[_PlyElement] = []
    for line in lines[1:-1]:
        words = line.split()
        if not words:  # a blank line: open3d reads past it too
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                if int(words[2]) < 0:
                    raise ValueError
                elements.append(_PlyElement(words[1], int(words[2]), []))
            elif words[0] == "property":
                element = elements[-1]
                if words[1] == "list":
                    if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
                        raise KeyError(words[2])
                    element.has_list = True
                    element.properties.append((words[4], "list"))
                else:
                    element.properties.append((words[2], _PLY_TYPES[words[1]]))
        except (IndexError, ValueError, KeyError):
            raise InputError(f"malformed PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format {fmt!r}")
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError("PLY has no vertex element")
    vertex = elements[names.index("vertex")]
    if not {"x", "y", "z"} <= {name for name, _ in vertex.properties}:
        raise InputError("PLY vertices have no x, y, z properties")
    return fmt, elements, data_offset, len(lines)


def _xyz_columns(element: _PlyElement) -> list[int]:
    names = [name for name, _ in element.properties]
    return [names.index(axis) for axis in "xyz"]


def _read_ply(path: Path) -> np.ndarray:
    fmt, elements, data_offset, header_lines = _ply_header(path)
    at = [e.name for e in elements].index("vertex")
    before, vertex, after = elements[:at], elements[at], elements[at + 1 :]
    if fmt == "ascii":  # one record a line
        rows = _data_rows(path, data_offset)
        first, total = sum(e.count for e in before), sum(e.count for e in elements)
        if len(rows) < first + vertex.count:
            raise InputError(f"truncated PLY: {len(rows)} of at least {first + vertex.count} data lines")
        if len(rows) != total:
            raise InputError(f"PLY holds {len(rows)} data lines where its header declares {total} (a wrong count)")
        if vertex.has_list:
            return _read_open3d(path, "ply", vertex.count)
        table = _parse_rows(rows[first : first + vertex.count], len(vertex.properties), header_lines + first + 1)
        return table[:, _xyz_columns(vertex)]
    if vertex.has_list or any(e.has_list for e in before):  # record sizes vary: offsets unknown until parsed
        return _read_open3d(path, "ply", vertex.count)
    order = "<" if fmt == "binary_little_endian" else ">"
    start = data_offset + sum(e.count * e.dtype(order).itemsize for e in before)
    needed = start - data_offset + vertex.count * vertex.dtype(order).itemsize
    available = path.stat().st_size - data_offset
    if available < needed:
        raise InputError(f"truncated PLY: {available} of {needed} bytes of vertex data")
    if not any(e.has_list for e in after):
        needed += sum(e.count * e.dtype(order).itemsize for e in after)
        if available != needed:
            raise InputError(
                f"PLY holds {available} bytes of data where its header declares {needed} (wrong "
                f"property types or counts: float written as double?)"
            )
    table = np.fromfile(path, dtype=vertex.dtype(order), count=vertex.count, offset=start)
    return np.stack([table[f"p{k}"] for k in _xyz_columns(vertex)], axis=1).astype(np.float64)


_PCD_TYPES = {
    ("F", 4): "f4",
    ("F", 8): "f8",
    ("I", 1): "i1",
    ("I", 2): "i2",
    ("I", 4): "i4",
    ("I", 8): "i8",
    ("U", 1): "u1",
    ("U", 2): "u2",
    ("U", 4): "u4",
    ("U", 8): "u8",
}


def _read_pcd(path: Path) -> np.ndarray:
    header = _read_header(path, b"DATA")
    if header is None:
        raise InputError("not a PCD file (no DATA line)")
    lines, data_offset = header
    fields: dict[str, list[str]] = {}
    for line in lines:
        words = line.split()
        if words and not words[0].startswith("#"):
            fields[words[0]] = words[1:]
    try:
        names = fields["FIELDS"]
        sizes = [int(s) for s in fields["SIZE"]]
        types = fields["TYPE"]
        counts = [int(c) for c in fields.get("COUNT", ["1"] * len(names))]
        width, height = int(fields["WIDTH"][0]), int(fields.get("HEIGHT", ["1"])[0])
        points = int(fields.get("POINTS", [str(width * height)])[0])
        data = fields["DATA"][0]
        codes = [_PCD_TYPES[(t, s)] for t, s in zip(types, sizes)]
    except KeyError as e:
        raise InputError(
            f"PCD header has no {e.args[0]} line or an unknown type"
            if isinstance(e.args[0], str)
            else f"PCD header has an unknown TYPE/SIZE {e.args[0]}"
        ) from None
    except (IndexError, ValueError):
        raise InputError("malformed PCD header") from None
    if not (len(names) == len(sizes) == len(types) == len(counts)) or min(counts + [width, height, points]) < 0:
        raise InputError("malformed PCD header (FIELDS, SIZE, TYPE and COUNT differ in length)")
    if points != width * height:
        raise InputError(f"PCD header declares {points} POINTS but WIDTH x HEIGHT = {width * height}")
    if not {"x", "y", "z"} <= set(names):
        raise InputError("PCD has no x, y, z fields")
    if data == "binary_compressed":
        return _read_open3d(path, "pcd", points)
    columns = [sum(counts[: names.index(axis)]) for axis in "xyz"]
    if data == "ascii":
        rows = _data_rows(path, data_offset)
        if len(rows) != points:
            raise InputError(
                f"{'truncated' if len(rows) < points else 'corrupt'} PCD: {len(rows)} data lines "
                f"where its header declares {points} POINTS"
            )
        return _parse_rows(rows, sum(counts), len(lines) + 1)[:, columns] if points else np.zeros((0, 3))
    if data != "binary":
        raise InputError(f"unknown PCD DATA {data!r}")
    dtype = np.dtype([(f"p{k}", "<" + code, (c,)) for k, (code, c) in enumerate(zip(codes, counts))])
    available, needed = path.stat().st_size - data_offset, points * dtype.itemsize
    if available != needed:
        raise InputError(
            f"{'truncated' if available < needed else 'corrupt'} PCD: {available} bytes of data where "
            f"its header declares {needed}"
        )
    table = np.fromfile(path, dtype=dtype, count=points, offset=data_offset)
    return np.stack([table[f"p{names.index(axis)}"][:, 0] for axis in "xyz"], axis=1).astype(np.float64)


# --- readers -------------------------------------------------------------------------------------


def _read_open3d(path: Path, fmt: str, expected: int) -> np.ndarray:
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), format=fmt, remove_nan_points=False, remove_infinite_points=False)
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) != expected:
        raise InputError(f"header promises {expected} points but {len(points)} could be read (corrupt file)")
    return points


_DECIMAL_COMMA = re.compile(r"(?:^|[ \t])[-+]?\d+,\d+(?:[eE][-+]?\d+)?(?=[ \t\r]|$)", re.MULTILINE)
"""A number with a decimal comma standing alone between blanks (a European-locale export); CSV's commas have no
blank on one side (``1.5,2.5``) or no digits after them (``1, 2``)."""


def _decimal_comma_line(text: str) -> tuple[int, str] | None:
    """The first line (number, text) where a number with a decimal comma stands beside other numbers, or None: read
    with commas as separators, such lines give wrong coordinates, on any line of the file."""
    for match in _DECIMAL_COMMA.finditer(text):
        start = text.rfind("\n", 0, match.start()) + 1
        end = text.find("\n", match.end())
        row = text[start : end if end >= 0 else len(text)].split("#", 1)[0]
        if match.end() - start <= len(row) and len(row.split()) >= 2:  # data, not a comment
            return text.count("\n", 0, start) + 1, row
    return None


def _read_text(path: Path) -> np.ndarray:
    try:
        text = path.read_text(encoding="utf-8-sig")  # a byte-order mark (Windows exports) is no number
    except UnicodeDecodeError:
        raise InputError("not a text file") from None
    text = text.replace(";", " ")  # semicolons separate columns in some exports
    if found := _decimal_comma_line(text):
        number, row = found
        raise InputError(f"line {number}: decimal commas ({row.strip()[:60]!r}) are not read: convert them to points")
    # Commas as separators are common in exported .xyz/.txt; extra columns (normals, colour) are ignored.
    lines = text.replace(",", " ").splitlines()
    first = next((k for k, line in enumerate(lines) if line.split("#", 1)[0].strip()), None)
    if first is None:
        raise InputError("no points")
    if _header_line(lines[first].split("#", 1)[0].split()):
        lines[first] = ""
    try:
        return np.loadtxt(lines, comments="#", usecols=(0, 1, 2), ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise InputError(_first_bad_line(lines) or f"expected x y z numbers on every line ({one_line(e)})") from None


def _first_bad_line(lines: list[str]) -> str | None:
    """The first of ``lines`` whose first three columns are not numbers, named by its line number in the file
    (numpy's row counts from 0 among data rows only)."""
    for number, line in enumerate(lines, start=1):
        words = line.split("#", 1)[0].split()
        if words and not (len(words) >= 3 and all(_number(word) for word in words[:3])):
            return f"line {number}: expected x y z numbers, got {line.strip()[:60]!r}"
    return None


def _header_line(words: list[str]) -> bool:
    """Whether the first line of a text scan is a header to skip: column names (``x y z``, CloudCompare's ``//X Y Z``:
    no word a number, so a data line with a typo is still refused) or a point count alone (as ``.pts`` files begin)."""
    if len(words) == 1 and words[0].isdigit():
        return True
    return not any(_number(word) for word in words)


def _number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _as_points(array: object) -> np.ndarray:
    if not isinstance(array, np.ndarray):
        raise InputError("file holds no plain array")
    if array.dtype.kind not in "iuf":
        raise InputError(f"array has non-numeric dtype {array.dtype}")
    if array.ndim == 2 and array.shape[0] == 3 < array.shape[1]:
        raise InputError(f"array has shape {array.shape}: it looks transposed (expected (N, 3))")
    if array.ndim != 2 or array.shape[1] < 3:
        raise InputError(f"array has shape {array.shape}, expected (N, 3) or (N, >=3)")
    return array[:, :3].astype(np.float64)


def _numpy_kind(path: Path) -> str:
    """What ``np.load`` takes the file for by its first bytes: "npy", "npz", or "" for anything else, which np.load
    takes for a pickle and refuses with advice to unpickle it, advice not to be passed on for a scan file."""
    with open(path, "rb") as f:
        head = f.read(6)
    return "npy" if head == b"\x93NUMPY" else "npz" if head[:4] in (b"PK\x03\x04", b"PK\x05\x06") else ""


def _read_npy(path: Path) -> np.ndarray:
    kind = _numpy_kind(path)
    if kind != "npy":
        raise InputError(
            "file is an .npz archive, not .npy"
            if kind
            else "not a NumPy array file (no .npy header; pickled data is not read)"
        )
    return _as_points(np.load(path, allow_pickle=False))


def _read_npz(path: Path) -> np.ndarray:
    kind = _numpy_kind(path)
    if kind != "npz":
        raise InputError(
            "file is an .npy array, not an .npz archive"
            if kind
            else "not a NumPy .npz archive (not a zip file; pickled data is not read)"
        )
    with np.load(path, allow_pickle=False) as archive:
        if not archive.files:
            raise InputError("archive holds no arrays")
        return _as_points(archive["points" if "points" in archive.files else archive.files[0]])


def _reason(error: Exception) -> str:
    """A library's error on one line, without libE57's debug trail (after '****')."""
    return " ".join(str(error).split("****")[0].split()) or type(error).__name__


COORDINATE_LIMIT = float(np.sqrt(np.finfo(np.float64).max / 12))
"""How far from 0 a coordinate may lie (about 3.9e153, past any survey): the diagonal of a box of such points, what
the checks before registration measure, still fits in float64. A point beyond counts as not finite."""
_LAS_HEADER_SIZES = {0: 227, 1: 227, 2: 227, 3: 235}  # public header bytes by minor version; 375 from LAS 1.4
_LAS_RECORD_SIZES = (20, 28, 26, 34, 57, 63, 30, 36, 38, 59, 67)  # bytes of a point record, by point format 0-10
_LAS_VLR_HEADER, _LAS_EVLR_HEADER = 54, 60
_LASZIP_VLR = (b"laszip encoded", 22204)  # user id and record id of the VLR that says how the points are compressed


def _las_point_count(path: Path) -> int:
    """The point count of a LAS/LAZ public header, once its sizes and counts are found to fit in the file (for LAZ,
    in its chunk table) and its scales and offsets to give finite coordinates.

    laspy trusts them: it loops over as many (E)VLRs as declared, reading nothing once past the end, and allocates
    the declared points, so a corrupt header would hang the run, eat memory without limit or pass as a scan too
    large for the machine. ``InputError`` naming the first that does not fit. Point data is compressed (LAZ) when
    the point format id has bit 7 set and bit 6 clear, as laspy decides: then its size is not known."""
    size = path.stat().st_size
    with open(path, "rb") as f:
        head = f.read(375)
    if head[:4] != b"LASF":
        raise InputError("no LASF signature")
    if len(head) < 227:
        raise InputError(f"corrupt header: a file of {size} bytes is shorter than the 227-byte LAS header")
    minor = head[25]
    header_size, offset, vlrs, format_id, record = struct.unpack_from("<HIIBH", head, 94)
    least = _LAS_HEADER_SIZES.get(minor, 375)
    if not least <= header_size <= size:
        raise InputError(
            f"corrupt header: a header size of {header_size} bytes, where LAS {head[24]}.{minor}'s is at "
            f"least {least} and the file holds {size}"
        )
    if not header_size <= offset <= size:
        raise InputError(
            f"corrupt header: point data at byte {offset}, outside the {header_size}-byte header and {size}-byte file"
        )
    if vlrs * _LAS_VLR_HEADER > offset - header_size:
        raise InputError(f"corrupt header: {vlrs:,} VLRs declared in {offset - header_size:,} bytes")
    count = struct.unpack_from("<I", head, 107)[0]
    if minor >= 4:
        first_evlr, evlrs, count = struct.unpack_from("<QIQ", head, 235)
        if evlrs and first_evlr + evlrs * _LAS_EVLR_HEADER > size:
            raise InputError(
                f"corrupt header: {evlrs:,} EVLRs declared from byte {first_evlr:,} of a {size:,}-byte file"
            )
    point_format = format_id & 0x3F
    if point_format >= len(_LAS_RECORD_SIZES) or record < _LAS_RECORD_SIZES[point_format]:
        raise InputError(f"corrupt header: point format {point_format} with {record}-byte records")
    for axis, scale, shift in zip("xyz", struct.unpack_from("<3d", head, 131), struct.unpack_from("<3d", head, 155)):
        if not abs(scale) * 2**31 + abs(shift) <= COORDINATE_LIMIT:  # also NaN
            why = (
                f"put coordinates past ±{COORDINATE_LIMIT:.2g}"
                if np.isfinite([scale, shift]).all()
                else "are not finite"
            )
            raise InputError(f"corrupt header: {axis} scale {scale:g} and offset {shift:g} {why}")
    compressed = bool(format_id & 0x80) and not format_id & 0x40
    if compressed:
        _check_laz_chunk_table(path, header_size, offset, size, count)
    elif count * record > size - offset:
        raise InputError(
            f"corrupt header: {count:,} points of {record} bytes declared in {size - offset:,} bytes of point data"
        )
    return count


def _check_laz_chunk_table(path: Path, header_size: int, offset: int, size: int, count: int) -> None:
    """``InputError`` when the LAZ chunk table (located by the int64 at the start of the point data) does not fit
    the bytes of compressed points before it or the header's ``count``: more chunks declared than there are bytes
    (lazrs reserves memory for them all first and aborts the process when it cannot), chunks whose sizes add up past
    the bytes (lazrs panics), or fewer points in the chunks than ``count`` (the file's size bounds no count, so the
    memory check would take it for a scan too large for the machine), or no table where its offset says (lazrs
    cannot read such a file either). An offset of -1 is a streaming writer's: the table's offset is then the file's
    last 8 bytes. A file without the laszip VLR is left to lazrs, which reports it."""
    import lazrs

    with open(path, "rb") as f:
        f.seek(offset)
        raw = f.read(8)
        table = struct.unpack("<q", raw)[0] if len(raw) == 8 else None
        if table == -1:
            f.seek(size - 8)
            table = struct.unpack("<q", f.read(8))[0]
        if table is None or not offset + 8 <= table <= size - 8:
            raise InputError(
                f"corrupt chunk table: its offset {table} lies outside the {size - offset:,} bytes of compressed points"
            )
        f.seek(table)
        _, chunks = struct.unpack("<II", f.read(8))
        available = table - offset - 8
        if chunks > available:
            raise InputError(
                f"corrupt chunk table: {chunks:,} chunks declared for {available:,} bytes of compressed points"
            )
        vlr = _laszip_vlr(f, header_size, offset)
        if vlr is None:
            return
        f.seek(offset)
        # (points, bytes) a chunk; for chunks of a fixed size, the size: the last one's count is then a bound
        entries = lazrs.read_chunk_table(f, lazrs.LazVlr(vlr))
    points, used = sum(n for n, _ in entries), sum(b for _, b in entries)
    if used > available:
        raise InputError(
            f"corrupt chunk table: chunks of {used:,} bytes declared in {available:,} bytes of compressed points"
        )
    if count > points:
        raise InputError(f"corrupt header: {count:,} points declared where the chunk table holds at most {points:,}")


def _laszip_vlr(f, header_size: int, offset: int) -> bytes | None:
    """The data of the laszip VLR among the VLRs between the header and the point data of the LAZ file open as
    ``f``, or None."""
    at = header_size
    while at + _LAS_VLR_HEADER <= offset:
        f.seek(at)
        head = f.read(_LAS_VLR_HEADER)
        record_id, length = struct.unpack_from("<HH", head, 18)
        if (head[2:18].rstrip(b"\0"), record_id) == _LASZIP_VLR:
            return f.read(length)
        at += _LAS_VLR_HEADER + length
    return None


def _read_las(path: Path) -> np.ndarray:
    """LAS, and LAZ through laspy's lazrs back end: the scaled and offset x, y, z of every point record."""
    import laspy

    try:
        _las_point_count(path)
        return np.asarray(laspy.read(path).xyz, dtype=np.float64)
    except Exception as e:  # noqa: BLE001 - laspy, lazrs and numpy each raise their own kinds
        raise InputError(f"not a readable {path.suffix[1:].upper()} file ({_reason(e)})") from None


def _read_e57(path: Path) -> np.ndarray:
    """Every point set of an E57 file (one file is one scan), each moved by its own pose into the file's frame;
    spherical coordinates are converted and points flagged invalid dropped (pye57)."""
    import pye57

    try:
        with pye57.E57(str(path)) as e57:
            parts = [e57.read_scan(k, transform=True, ignore_missing_fields=True) for k in range(e57.scan_count)]
    except Exception as e:  # noqa: BLE001 - libE57 raises its own kinds
        raise InputError(f"not a readable E57 file ({_reason(e)})") from None
    if not parts:
        raise InputError("E57 file holds no point set")
    return np.concatenate([np.stack([p["cartesianX"], p["cartesianY"], p["cartesianZ"]], axis=1) for p in parts])


def load_scan(path: str | Path) -> np.ndarray:
    """Points of one scan as a C-contiguous (N, 3) float64 array, N >= 1.

    .ply / .pcd (ASCII or binary; x, y, z of any numeric type); .xyz / .txt: x y z per line (whitespace, commas or
    semicolons; ``#`` comments, extra columns and a first line of column names or a point count ignored; decimal
    commas refused); .npy: an (N, >=3) numeric array; .npz: the array
    ``points``, else the first one; .las / .laz: the point records' coordinates (laspy, lazrs); .e57: all its point
    sets in the file's frame (pye57).
    Non-finite rows are kept (see ``finite_points``). Raises ``InputError`` when the file cannot be
    read, is corrupt or truncated, has the wrong shape, or holds no points.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix not in SCAN_SUFFIXES:
            raise InputError(f"unknown scan format {path.suffix!r} (supported: {', '.join(SCAN_SUFFIXES)})")
        if why := not_regular(path):
            raise InputError(why)
        if path.stat().st_size == 0:
            raise InputError("empty file")
        if suffix == ".ply":
            points = _read_ply(path)
        elif suffix == ".pcd":
            points = _read_pcd(path)
        elif suffix in (".xyz", ".txt"):
            points = _read_text(path)
        elif suffix == ".npy":
            points = _read_npy(path)
        elif suffix in (".las", ".laz"):
            points = _read_las(path)
        elif suffix == ".e57":
            points = _read_e57(path)
        else:
            points = _read_npz(path)
    except InputError as e:
        raise InputError(f"cannot read scan {path}: {e}") from None
    except Exception as e:  # noqa: BLE001 - any reader failure is bad input, reported on one line
        raise InputError(f"cannot read scan {path}: {one_line(e)}") from None
    if len(points) == 0:
        raise InputError(f"cannot read scan {path}: no points")
    return np.ascontiguousarray(points)


READ_BYTES_PER_POINT = {"text": 400, "binary": 120}
"""Peak memory of reading a scan and computing its features, per point (measured, ``benchmarks/bench_memory.py``):
text formats hold the file's lines as Python objects while parsing; binary ones the reader's table, the float64
points, their finite copy and the features' working copies."""


def point_count(path: str | Path) -> int:
    """How many points the scan file at ``path`` holds, from its header (PLY, PCD, NPY, NPZ, LAS/LAZ, E57) or, for
    text, its size over the mean length of its first lines; 0 when that cannot be told (the reader will say why)."""
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            _, elements, _, _ = _ply_header(path)
            return next(e.count for e in elements if e.name == "vertex")
        if suffix == ".pcd":
            lines, _ = _read_header(path, b"DATA") or ([], 0)
            fields = {words[0]: words[1:] for words in map(str.split, lines) if words}
            return int(fields["POINTS"][0])
        if suffix == ".npy":
            with open(path, "rb") as f:
                return _npy_rows(f)
        if suffix == ".npz":
            with np.load(path, allow_pickle=False) as archive:
                name = "points" if "points" in archive.files else archive.files[0]
                with archive.zip.open(name + ".npy") as member:
                    return _npy_rows(member)
        if suffix in (".las", ".laz"):
            return _las_point_count(path)
        if suffix == ".e57":
            import pye57

            with pye57.E57(str(path)) as e57:
                return sum(int(e57.get_header(k).point_count) for k in range(e57.scan_count))
        with open(path, "rb") as f:
            head = f.read(1 << 16)
        lines = head.count(b"\n")
        return int(path.stat().st_size * lines / len(head)) if lines else 1
    except Exception:  # noqa: BLE001 - a header that cannot be read is the reader's to report
        return 0


def _npy_rows(f) -> int:
    """The first dimension an .npy header declares (``f`` at its start)."""
    fmt = np.lib.format
    read = fmt.read_array_header_1_0 if fmt.read_magic(f) == (1, 0) else fmt.read_array_header_2_0
    return int(read(f)[0][0])


def check_memory(path: str | Path) -> None:
    """``InputError`` when reading the scan at ``path`` and computing its features would need more memory than is
    available now (``READ_BYTES_PER_POINT``): one line before the machine runs out, instead of the kernel's kill.
    Nothing is opened that is not a regular file (``not_regular``: the reader says why it is skipped)."""
    import psutil

    path = Path(path)
    if not_regular(path):
        return
    count = point_count(path)
    kind = "text" if _is_text(path) else "binary"
    needed, available = count * READ_BYTES_PER_POINT[kind], psutil.virtual_memory().available
    if needed > available:
        raise InputError(
            f"scan {path.name} holds {count:,} points: reading it needs about {needed / 2**30:.1f} GB, "
            f"{available / 2**30:.1f} GB are available (thin it first, e.g. by voxel down-sampling)"
        )


def _is_text(path: Path) -> bool:
    """Whether the scan at ``path`` is parsed as text (.xyz, .txt, ASCII PLY and PCD)."""
    suffix = path.suffix.lower()
    if suffix not in (".ply", ".pcd"):
        return suffix in (".xyz", ".txt")
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    return b"format ascii" in head or b"DATA ascii" in head


def finite_points(points: np.ndarray) -> tuple[np.ndarray, int]:
    """The rows of ``points`` whose coordinates are all finite and within ``COORDINATE_LIMIT`` (NaN fails both
    comparisons: bools only, no float copy of a large scan), and how many rows were dropped."""
    keep = ((points <= COORDINATE_LIMIT) & (points >= -COORDINATE_LIMIT)).all(axis=1)
    return points[keep], int(len(points) - keep.sum())


# --- writers -------------------------------------------------------------------------------------


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write a binary PLY (double-precision x, y, z; optional (N, 3) colours, floats in [0, 1] or uint8, as uchar
    red, green, blue) atomically. Written here rather than by open3d: on a full disk its RPly prints a line per
    failed row and open3d returns success with the file cut short."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != points.shape:
            raise ValueError(f"colors must be {points.shape}, got {colors.shape}")
        if colors.dtype != np.uint8:
            colors = np.round(np.clip(colors, 0.0, 1.0) * 255.0).astype(np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    rows = np.empty(len(points), dtype=fields)
    for k, axis in enumerate("xyz"):
        rows[axis] = points[:, k]
    if colors is not None:
        for k, channel in enumerate(("red", "green", "blue")):
            rows[channel] = colors[:, k]
    types = {"<f8": "double", "u1": "uchar"}
    header = (
        f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
        + "".join(f"property {types[kind]} {name}\n" for name, kind in fields)
        + "end_header\n"
    )
    with atomic_write(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(rows.tobytes())


def write_scan(path: str | Path, points: np.ndarray) -> None:
    """Write points (N, 3) atomically in the format named by ``path``'s suffix (any of
    ``SCAN_SUFFIXES``); text and numpy formats keep full float64 precision, .pcd is float32."""
    path = Path(path)
    points = np.asarray(points, dtype=np.float64)
    suffix = path.suffix.lower()
    if suffix == ".ply":
        write_ply(path, points)
    elif suffix == ".pcd":
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        with atomic_path(path) as tmp:
            if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
                raise OSError(f"open3d could not write {path}")
    elif suffix in (".xyz", ".txt"):
        with atomic_write(path, "w") as f:
            np.savetxt(f, points, fmt="%.17g")
    elif suffix == ".npy":
        with atomic_write(path, "wb") as f:
            np.save(f, points)
    elif suffix == ".npz":
        with atomic_write(path, "wb") as f:
            np.savez(f, points=points)
    else:
        raise ValueError(f"unknown scan format {path.suffix!r} (supported: {', '.join(SCAN_SUFFIXES)})")
