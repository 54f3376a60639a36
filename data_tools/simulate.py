"""Simulated multiview scans for training the overlap head (never the real scans: those are evaluation data).

A scene is a procedurally generated mesh ray-cast (open3d ``RaycastingScene``) from 8–60 viewpoints, so every
scan is a partial, self-occluded view with range noise, and its GT pose is known. The mesh pieces and the
ray caster are ``sghr_gtsam.synthetic``'s (``_room``, ``_object``, ``_clutter``, ``_look_at``, ``_scan``);
what training needs on top of the demo's scenes:

- **Rooms** (3DMatch-like): the demo room stretched to 4–9 m × 3.2–6.4 m × 2.4–3 m with 0–8 extra pieces of
  clutter; a hand-held sensor walks a random path through the free space (steps of 0.1–0.6 m, heading changing
  by ~20° a step, now and then a jump to a new place), looking 35° down to 9° up, field of view 60–100°, rays
  every ~0.3° and ranges cut at 4.5 m (a depth camera). Range noise 2–6 mm. Scans in the sensor frame (as
  3DMatch fragments are in their camera frame).
- **Objects** (Stanford-like): the demo's lumpy object seen from a random walk on the sphere of directions
  (steps of 10–60°, sometimes a jump), 1.8–2.8 m away, any roll, 40° field of view. Half the scenes express
  the scans in an object-centred frame (origin near the object's centre, random orientation) as the Stanford
  scans are, which flips the side FPFH's normals face (``compute_features`` orients them towards the origin).

Consecutive views overlap strongly and far-apart ones not at all, so the pairs' overlaps span 0..1.
Point densities match the real fragments at the pipeline's voxel (``default_voxel``: 1/100 of the median
scan's diagonal): the shipped head's 1663 scans have a median of 4.5k voxel-grid points (5 % under 1.6k;
kitchen: 4.3–7.5k, bunny: 4.0–4.8k); raw scans have 8k–90k points (real fragments: 15k–314k).

``make_training_scene`` returns the scans, poses and GT overlaps (``data_tools.gt_overlap``, kitchen
calibration scaled to the scene's voxel: radius 0.72 voxel on a 0.24-voxel grid, symmetric mean);
``make_turntable`` is an evaluation scene, not training data: an object turned in equal steps in front of one
sensor (``benchmarks/bench_turntable.py``). ``cache_dataset`` adds FPFH descriptors
(``sghr_gtsam.features.local.compute_features`` at the scene's voxel)
and writes one file per scene in the form ``sghr_gtsam.train`` reads. Command line (resumable: scenes already
in the folder are kept)::

    python -m data_tools.simulate CACHE_DIR --scenes 60 --seed 0 --jobs 2
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import open3d as o3d

from data_tools.gt_overlap import combine, directed_overlap_matrix, relative_params
from sghr_gtsam.features.local import compute_features, default_voxel
from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.synthetic.geometry import (
    SyntheticScene,
    _clutter,
    _look_at,
    _object,
    _random_rotation,
    _room,
    _scan,
    _Sensor,
)

KINDS = ("room", "object")
MIN_SCANS, MAX_SCANS = 8, 60
MAX_DESCRIPTORS = 5000  # per scan in the cache: the largest beta (keypoints a scan) training draws
MIN_POINTS = 2500  # a view with fewer points (a wall right in front of the sensor) is taken again
MIN_ROOM_EXTENT = 2.0  # m, bounding-box diagonal of a room scan (the kitchen fragments': 3-5 m)
LABEL_QUERIES = 2000  # query points a scan for the GT overlap labels (std. error <= 0.011)


@dataclass
class TrainingScene:
    kind: str
    scans: list[np.ndarray]  # (P_i, 3) in each scan's own frame
    poses: np.ndarray  # (N, 4, 4): p_world = poses[i] @ p_scan
    voxel: float  # the pipeline's default voxel for these scans
    directed: np.ndarray  # (N, N): fraction of scan i's points with a neighbour in scan j
    overlap: np.ndarray  # (N, N): symmetric GT overlap (mean of both directions), diagonal 1


def _raycaster(mesh: o3d.geometry.TriangleMesh) -> o3d.t.geometry.RaycastingScene:
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene


# --- rooms --------------------------------------------------------------------------------------------------


def _training_room(rng: np.random.Generator) -> tuple[o3d.geometry.TriangleMesh, np.ndarray]:
    """The demo room (5 x 4 x 2.5 m) stretched per axis, with extra clutter; returns it and its half size."""
    mesh = _room(rng)
    scale = np.array([rng.uniform(0.8, 1.8), rng.uniform(0.8, 1.6), rng.uniform(0.95, 1.2)])
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * scale)
    half = np.array([2.5, 2.0, 2.5]) * scale * [1, 1, 0.5]
    for _ in range(rng.integers(0, 9)):
        base = np.r_[rng.uniform(-1, 1, 2) * (half[:2] - 0.6), 0.0]
        mesh += _clutter(rng, rng.uniform(0.2, 0.6), base)
    return mesh, half


def _free(scene: o3d.t.geometry.RaycastingScene, eye: np.ndarray, ceiling: float) -> bool:
    """Clear of every surface by 0.3 m and under open ceiling (not inside furniture)."""
    p = o3d.core.Tensor(eye[None].astype(np.float32))
    if scene.compute_distance(p).numpy()[0] < 0.3:
        return False
    up = o3d.core.Tensor(np.r_[eye, 0.0, 0.0, 1.0][None].astype(np.float32))
    return eye[2] + scene.cast_rays(up)["t_hit"].numpy()[0] > ceiling - 0.15


def _room_poses(
    n: int, scene: o3d.t.geometry.RaycastingScene, half: np.ndarray, rng: np.random.Generator
) -> list[tuple[np.ndarray, float]]:
    """Sensor poses along a random walk; each with an orientation drawn later (see ``_room_views``)."""
    lo = np.r_[-half[:2] + 0.5, 1.0]
    hi = np.r_[half[:2] - 0.5, min(1.9, 2 * half[2] - 0.4)]
    ceiling = 2 * half[2]

    def anywhere() -> np.ndarray:
        for _ in range(200):
            eye = rng.uniform(lo, hi)
            if _free(scene, eye, ceiling):
                return eye
        raise RuntimeError("no free place for the sensor")

    eye, yaw, out = anywhere(), rng.uniform(0, 2 * np.pi), []
    for k in range(n):
        if k and rng.random() < 0.08:
            eye, yaw = anywhere(), rng.uniform(0, 2 * np.pi)
        elif k:
            for _ in range(50):
                heading = yaw + rng.normal(0, 0.8)
                step = rng.uniform(0.1, 0.6) * np.array([np.cos(heading), np.sin(heading), 0.0])
                step[2] = rng.normal(0, 0.08)
                candidate = np.clip(eye + step, lo, hi)
                if _free(scene, candidate, ceiling):
                    eye = candidate
                    break
            yaw += rng.normal(0, 0.35)
        out.append((eye.copy(), yaw))
    return out


def _room_scans(n: int, rng: np.random.Generator) -> tuple[list[np.ndarray], np.ndarray]:
    mesh, half = _training_room(rng)
    scene = _raycaster(mesh)
    noise = rng.uniform(0.002, 0.006)
    scans, poses = [], []
    for eye, yaw in _room_poses(n, scene, half, rng):
        for attempt in range(10):
            look = yaw + (rng.normal(0, 0.6) if attempt else 0.0)
            pitch = rng.uniform(-0.6, 0.15)
            d = np.array([np.cos(pitch) * np.cos(look), np.cos(pitch) * np.sin(look), np.sin(pitch)])
            T = _look_at(eye, eye + d, rng.normal(0, 0.1))
            h = rng.uniform(60.0, 100.0)
            v = h * rng.uniform(0.65, 0.8)
            sensor = _Sensor(eye[None], (eye + d)[None], (h, v), (int(h / 0.3), int(v / 0.3)), 0.0)
            P = _scan(scene, T, sensor, noise, rng)
            P = P[np.linalg.norm(P, axis=1) < 4.5]
            if len(P) >= MIN_POINTS and np.linalg.norm(np.ptp(P, axis=0)) >= MIN_ROOM_EXTENT:
                break
        scans.append(P)
        poses.append(T)
    return scans, np.stack(poses)


# --- objects ------------------------------------------------------------------------------------------------


def _rotate_towards(u: np.ndarray, angle: float, rng: np.random.Generator) -> np.ndarray:
    """Unit vector ``angle`` radians away from unit ``u`` in a random direction."""
    w = rng.normal(size=3)
    w -= w.dot(u) * u
    w /= np.linalg.norm(w)
    return np.cos(angle) * u + np.sin(angle) * w


def _object_scans(n: int, rng: np.random.Generator) -> tuple[list[np.ndarray], np.ndarray]:
    mesh = _object(rng)
    scene = _raycaster(mesh)
    noise = rng.uniform(0.0005, 0.002)
    centred = rng.random() < 0.5
    direction = rng.normal(size=3)
    direction /= np.linalg.norm(direction)
    scans, poses = [], []
    for k in range(n):
        if k and rng.random() < 0.15:
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
        elif k:
            direction = _rotate_towards(direction, np.radians(rng.uniform(10, 60)), rng)
        for _ in range(10):
            eye = rng.uniform(1.8, 2.8) * direction
            target = rng.uniform(-0.15, 0.15, 3)
            if abs(np.dot(target - eye, [0, 0, 1])) > 0.999 * np.linalg.norm(target - eye):
                target = target + [0.05, 0.0, 0.0]  # _look_at needs a view off the vertical
            T = _look_at(eye, target, rng.uniform(-np.pi, np.pi))
            P = _scan(scene, T, _Sensor(eye[None], target[None], (40.0, 40.0), (300, 300), 0.0), noise, rng)
            if len(P) >= MIN_POINTS:
                break
        if centred:  # the scan in a frame near the object's centre, as the Stanford scans are
            frame = make_T(_random_rotation(rng), rng.uniform(-0.05, 0.05, 3))
            world = P @ T[:3, :3].T + T[:3, 3]
            local = inv_T(frame)
            P, T = world @ local[:3, :3].T + local[:3, 3], frame
        scans.append(P)
        poses.append(T)
    return scans, np.stack(poses)


def make_turntable(
    n_scans: int, seed: int = 0, noise: float = 0.001, elevation_deg: float = 20.0, distance: float = 2.2
) -> SyntheticScene:
    """An object on a turntable: ``n_scans`` range scans ``360 / n_scans`` degrees apart, as one fixed sensor sees
    the demo's lumpy object (``synthetic.geometry._object``, ~1 m across) turned in equal steps. In the object's frame
    the
    sensor moves on a horizontal circle of radius ``distance`` · cos(elevation), ``elevation_deg`` above the
    turntable's centre, looking at that centre with no roll; 40° field of view, 220 × 220 rays with sub-ray jitter,
    Gaussian range noise of std ``noise`` m (1 mm: the middle of the training objects' 0.5–2 mm). Scans in the
    sensor frame, ``poses[i]`` the GT sensor pose in the object frame; the object and the turntable's start angle
    depend on ``seed``. Returns a ``synthetic.SyntheticScene`` (voxel 2 cm as ``make_scene``'s objects)."""
    if n_scans < 2:
        raise ValueError("a turntable needs at least 2 scans")
    rng = np.random.default_rng(seed)
    mesh = _object(rng)
    angles = rng.uniform(0, 2 * np.pi) + 2 * np.pi * np.arange(n_scans) / n_scans
    e = np.radians(elevation_deg)
    eyes = distance * np.stack([np.cos(angles) * np.cos(e), np.sin(angles) * np.cos(e), np.full(n_scans, np.sin(e))], 1)
    sensor = _Sensor(eyes, np.zeros((n_scans, 3)), fov_deg=(40.0, 40.0), grid=(220, 220), max_roll=0.0)
    poses = np.stack([_look_at(eye, np.zeros(3), 0.0) for eye in eyes])
    scene = _raycaster(mesh)
    scans = [_scan(scene, T, sensor, noise, rng) for T in poses]
    return SyntheticScene([f"scan_{k:02d}" for k in range(n_scans)], scans, poses, 0.02)


# --- scenes and the cache -----------------------------------------------------------------------------------


def make_training_scene(kind: str, n_scans: int, seed: int | list[int]) -> TrainingScene:
    """A scene of ``kind`` seen by ``n_scans`` scans, with its GT overlaps; deterministic for a seed."""
    if kind not in KINDS:
        raise ValueError(f"unknown scene kind {kind!r} ({', '.join(KINDS)})")
    if n_scans < 2:
        raise ValueError("a scene needs at least 2 scans")
    rng = np.random.default_rng(seed)
    scans, poses = (_room_scans if kind == "room" else _object_scans)(n_scans, rng)
    voxel = default_voxel(scans)
    radius, grid = relative_params(voxel)
    directed = directed_overlap_matrix(
        scans, poses, radius, grid, max_points=LABEL_QUERIES, seed=int(rng.integers(2**31))
    )
    return TrainingScene(kind, scans, poses, voxel, directed, combine(directed, "mean"))


def scene_descriptors(scene: TrainingScene, seed: int = 0, max_points: int = MAX_DESCRIPTORS) -> list[np.ndarray]:
    """FPFH of every scan at the scene's voxel (``compute_features``, the pipeline's own descriptors),
    at most ``max_points`` a scan (a seeded random subset)."""
    rng = np.random.default_rng(seed)
    out = []
    for P in scene.scans:
        d = compute_features(P, scene.voxel).fpfh
        if len(d) > max_points:
            d = d[np.sort(rng.choice(len(d), max_points, replace=False))]
        out.append(d)
    return out


def scene_plan(index: int, seed: int, object_fraction: float = 0.4) -> tuple[str, int, list[int]]:
    """Kind, scan count and seed of scene ``index`` of a dataset: a function of (seed, index) only, so a
    dataset is the same however it is split into runs or jobs."""
    rng = np.random.default_rng([seed, index])
    kind = "object" if rng.random() < object_fraction else "room"
    return kind, int(rng.integers(MIN_SCANS, MAX_SCANS + 1)), [seed, index, 1]


def _cache_one(args: tuple[Path, int, int, float]) -> tuple[int, str, int, float]:
    from sghr_gtsam.train import cache_path, write_cache_scene

    folder, index, seed, object_fraction = args
    t0 = time.perf_counter()
    kind, n, scene_seed = scene_plan(index, seed, object_fraction)
    scene = make_training_scene(kind, n, scene_seed)
    desc = scene_descriptors(scene, seed=index)
    write_cache_scene(
        cache_path(folder, index),
        desc,
        scene.overlap,
        directed=scene.directed,
        poses=scene.poses,
        voxel=scene.voxel,
        kind=kind,
    )
    return index, kind, n, time.perf_counter() - t0


def cache_dataset(
    folder: str | Path, scenes: int, seed: int = 0, jobs: int = 1, object_fraction: float = 0.4, progress: bool = True
) -> list[Path]:
    """Simulate scenes 0 .. ``scenes``-1 of dataset ``seed`` and cache their descriptors and GT overlaps in
    ``folder`` (one ``scene_XXXXX.npz`` each, written atomically; those already there are kept)."""
    from tqdm import tqdm

    from sghr_gtsam.train import cache_path

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    todo = [(folder, k, seed, object_fraction) for k in range(scenes) if not cache_path(folder, k).exists()]
    bar = tqdm(total=len(todo), desc="simulate + FPFH", unit="scene", disable=not progress)
    if jobs > 1 and len(todo) > 1:
        # open3d reads OMP_NUM_THREADS when it is imported: one thread a worker, the workers in parallel.
        os.environ["OMP_NUM_THREADS"] = "1"
        with mp.get_context("spawn").Pool(jobs) as pool:
            for index, kind, n, seconds in pool.imap_unordered(_cache_one, todo):
                bar.set_postfix_str(f"#{index} {kind} {n} scans {seconds:.0f} s")
                bar.update()
    else:
        for item in todo:
            index, kind, n, seconds = _cache_one(item)
            bar.set_postfix_str(f"#{index} {kind} {n} scans {seconds:.0f} s")
            bar.update()
    bar.close()
    return [cache_path(folder, k) for k in range(scenes)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="Simulate training scenes and cache their FPFH descriptors and GT overlaps for sghr_gtsam.train."
    )
    parser.add_argument("cache_dir", type=Path, help="where the scene files go (outside the repository)")
    parser.add_argument("--scenes", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--object-fraction", type=float, default=0.4)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    cache_dataset(args.cache_dir, args.scenes, args.seed, args.jobs, args.object_fraction)
    print(f"{args.scenes} scenes in {args.cache_dir} ({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
