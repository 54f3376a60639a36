"""3D g2o pose graphs (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``) and the SE-Sync objective used to score them.

g2o stores each edge's 6×6 information as its 21 upper-triangular values, row by row, in the order
[translation, rotation]; ``PoseGraph.information`` is in gtsam's order [rotation, translation]. The rotation
block is used as written, as gtsam's ``readG2o`` and SE-Sync do.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from sghr_gtsam.io.atomic import atomic_write
from sghr_gtsam.io.poses import check_rigid
from sghr_gtsam.se3 import make_T
from sghr_gtsam.types import InputError, PoseGraph

_UPPER = np.triu_indices(6)
_G2O_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])  # gtsam index k holds g2o index _G2O_TO_GTSAM[k]


def _poses(x: np.ndarray, where: list[str]) -> np.ndarray:
    """Rows ``x y z qx qy qz qw`` as 4×4 transforms; ``where[k]`` names row k's line for errors."""
    x = x.reshape(-1, 7)
    finite = np.all(np.isfinite(x), axis=1)
    # A quaternion is a direction: any finite non-zero one is normalised, 1e-200 as 1e300 (each scaled by its
    # largest entry first, so that neither its norm's square underflows nor overflows).
    q = np.where(finite[:, None], x[:, 3:], 1.0)
    largest = np.abs(q).max(axis=1, keepdims=True)
    q = q / np.where(largest > 0, largest, 1.0)
    norm = np.linalg.norm(q, axis=1)
    bad = ~finite | (norm == 0)
    if bad.any():
        raise InputError(f"{where[np.flatnonzero(bad)[0]]}: pose is not finite or its quaternion is zero")
    return make_T(Rotation.from_quat(q / norm[:, None]).as_matrix().reshape(-1, 3, 3), x[:, :3])


def _lowest_eigenvalues(omega: np.ndarray) -> np.ndarray:
    """Each symmetric matrix's (E, 6, 6) lowest eigenvalue relative to its largest entry: no overflow, and a
    tolerance that scales."""
    scale = np.abs(omega).max(axis=(1, 2))
    return np.linalg.eigvalsh(omega / np.where(scale > 0, scale, 1.0)[:, None, None])[:, 0]


def not_definite(omega: np.ndarray) -> np.ndarray:
    """(E,) bool: each symmetric (E, k, k) matrix not positive definite, judged on its correlations
    (``Ω_ij / √(Ω_ii Ω_jj)``): rotations in radians beside translations in micrometres span 1e16 and are definite."""
    d = np.diagonal(omega, axis1=1, axis2=2)
    positive = (d > 0).all(axis=1)
    s = 1.0 / np.sqrt(np.where(d > 0, d, 1.0))
    return ~positive | (np.linalg.eigvalsh(omega * s[:, :, None] * s[:, None, :])[:, 0] <= 1e-12)


def isotropic_ready(omega: np.ndarray) -> np.ndarray:
    """(E,) bool: information matrices (E, 6, 6) whose rotation and translation blocks are both positive definite,
    all that SE-Sync's isotropic precisions (``sesync_precisions``) need of them, even where the whole is not."""
    return ~not_definite(omega[:, :3, :3]) & ~not_definite(omega[:, 3:, 3:])


def check_information(information: np.ndarray, edges: int | None = None, semidefinite: bool = True) -> np.ndarray:
    """``information`` as floats, one (6, 6) matrix or with ``edges`` (edges, 6, 6), or a one-line ``InputError``
    unless each matrix is finite, symmetric and (``semidefinite``) positive semi-definite (zero: a failed
    registration, no measurement)."""
    shape = (6, 6) if edges is None else (edges, 6, 6)
    try:
        info = np.asarray(information, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"information must be a numeric {shape} array") from None
    if info.shape != shape:
        raise InputError(f"information must have shape {shape}, got {info.shape}")
    stack = info.reshape(-1, 6, 6)

    def refuse(bad: np.ndarray, what: str) -> None:
        if bad.any():
            where = "" if edges is None else f"edge {np.flatnonzero(bad)[0]}: "
            raise InputError(f"{where}information is not {what}")

    refuse(~np.isfinite(stack).all(axis=(1, 2)), "finite")
    scale = np.abs(stack).max(axis=(1, 2))
    refuse(np.abs(stack - np.swapaxes(stack, 1, 2)).max(axis=(1, 2)) > 1e-9 * scale, "symmetric")
    if semidefinite:
        refuse(_lowest_eigenvalues(stack) < -1e-9, "positive semi-definite")
    return info


