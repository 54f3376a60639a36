"""Small registrable scenes with known poses, for ``python -m sghr_gtsam demo`` and data-free tests.

A scene is a procedurally generated mesh (a furnished room, or one bumpy closed object) that is
ray-cast from sensors spread along a path around it, so consecutive scans overlap well while each
one sees only part of the scene. Every scan is expressed in its own sensor frame; ``poses[i]`` is
the sensor's pose in the scene frame (``p_world = poses[i] @ p_scan``), so even the first pose is
not the identity.
Sensor frame: z forward along the central ray, x right, y down (camera convention).

Tuned so that FPFH + RANSAC + ICP at ``scene.voxel`` registers consecutive scans, provided the normals
are oriented towards each scan's origin (the sensor): with open3d's unoriented normals the FPFH
descriptors of one surface differ between scans and a quarter of the room's pairs fail.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import open3d as o3d

from sghr_gtsam.errors import InputError
from sghr_gtsam.io.poses import read_poses, write_poses
from sghr_gtsam.io.scans import write_scan
from sghr_gtsam.synthetic.building import make_building
from sghr_gtsam.synthetic.geometry import (
    SyntheticScene,
    _fragment,
    _look_at,
    _object,
    _object_sensors,
    _room,
    _room_sensors,
    _scan,
)

KINDS = ("room", "object", "fragments")
"""The kinds of one mesh scanned from around it; ``SCENE_KINDS`` adds the buildings (``synthetic.building``)."""
SCENE_KINDS = (*KINDS, "building", "hotel")


def make_scene(kind: str = "room", n_scans: int = 6, seed: int = 0, noise: float = 0.003) -> SyntheticScene:
    """Generate a scene of ``kind`` ("room": ~5 m furnished room, voxel 5 cm; "object": ~1 m bumpy object, voxel
    2 cm; "fragments": the room seen by a handheld depth camera, each scan fused from the frames of a short walk, in
    its first frame's camera frame, as RGB-D fragments are (``geometry._fragment``); "building": rooms along
    corridors growing with ``n_scans``, at least 9; "hotel": the building with every room the same,
    ``synthetic.building``) seen by ``n_scans`` sensors, with Gaussian range noise of std ``noise`` metres. About
    5-15k points a scan (fragments: more); well under a second for 6 scans; deterministic for a given seed."""
    if kind not in SCENE_KINDS:
        raise ValueError(f"unknown scene kind {kind!r} (choose from {', '.join(SCENE_KINDS)})")
    if n_scans < 2:
        raise ValueError("a scene needs at least 2 scans")
    if not (np.isfinite(noise) and noise >= 0):  # a NaN noise made every point NaN, silently
        raise ValueError(f"noise must be a finite number >= 0; got {noise!r}")
    if kind not in KINDS:
        return make_building(n_scans, seed, noise, identical_rooms=kind == "hotel")
    rng = np.random.default_rng(seed)
    if kind in ("room", "fragments"):
        mesh, sensor, voxel = _room(rng), _room_sensors(n_scans, rng), 0.05
    else:
        mesh, sensor, voxel = _object(rng), _object_sensors(n_scans, rng), 0.02
    raycaster = o3d.t.geometry.RaycastingScene()
    raycaster.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))

    if kind == "fragments":
        scans, poses = zip(
            *(_fragment(raycaster, e, t, voxel, noise, rng) for e, t in zip(sensor.eyes, sensor.targets))
        )
        return SyntheticScene([f"scan_{k:02d}.ply" for k in range(n_scans)], list(scans), np.stack(poses), voxel)
    rolls = rng.uniform(-sensor.max_roll, sensor.max_roll, len(sensor.eyes))
    poses = np.stack([_look_at(e, t, roll) for e, t, roll in zip(sensor.eyes, sensor.targets, rolls)])
    scans = [_scan(raycaster, T, sensor, noise, rng) for T in poses]
    return SyntheticScene([f"scan_{k:02d}.ply" for k in range(n_scans)], scans, poses, voxel)


def write_scene(scene: SyntheticScene, folder: str | Path, formats: Sequence[str] = ("ply",)) -> list[Path]:
    """Write the scans to ``folder`` (created if needed) and ``gt_poses.txt`` naming the written files.

    Scan k is written as ``formats[k % len(formats)]`` (suffixes from ``SCAN_SUFFIXES`` without the
    dot; the format replaces the suffix of ``scene.names[k]``), so e.g. ``("ply", "npy", "xyz")``
    exercises several readers. Returns the scan paths.
    """
    if not formats:
        raise ValueError("formats must name at least one scan format")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = [
        folder / Path(name).with_suffix("." + formats[k % len(formats)].lstrip(".")).name
        for k, name in enumerate(scene.names)
    ]
    for path, points in zip(paths, scene.scans):
        write_scan(path, points)
    write_poses(
        folder / GT_POSES,
        [p.name for p in paths],
        scene.poses,
        comment=_GT_COMMENT,
    )
    return paths


GT_POSES = "gt_poses.txt"
_GT_COMMENT = "Synthetic scene (sghr_gtsam.synthetic). Per scan: its file name, then T with p_world = T @ p_scan."


def written_scene(folder: str | Path) -> bool:
    """Whether ``folder`` holds only what ``write_scene`` wrote: its ``gt_poses.txt`` (told by its comment) and
    regular files it names. The demo replaces such a folder and nothing else (a user's scans or notes put in it
    would be lost)."""
    folder = Path(folder)
    poses = folder / GT_POSES
    try:
        if poses.is_symlink() or not poses.is_file():  # never open a pipe
            return False
        with open(poses, encoding="utf-8") as f:
            if f.readline().rstrip("\n") != f"# {_GT_COMMENT}":
                return False
        names = set(read_poses(poses)[0]) | {GT_POSES}
        return all(p.name in names and p.is_file() and not p.is_symlink() for p in folder.iterdir())
    except (OSError, UnicodeDecodeError, InputError):
        return False
