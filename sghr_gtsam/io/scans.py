"""Reading and writing scans (point clouds as (N, 3) float64 arrays).

Every failure to read a scan becomes a one-line ``InputError("cannot read scan X: reason")``.
open3d does not report failures: it returns an empty cloud for a garbage file and a full-length
cloud padded with zeros for a truncated PLY, so PLY and PCD headers are checked here first and the
point count open3d returns is compared with the header's.
"""

from __future__ import annotations

import fnmatch
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from sghr_gtsam.io.atomic import atomic_path, atomic_write
from sghr_gtsam.types import InputError

SCAN_SUFFIXES = (".ply", ".pcd", ".xyz", ".txt", ".npy", ".npz", ".las", ".laz", ".e57")

NON_SCAN_PATTERNS = ("*pose*.txt", "*traj*.txt", "*overlap*.txt", "readme*", "license*")
"""``.txt`` is also a scan format, so files matching these (lower-cased) names are not listed as
scans: ground truth and outputs such as ``gt_poses.txt``, ``poses.txt``, ``0.pose.txt``,
``overlap.txt``. ``.log`` / ``.conf`` / ``.info`` files are never scans (not in ``SCAN_SUFFIXES``)."""


def _natural_key(path: Path) -> tuple[list[str | int], str]:
    """``scan_2`` before ``scan_10``: digit runs compare as numbers, case is ignored, and the exact
    name breaks ties (so the order never depends on the file system's listing order)."""
    parts = re.split(r"(\d+)", path.name)  # text, digits, text, ...: types match position by position
    return [int(part) if k % 2 else part.lower() for k, part in enumerate(parts)], path.name


def _is_scan_file(path: Path) -> bool:
    name = path.name.lower()
    return (
        path.is_file()
        and path.suffix.lower() in SCAN_SUFFIXES
        and not name.startswith(".")  # hidden files, including atomic_write's temporaries
        and not any(fnmatch.fnmatch(name, pattern) for pattern in NON_SCAN_PATTERNS)
    )