def _parse(tok: list[str], where: str) -> tuple[list[int], np.ndarray]:
    """Integer ids and float values of a vertex (1 id, 7 values) or edge (2 ids, 28 values) line."""
    n_ids = {"VERTEX_SE3:QUAT": 1, "EDGE_SE3:QUAT": 2}.get(tok[0])
    if n_ids is None or len(tok) != 1 + n_ids + (7 if n_ids == 1 else 28):
        raise InputError(
            f"{where}: not a VERTEX_SE3:QUAT or EDGE_SE3:QUAT line with the right number of "
            f"values: {' '.join(tok)[:60]!r}"
        )
    ids = tok[1 : 1 + n_ids]
    # gtsam keys are unsigned 64-bit: it reads -1 as 2**64 - 1 and wraps larger ids, joining vertices we keep apart
    if not all(_ID.fullmatch(t) and int(t) < 2**64 for t in ids):
        raise InputError(f"{where}: vertex ids must be whole numbers in [0, 2**64): {' '.join(tok)[:60]!r}")
    try:
        return [int(t) for t in ids], np.array(tok[1 + n_ids :], dtype=float)
    except ValueError:
        raise InputError(f"{where}: malformed number in {' '.join(tok)[:60]!r}") from None


_ID = re.compile("[0-9]+")  # ASCII digits only: int() also takes "+1", "0_0" and other scripts' digits


def _text(path: Path) -> str:
    """The file's text: UTF-8 (a byte-order mark dropped), else Latin-1 (a comment in another encoding is still a
    comment; the numbers are ASCII either way). Devices (/dev/zero) and folders are refused: they never end."""
    try:
        if not path.is_file() and path.exists() and not path.is_fifo():
            raise InputError(f"cannot read g2o file {path}: not a regular file")
        raw = path.read_bytes()
    except OSError as exc:
        raise InputError(f"cannot read g2o file {path}: {exc}") from None
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        return raw.decode("latin-1")


def read_g2o(
    path: str | Path, positive_definite: bool = False, indefinite: bool = False
) -> tuple[list[int], np.ndarray | None, PoseGraph]:
    """Vertex ids (file order), their poses (N, 4, 4) and the edges as a ``PoseGraph`` (weight 1). A file without
    vertex lines (a run's graph_rejected.g2o: edges only, its scans may have no pose) gives the sorted ids its
    edges name, poses None, and an empty graph when it has no edges either; with ``positive_definite`` (a graph to
    optimize, as ``sync`` reads it) such a file is refused.

    ``FIX`` lines (gauge hints: ``fixed_ids``), blank lines and ``#`` comments are skipped; anything else that is not a
    well-formed vertex or edge (finite values, a non-zero quaternion, a symmetric positive semi-definite information
    matrix, positive definite with ``positive_definite``, between two different vertices that are defined) raises
    ``InputError`` naming the line. Repeated edges are kept. (The zero information of a failed registration in
    a run's graph_rejected.g2o is semi-definite.) With ``indefinite`` the information is not judged at all (the
    caller judges it by what its noise model needs: ``isotropic_ready``).
    """
    path = Path(path)
    lines = _text(path).split("\n")  # not splitlines: a form feed or \x1c inside a line does not end it for g2o
    ids: list[int] = []
    vertices: list[np.ndarray] = []
    vertex_lines: list[str] = []
    ends: list[tuple[int, int]] = []
    edges: list[np.ndarray] = []
    edge_lines: list[str] = []
    for line_no, line in enumerate(lines, start=1):
        tok = line.split()
        if not tok or tok[0].startswith("#") or tok[0] == "FIX":
            continue
        where = f"{path}: line {line_no}"
        keys, x = _parse(tok, where)
        if len(keys) == 1:
            ids.append(keys[0])
            vertices.append(x)
            vertex_lines.append(where)
        else:
            ends.append((keys[0], keys[1]))
            edges.append(x)
            edge_lines.append(where)
    poses = _poses(np.array(vertices), vertex_lines) if ids else None
    values = np.array(edges).reshape(-1, 28)
    T = _poses(values[:, :7], edge_lines)
    finite = np.all(np.isfinite(values[:, 7:]), axis=1)
    if not finite.all():
        raise InputError(f"{edge_lines[np.flatnonzero(~finite)[0]]}: information is not finite")
    E = len(ends)
    omega = np.zeros((E, 6, 6))
    omega[:, _UPPER[0], _UPPER[1]] = values[:, 7:]
    omega = omega + np.swapaxes(np.triu(omega, 1), 1, 2)
    if indefinite:
        bad = np.zeros(E, dtype=bool)
    else:
        bad = not_definite(omega) if positive_definite else _lowest_eigenvalues(omega) < -1e-9
    if bad.any():
        raise InputError(
            f"{edge_lines[np.flatnonzero(bad)[0]]}: information matrix is not positive "
            f"{'definite' if positive_definite else 'semi-definite'}"
        )
    information = omega[:, _G2O_TO_GTSAM][:, :, _G2O_TO_GTSAM]
    if not ids:
        if positive_definite:
            raise InputError(f"{path}: no VERTEX_SE3:QUAT lines")
        ids = sorted({v for edge in ends for v in edge})
    index = {v: k for k, v in enumerate(ids)}
    if len(index) != len(ids):
        seen: set[int] = set()
        again = next(k for k, v in enumerate(ids) if v in seen or seen.add(v))
        raise InputError(f"{vertex_lines[again]}: vertex {ids[again]} is defined a second time")
    for (a, b), where in zip(ends, edge_lines):
        if a not in index or b not in index:
            raise InputError(f"{where}: edge {a}-{b} refers to a vertex that is not defined")
        if a == b:
            raise InputError(f"{where}: edge {a}-{b} joins a vertex to itself")
    graph = PoseGraph(
        n=len(ids),
        i=np.array([index[a] for a, _ in ends], dtype=int).reshape(E),
        j=np.array([index[b] for _, b in ends], dtype=int).reshape(E),
        T=T,
        weight=np.ones(E),
        information=information,
    )
    return ids, poses, graph


