"""Pose files: our ``gt_poses.txt`` / ``poses.txt`` form, KITTI, TUM, and the 3DMatch ground truth
(``gt.log``, ``gt.info``, ``gt_overlap.log``). All writers are atomic; every reader raises a one-line
``InputError`` on a malformed file.

Text formats (blank lines and lines starting with ``#`` are ignored everywhere):

- poses (``gt_poses.txt``): per scan a line with its name (the scan's file name), then 4 rows of
  the 4x4 ``T_i`` with ``p_world = T_i @ p_scan``.
- KITTI: one line per pose, the 12 numbers of ``T_i[:3, :]`` row by row.
- TUM: one line per pose, ``timestamp tx ty tz qx qy qz qw`` (the unit quaternion of ``T_i[:3, :3]``, scalar last,
  written with qw >= 0); scans have no time, so the timestamp is the scan's index.
- gt.log (Redwood / 3DMatch): per pair a header ``i j n_fragments``, then 4 rows of ``T_ij``, which
  maps points of fragment j into the frame of fragment i (``T_ij = inv(T_i) @ T_j``).
- gt.info: per pair a header ``i j n_fragments``, then a 6x6 information matrix in the 3DMatch
  evaluation's order [translation, rotation (quaternion vector part)], not gtsam's [rotation, translation].
- gt_overlap.log: one line ``i,j,overlap`` per pair (i < j), overlap a fraction in [0, 1].
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sghr_gtsam.io.atomic import atomic_write
from sghr_gtsam.se3 import non_rigid
from sghr_gtsam.types import InputError


def _content_lines(path: Path, what: str) -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of every line that is neither blank nor a comment."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"cannot read {what} {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read {what} {path}: {' '.join(str(e).split())}") from None
    return [(k, s) for k, line in enumerate(text.splitlines(), 1) if (s := line.strip()) and not s.startswith("#")]


def _numbers(path: Path, what: str, line: tuple[int, str], count: int) -> list[float]:
    number, text = line
    try:
        values = [float(word) for word in text.replace(",", " ").split()]
    except ValueError:
        values = []
    if len(values) != count:
        raise InputError(f"cannot read {what} {path}: line {number}: expected {count} numbers, got {text[:60]!r}")
    return values


def _blocks(path: Path, what: str, rows: int) -> list[list[tuple[int, str]]]:
    """Content lines cut into blocks of one header line plus ``rows`` rows."""
    lines = _content_lines(path, what)
    if not lines:
        raise InputError(f"cannot read {what} {path}: no entries")
    size = rows + 1
    if len(lines) % size:
        raise InputError(
            f"cannot read {what} {path}: {len(lines)} content lines is not a whole number of "
            f"{size}-line blocks (truncated?)"
        )
    return [lines[k : k + size] for k in range(0, len(lines), size)]


def _pair(path: Path, what: str, line: tuple[int, str]) -> tuple[int, int]:
    number, text = line
    words = text.replace(",", " ").split()
    if len(words) < 2 or not (words[0].isdigit() and words[1].isdigit()):
        raise InputError(f"cannot read {what} {path}: line {number}: expected 'i j ...', got {text[:60]!r}")
    return int(words[0]), int(words[1])


def _matrix(path: Path, what: str, lines: list[tuple[int, str]], n: int) -> np.ndarray:
    return np.array([_numbers(path, what, line, n) for line in lines])


def check_rigid(poses: np.ndarray, what: str, labels: Sequence[int] | None = None) -> None:
    """One-line ``InputError`` naming the first of ``poses`` (N, 4, 4) (by its index, or its entry of ``labels``)
    that is not finite or not a rigid transform (``se3.non_rigid``)."""
    name = range(len(poses)) if labels is None else labels
    finite = np.isfinite(poses).all(axis=(1, 2))
    if not finite.all():
        raise InputError(f"{what} {name[np.flatnonzero(~finite)[0]]} is not finite")
    bad = non_rigid(poses)
    if bad.any():
        raise InputError(
            f"{what} {name[np.flatnonzero(bad)[0]]} is not a rigid transform (rotation orthonormal "
            f"with determinant +1, last row 0 0 0 1)"
        )


def unwritable_name(name: object) -> str | None:
    """Why ``name`` cannot name a pose in a pose file, or None: a name is a line of its own of UTF-8 text, read
    back stripped, and a line starting with '#' is a comment."""
    if not isinstance(name, str):
        return "is not a string"
    if not name.strip() or name.strip() != name or name.splitlines() != [name] or name.startswith("#"):
        return "cannot be written on its own line"
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:  # a file name's bytes that are not UTF-8 (Python keeps them as surrogates)
        return "cannot be written as UTF-8 text"
    return None


def shown_name(name: str) -> str:
    """``name`` as a message shows it: as it is, or quoted with escapes when a pose file could not hold it (a line
    break, bytes that are not UTF-8), so that the message stays one printable line."""
    return name if unwritable_name(name) is None else repr(name)


def _check_poses(poses: np.ndarray) -> np.ndarray:
    """``poses`` as a non-empty (N, 4, 4) float array: a file without entries is one its reader refuses."""
    try:
        poses = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("poses must be a numeric (N, 4, 4) array") from None
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not len(poses):
        raise InputError(f"poses must be a non-empty (N, 4, 4) array, got shape {poses.shape}")
    return poses


def write_poses(path: str | Path, names: Sequence[str], poses: np.ndarray, comment: str | None = None) -> None:
    """Write poses (N, 4, 4) ``T_i`` with their scan names (str); ``comment`` becomes leading ``#`` lines.
    Numbers are written in the shortest form that reads back exactly; NaN (a pose not known) too, as
    ``read_poses`` keeps it."""
    poses = _check_poses(poses)
    if len(names) != len(poses):
        raise InputError(f"{len(names)} names for {len(poses)} poses")
    for name in names:
        if why := unwritable_name(name):
            raise InputError(f"pose name {name!r} {why}")
    out = [f"# {line}" for line in comment.splitlines()] if comment else []
    for name, T in zip(names, poses):
        out.append(name)
        out.extend(" ".join(repr(float(x)) for x in row) for row in T)
    with atomic_write(path) as f:
        f.write("\n".join(out) + "\n")


def read_poses(path: str | Path) -> tuple[list[str], np.ndarray]:
    """Names and poses (N, 4, 4) from a ``gt_poses.txt``-style file. NaN entries (a fragment with no
    known pose, as in ``derived_abs_poses``) are kept."""
    path = Path(path)
    blocks = _blocks(path, "poses", 4)
    names = [block[0][1] for block in blocks]
    poses = np.stack([_matrix(path, "poses", block[1:], 4) for block in blocks])
    return names, poses


def write_kitti(path: str | Path, poses: np.ndarray) -> None:
    """Write poses (N, 4, 4) in the KITTI form, 12 numbers a line."""
    poses = _check_poses(poses)
    with atomic_write(path) as f:
        f.write("".join(" ".join(repr(float(x)) for x in T[:3].ravel()) + "\n" for T in poses))


def read_kitti(path: str | Path) -> np.ndarray:
    """Poses (N, 4, 4) from a KITTI file."""
    path = Path(path)
    lines = _content_lines(path, "KITTI poses")
    if not lines:
        raise InputError(f"cannot read KITTI poses {path}: no entries")
    poses = np.tile(np.eye(4), (len(lines), 1, 1))
    poses[:, :3, :] = _matrix(path, "KITTI poses", lines, 12).reshape(-1, 3, 4)
    return poses


def write_tum(path: str | Path, poses: np.ndarray, stamps: Sequence[float]) -> None:
    """Write rigid poses (N, 4, 4) in the TUM form with their finite timestamps (N,), which must increase. A
    rotation off-orthonormal within ``se3.RIGID_TOL`` is written as the quaternion of its nearest rotation."""
    from scipy.spatial.transform import Rotation

    poses = _check_poses(poses)
    check_rigid(poses, "TUM pose")
    try:
        stamps = np.asarray(stamps, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("TUM timestamps must be numbers") from None
    if stamps.shape != (len(poses),) or not np.isfinite(stamps).all() or np.any(np.diff(stamps) <= 0):
        raise InputError(f"need {len(poses)} finite increasing timestamps, got {stamps.ravel().tolist()[:10]}")
    q = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # x y z w
    q *= np.where(q[:, 3:] < 0, -1.0, 1.0)
    with atomic_write(path) as f:
        f.write(
            "".join(" ".join(repr(float(x)) for x in (t, *T[:3, 3], *qk)) + "\n" for t, T, qk in zip(stamps, poses, q))
        )


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and poses (N, 4, 4) from a TUM file; a quaternion must be of unit length (±1e-6)."""
    from scipy.spatial.transform import Rotation

    path = Path(path)
    lines = _content_lines(path, "TUM poses")
    if not lines:
        raise InputError(f"cannot read TUM poses {path}: no entries")
    rows = _matrix(path, "TUM poses", lines, 8)
    norms = np.linalg.norm(rows[:, 4:], axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-6):
        bad = int(np.argmax(np.abs(norms - 1.0)))
        raise InputError(f"cannot read TUM poses {path}: line {lines[bad][0]}: quaternion of length {norms[bad]:.6g}")
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = Rotation.from_quat(rows[:, 4:]).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    return rows[:, 0], poses