def list_scans(folder: str | Path) -> list[Path]:
    """Scan files in ``folder`` (not recursive), in natural file-name order (``cloud_bin_2`` before
    ``cloud_bin_10``); the order defines the scan indices. Raises ``InputError`` when the folder does
    not exist or holds no scans."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"scan folder {folder} does not exist" if not folder.exists() else f"{folder} is not a folder")
    scans = sorted((p for p in folder.iterdir() if _is_scan_file(p)), key=_natural_key)
    if not scans:
        raise InputError(f"no scans in {folder} (looked for {', '.join(SCAN_SUFFIXES)})")
    return scans


# --- PLY / PCD header checks -------------------------------------------------------------------

_PLY_TYPE_SIZES = {
    "char": 1, "int8": 1, "uchar": 1, "uint8": 1, "short": 2, "int16": 2, "ushort": 2, "uint16": 2,
    "int": 4, "int32": 4, "uint": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}  # fmt: skip
_HEADER_LIMIT = 1 << 20  # a header longer than this is not a point cloud header


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[str]
    stride: int | None  # bytes per record in a binary file; None when a list property makes it vary


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


def _check_ply(path: Path) -> int:
    """Check a PLY header and that all vertex data is present; return the vertex count."""
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
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                if int(words[2]) < 0:
                    raise ValueError
                elements.append(_PlyElement(words[1], int(words[2]), [], 0))
            elif words[0] == "property":
                element = elements[-1]
                element.properties.append(words[-1])
                if words[1] == "list":
                    element.stride = None
                elif element.stride is not None:
                    element.stride += _PLY_TYPE_SIZES[words[1]]
        except (IndexError, ValueError, KeyError):
            raise InputError(f"malformed PLY header line {line!r}") from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format {fmt!r}")
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError("PLY has no vertex element")
    upto = elements[: names.index("vertex") + 1]
    vertex = upto[-1]
    if not {"x", "y", "z"} <= set(vertex.properties):
        raise InputError("PLY vertices have no x, y, z properties")

    if fmt == "ascii":
        needed = sum(e.count for e in upto)
        with open(path, "rb") as f:
            f.seek(data_offset)
            rows = [row for row in f.read().splitlines() if row.strip()]
        if len(rows) < needed:
            raise InputError(f"truncated PLY: {len(rows)} of at least {needed} data lines")
        if vertex.stride is not None and vertex.count and len(rows[needed - 1].split()) != len(vertex.properties):
            raise InputError("truncated or malformed PLY vertex data")
    elif all(e.stride is not None for e in upto):  # with list properties the size is not known up front
        needed = sum(e.count * e.stride for e in upto)  # type: ignore[operator]
        available = path.stat().st_size - data_offset
        if available < needed:
            raise InputError(f"truncated PLY: {available} of {needed} bytes of vertex data")
    return vertex.count


def _check_pcd(path: Path) -> int:
    """Check a PCD header; return its point count."""
    header = _read_header(path, b"DATA")
    if header is None:
        raise InputError("not a PCD file (no DATA line)")
    for line in header[0]:
        words = line.split()
        if len(words) == 2 and words[0] == "POINTS" and words[1].isdigit():
            return int(words[1])
    raise InputError("PCD header has no POINTS line")


# --- readers -------------------------------------------------------------------------------------


def _read_open3d(path: Path, fmt: str, expected: int) -> np.ndarray:
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.io.read_point_cloud(str(path), format=fmt, remove_nan_points=False, remove_infinite_points=False)
    points = np.asarray(cloud.points, dtype=np.float64)
    if len(points) != expected:
        raise InputError(f"header promises {expected} points but {len(points)} could be read (corrupt file)")
    return points


def _read_text(path: Path) -> np.ndarray:
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError("not a text file") from None
    # Commas as separators are common in exported .xyz/.txt; extra columns (normals, colour) are ignored.
    lines = text.replace(",", " ").splitlines()
    if not any(line.split("#", 1)[0].strip() for line in lines):
        raise InputError("no points")
    try:
        return np.loadtxt(lines, comments="#", usecols=(0, 1, 2), ndmin=2, dtype=np.float64)
    except ValueError as e:
        raise InputError(f"expected x y z numbers on every line ({' '.join(str(e).split())})") from None


def _as_points(array: object) -> np.ndarray:
    if not isinstance(array, np.ndarray):
        raise InputError("file holds no plain array")
    if array.dtype.kind not in "iuf":
        raise InputError(f"array has non-numeric dtype {array.dtype}")
    if array.ndim != 2 or array.shape[1] < 3:
        raise InputError(f"array has shape {array.shape}, expected (N, 3) or (N, >=3)")
    return array[:, :3].astype(np.float64)


def _read_npy(path: Path) -> np.ndarray:
    data = np.load(path, allow_pickle=False)
    if isinstance(data, np.lib.npyio.NpzFile):
        data.close()
        raise InputError("file is an .npz archive, not .npy")
    return _as_points(data)


def _read_npz(path: Path) -> np.ndarray:
    with np.load(path, allow_pickle=False) as archive:
        if not archive.files:
            raise InputError("archive holds no arrays")
        return _as_points(archive["points" if "points" in archive.files else archive.files[0]])


def _reason(error: Exception) -> str:
    """A library's error on one line, without libE57's debug trail (after '****')."""
    return " ".join(str(error).split("****")[0].split()) or type(error).__name__


def _read_las(path: Path) -> np.ndarray:
    """LAS, and LAZ through laspy's lazrs back end: the scaled and offset x, y, z of every point record."""
    import laspy

    try:
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

    .ply / .pcd via open3d; .xyz / .txt: x y z per line (whitespace or commas, ``#`` comments, extra
    columns ignored); .npy: an (N, >=3) numeric array; .npz: the array ``points``, else the first one;
    .las / .laz: the point records' coordinates (laspy, lazrs); .e57: all its point sets in the file's frame (pye57).
    Non-finite rows are kept (see ``finite_points``). Raises ``InputError`` when the file cannot be
    read, is corrupt or truncated, has the wrong shape, or holds no points.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    try:
        if suffix not in SCAN_SUFFIXES:
            raise InputError(f"unknown scan format {path.suffix!r} (supported: {', '.join(SCAN_SUFFIXES)})")
        if not path.is_file():
            raise InputError("no such file" if not path.exists() else "not a file")
        if path.stat().st_size == 0:
            raise InputError("empty file")
        if suffix == ".ply":
            points = _read_open3d(path, "ply", _check_ply(path))
        elif suffix == ".pcd":
            points = _read_open3d(path, "pcd", _check_pcd(path))
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
        reason = " ".join(str(e).split()) or type(e).__name__
        raise InputError(f"cannot read scan {path}: {reason}") from None
    if len(points) == 0:
        raise InputError(f"cannot read scan {path}: no points")
    return np.ascontiguousarray(points)


def finite_points(points: np.ndarray) -> tuple[np.ndarray, int]:
    """The rows of ``points`` whose coordinates are all finite, and how many rows were dropped."""
    keep = np.isfinite(points).all(axis=1)
    return points[keep], int(len(points) - keep.sum())


# --- writers -------------------------------------------------------------------------------------


def write_ply(path: str | Path, points: np.ndarray, colors: np.ndarray | None = None) -> None:
    """Write a binary PLY (double-precision x, y, z; optional (N, 3) colours, floats in [0, 1] or
    uint8) atomically."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {points.shape}")
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if colors is not None:
        colors = np.asarray(colors)
        if colors.shape != points.shape:
            raise ValueError(f"colors must be {points.shape}, got {colors.shape}")
        rgb = colors / 255.0 if colors.dtype == np.uint8 else colors.astype(np.float64)
        cloud.colors = o3d.utility.Vector3dVector(rgb)
    with atomic_path(path) as tmp:
        if not o3d.io.write_point_cloud(str(tmp), cloud, write_ascii=False):
            raise OSError(f"open3d could not write {path}")


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