def fixed_ids(path: str | Path) -> list[int]:
    """The vertex ids of a g2o file's ``FIX`` lines, in file order (``read_g2o`` skips those lines): the vertices a
    g2o optimizer holds at their input poses. Ids that are not whole numbers are ignored, as gtsam ignores them."""
    ids = []
    for line in _text(Path(path)).split("\n"):
        tok = line.split()
        if tok[:1] == ["FIX"]:
            ids.extend(int(t) for t in tok[1:] if _ID.fullmatch(t))
    return ids


def edge_line(path: str | Path, k: int) -> int | None:
    """The line number of the ``k``-th edge of a g2o file, counted as ``read_g2o`` counts lines; None past the last."""
    edges = (n for n, line in enumerate(_text(Path(path)).split("\n"), 1) if line.split()[:1] == ["EDGE_SE3:QUAT"])
    return next((n for e, n in enumerate(edges) if e == k), None)


def _pose_fields(T: np.ndarray) -> list[str]:
    """``x y z qx qy qz qw`` of each transform (E, 4, 4), formatted with ``repr`` (lossless)."""
    values = np.hstack([T[:, :3, 3], Rotation.from_matrix(T[:, :3, :3]).as_quat()])
    return [" ".join(map(repr, row)) for row in values.tolist()]


