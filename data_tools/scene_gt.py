"""Ground truth of one scene as the outlier-graph generator uses it (``SceneGT``): a 3DMatch test scene read from
the shared data (``load_scene``) or, made by ``data_tools.building``, a generated building; and where a model's
scans went against it (``placement_groups``)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np

from sghr_gtsam.io.poses import read_gt_info, read_gt_log, read_gt_overlap, read_poses
from sghr_gtsam.se3 import inv_T, project_to_so3, rotation_angle


@dataclass
class SceneGT:
    """Ground truth of one scene (a 3DMatch test scene or a generated building), indexed by graph node."""

    name: str  # seeds the corruption's random streams
    ids: list[int]  # fragment number of each node (the names gt_log and gt_info use)
    poses: np.ndarray  # (N, 4, 4) GT T_i, rotations projected to SO(3)
    overlap: np.ndarray  # (N, N) symmetric GT overlap, 0 on the diagonal
    vertical: np.ndarray  # (3,) unit vertical axis in the world frame (sign arbitrary)
    gt_log: dict[tuple[int, int], np.ndarray]  # fragment pair -> T_ij, for evaluate.registration_recall
    gt_info: dict[tuple[int, int], np.ndarray]  # fragment pair -> 6×6 information, order [translation, rotation]


def data_root() -> Path:
    """The shared data: ``$SGHR_DATA`` or ``../shared/data`` beside the repository (the default of the tests and
    the benchmarks)."""
    return Path(os.environ.get("SGHR_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))


def log_overlaps(path: Path, ids: list[int]) -> np.ndarray:
    """(N, N) symmetric GT overlaps of the fragments numbered ``ids`` from a 3DMatch ``gt_overlap.log`` (0 on the
    diagonal and for pairs it does not list)."""
    index = {f: k for k, f in enumerate(ids)}
    overlap = np.zeros((len(ids), len(ids)))
    for (a, b), v in read_gt_overlap(path).items():
        if a in index and b in index:
            overlap[index[a], index[b]] = overlap[index[b], index[a]] = v
    return overlap


@cache
def load_scene(scene: str, root: Path | None = None) -> SceneGT:
    """Read one scene's GT; cached, so callers must not modify the arrays."""
    base = (root or data_root()) / "3dmatch-test-gt"
    names, P = read_poses(base / "derived_abs_poses" / f"{scene}.txt")
    keep = np.isfinite(P).all(axis=(1, 2))
    ids = [int(name) for name, k in zip(names, keep) if k]
    poses = P[keep]
    poses[:, :3, :3] = project_to_so3(poses[:, :3, :3])

    overlap = log_overlaps(base / "3DMatch" / scene / "gt_overlap.log", ids)

    positions = poses[:, :3, 3] - poses[:, :3, 3].mean(axis=0)
    vertical = np.linalg.eigh(positions.T @ positions)[1][:, 0]
    scene_dir = base / "3DMatch" / scene
    return SceneGT(
        scene, ids, poses, overlap, vertical, read_gt_log(scene_dir / "gt.log"), read_gt_info(scene_dir / "gt.info")
    )


def placement_groups(poses: np.ndarray, truth: np.ndarray, ids: list[int]) -> list[str]:
    """Where the scans went: scans whose correction ``T_est T_gt⁻¹`` agrees (5° / 0.2 m at their positions)
    form one rigidly placed group, largest first; each as 'count: fragment ranges (rotation of the group
    relative to the largest one)'."""
    G = poses @ inv_T(truth)
    left = list(range(len(ids)))
    groups = []
    while left:
        s = max(left, key=lambda k: sum(_same(G[k], G[m], truth[m]) for m in left))
        members = [m for m in left if _same(G[s], G[m], truth[m])]
        groups.append((s, members))
        left = [m for m in left if m not in members]
    out = []
    for s, members in groups:
        turn = np.degrees(rotation_angle(G[s][:3, :3] @ G[groups[0][0]][:3, :3].T))
        out.append(f"{len(members)}: {_ranges([ids[m] for m in members])} ({turn:.0f}°)")
    return out


def _same(A: np.ndarray, B: np.ndarray, T: np.ndarray) -> bool:
    D = A @ inv_T(B)
    angle = np.degrees(rotation_angle(D[:3, :3]))
    return bool(angle <= 5.0 and np.linalg.norm((D @ T)[:3, 3] - T[:3, 3]) <= 0.2)


def _ranges(values: list[int]) -> str:
    values = sorted(values)
    out, start = [], values[0]
    for a, b in zip(values, values[1:] + [None]):
        if b != a + 1:
            out.append(f"{start}" if start == a else f"{start}–{a}")
            start = b
    return " ".join(out)