def read_gt_log(path: str | Path) -> dict[tuple[int, int], np.ndarray]:
    """3DMatch / Redwood ``gt.log``: {(i, j): T_ij (4, 4)}. The matrices are off-orthonormal by up to
    5e-4 in the original files; project them (``se3.project_to_so3``) before measuring angles."""
    path = Path(path)
    return {_pair(path, "gt.log", b[0]): _matrix(path, "gt.log", b[1:], 4) for b in _blocks(path, "gt.log", 4)}


def read_gt_info(path: str | Path) -> dict[tuple[int, int], np.ndarray]:
    """3DMatch ``gt.info``: {(i, j): information (6, 6)}, order [translation, rotation]."""
    path = Path(path)
    return {_pair(path, "gt.info", b[0]): _matrix(path, "gt.info", b[1:], 6) for b in _blocks(path, "gt.info", 6)}


def read_gt_overlap(path: str | Path) -> dict[tuple[int, int], float]:
    """3DMatch ``gt_overlap.log``: {(i, j): overlap fraction} for every listed pair (i < j)."""
    path = Path(path)
    lines = _content_lines(path, "gt_overlap.log")
    if not lines:
        raise InputError(f"cannot read gt_overlap.log {path}: no entries")
    overlap = {}
    for line in lines:
        pair = _pair(path, "gt_overlap.log", line)
        overlap[pair] = _numbers(path, "gt_overlap.log", line, 3)[2]
    return overlap