def write_g2o(
    path: str | Path, ids: list[int], poses: np.ndarray | None, graph: PoseGraph, indefinite: bool = False
) -> None:
    """Write vertices ``ids`` at ``poses`` and the measured edges, atomically; ``poses=None``: edges only
    (node ``k`` of ``graph`` written as ``ids[k]``).

    Without ``graph.information`` an edge's information is written as ``weight · I``. Numbers are written
    with ``repr`` so that reading the file back gives the same values. What ``read_g2o`` would refuse is refused
    before anything is written (``InputError``): ids that are not distinct integers, poses or edge transforms that
    are not finite rigid transforms, an edge that is not between two different nodes, information that is not
    finite, symmetric and positive semi-definite (any symmetric one with ``indefinite``: an input's information
    written back as it was given).
    """
    ids = list(ids)
    odd = [v for v in ids if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer))]
    if odd:
        raise InputError(f"write_g2o: vertex ids must be integers, got {odd[0]!r}")
    if len(set(ids)) != len(ids):
        raise InputError("write_g2o: duplicate vertex ids")
    n = len(ids)
    if (poses is not None and len(poses) != n) or n != graph.n:
        raise InputError(
            f"write_g2o: {n} ids, {'no' if poses is None else len(poses)} poses and {graph.n} graph nodes differ"
        )
    if poses is not None:
        if not n:
            raise InputError("write_g2o: no vertices to write (poses=None writes the edges alone)")
        poses = np.asarray(poses, dtype=float)
        if poses.shape != (n, 4, 4):
            raise InputError(f"write_g2o: poses must have shape ({n}, 4, 4), got {poses.shape}")
        check_rigid(poses, "write_g2o: pose")
    i, j, T = np.asarray(graph.i), np.asarray(graph.j), np.asarray(graph.T, dtype=float)
    E = len(i)
    if i.shape != (E,) or j.shape != (E,) or T.shape != (E, 4, 4):
        raise InputError(f"write_g2o: edge arrays disagree: i {i.shape}, j {j.shape}, T {T.shape}")
    if E and not (np.issubdtype(i.dtype, np.integer) and np.issubdtype(j.dtype, np.integer)):
        raise InputError("write_g2o: edge node indices must be integers")
    out = np.flatnonzero((i < 0) | (i >= n) | (j < 0) | (j >= n) | (i == j))
    if len(out):
        raise InputError(
            f"write_g2o: edge {out[0]} joins nodes {i[out[0]]} and {j[out[0]]}: not two different nodes of [0, {n})"
        )
    check_rigid(T, "write_g2o: edge")
    if graph.information is None:
        weight = np.asarray(graph.weight, dtype=float)
        if weight.shape != (E,) or not np.all(np.isfinite(weight) & (weight >= 0)):
            raise InputError(f"write_g2o: without information, the weights must be {E} finite values >= 0")
        info = weight[:, None, None] * np.eye(6)
    else:
        info = check_information(graph.information, E, semidefinite=not indefinite)
    back = np.argsort(_G2O_TO_GTSAM)
    upper = info[:, back][:, :, back][:, _UPPER[0], _UPPER[1]]
    with atomic_write(path) as f:
        for v, fields in zip(ids, [] if poses is None else _pose_fields(poses)):
            f.write(f"VERTEX_SE3:QUAT {v} {fields}\n")
        for a, b, fields, values in zip(i, j, _pose_fields(T), upper.tolist()):
            f.write(f"EDGE_SE3:QUAT {ids[a]} {ids[b]} {fields} {' '.join(map(repr, values))}\n")


def sesync_precisions(information: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SE-Sync's isotropic precisions ``(κ, τ)`` (E,) from information matrices in gtsam order.

    ``τ = 3 / tr(Ω_tt⁻¹)``, ``κ = 3 / (2 tr(Ω_rr⁻¹))`` (Rosen et al. 2019).
    """
    kappa = 3.0 / (2.0 * np.trace(np.linalg.inv(information[:, :3, :3]), axis1=1, axis2=2))
    tau = 3.0 / np.trace(np.linalg.inv(information[:, 3:, 3:]), axis1=1, axis2=2)
    return kappa, tau


def isotropic_information(information: np.ndarray) -> np.ndarray:
    """The gtsam information ``diag(2κ, 2κ, 2κ, τ, τ, τ)`` whose graph error is half the SE-Sync objective
    (to second order in the residuals: gtsam measures rotations on the manifold, SE-Sync by chords)."""
    kappa, tau = sesync_precisions(information)
    out = np.zeros((len(kappa), 6, 6))
    out[:, [0, 1, 2], [0, 1, 2]] = 2.0 * kappa[:, None]
    out[:, [3, 4, 5], [3, 4, 5]] = tau[:, None]
    return out


def sesync_objective(poses: np.ndarray, graph: PoseGraph) -> float:
    """SE-Sync's ``f = Σ κ‖R_j − R_i R̃_ij‖²_F + τ‖t_j − t_i − R_i t̃_ij‖²`` (no ½) at ``poses``, with κ, τ
    from ``graph.information``."""
    if graph.information is None:
        raise InputError("the SE-Sync objective needs the edges' information matrices")
    kappa, tau = sesync_precisions(graph.information)
    Ri, Rj = poses[graph.i, :3, :3], poses[graph.j, :3, :3]
    rot = np.sum((Rj - Ri @ graph.T[:, :3, :3]) ** 2, axis=(1, 2))
    trans = poses[graph.j, :3, 3] - poses[graph.i, :3, 3] - np.einsum("eab,eb->ea", Ri, graph.T[:, :3, 3])
    return float(np.sum(kappa * rot) + np.sum(tau * np.sum(trans**2, axis=1)))
