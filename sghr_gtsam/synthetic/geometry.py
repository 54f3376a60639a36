"""The geometry of the generated scenes: a furnished room and a bumpy object as meshes, the sensors spread
around them, and the ray casting that scans them (``synthetic.make_scene``); the building reuses the room, its
furniture and the sensor model (``synthetic.building``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import open3d as o3d

from sghr_gtsam.se3 import make_T


@dataclass
class SyntheticScene:
    """Scans in their own sensor frames and their ground-truth poses ``T_i`` (scene frame, metres)."""

    names: list[str]  # "scan_00.ply", ...: the file names ``write_scene`` gives with its default format
    scans: Sequence[np.ndarray]  # (N_i, 3) float64; a building's are ray-cast when read (``synthetic.building``)
    poses: np.ndarray  # (N, 4, 4) T_i: p_world = T_i @ p_scan
    voxel: float  # a voxel size suited to the scene's point spacing


@dataclass
class _Sensor:
    """Where the scans are taken from and how densely (a pinhole grid of rays)."""

    eyes: np.ndarray  # (N, 3) sensor centres
    targets: np.ndarray  # (N, 3) points the sensors look at
    fov_deg: tuple[float, float]  # horizontal, vertical
    grid: tuple[int, int]  # rays across, rays down
    max_roll: float  # radians; the roll about the viewing axis is uniform in [-max_roll, max_roll]


# --- geometry ------------------------------------------------------------------------------------


def _rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    return o3d.geometry.get_rotation_matrix_from_axis_angle(rng.normal(size=3))


def _box(size: Sequence[float], center: Sequence[float], R: np.ndarray | None = None) -> o3d.geometry.TriangleMesh:
    """A box of ``size`` centred at ``center``, rotated by ``R`` about its centre."""
    mesh = o3d.geometry.TriangleMesh.create_box(*size)
    mesh.translate(-np.asarray(size, dtype=float) / 2)
    if R is not None:
        mesh.rotate(R, center=np.zeros(3))
    return mesh.translate(center)


def _blob(rng: np.random.Generator, radius: float) -> o3d.geometry.TriangleMesh:
    """A closed irregular rock of about ``radius``, centred at the origin: the convex hull of random
    points (facets, edges and corners at varied angles), then bumps and dents at four scales.
    Smooth shapes are not enough: two views of a smooth blob slide onto each other."""
    points = rng.normal(size=(40, 3))
    points *= rng.uniform(0.75, 1.0, (40, 1)) / np.linalg.norm(points, axis=1, keepdims=True)
    hull, _ = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).compute_convex_hull()
    hull = hull.subdivide_midpoint(3)
    v = np.asarray(hull.vertices)
    u = v / np.linalg.norm(v, axis=1, keepdims=True)
    scale_r = np.ones(len(v))
    for width, count in ((0.5, 8), (0.25, 20), (0.12, 40), (0.07, 80)):
        centers = rng.normal(size=(count, 3))
        centers /= np.linalg.norm(centers, axis=1, keepdims=True)
        heights = rng.uniform(-0.5, 0.5, count) * width
        scale_r += (heights * np.exp(-((u[:, None] - centers[None]) ** 2).sum(-1) / (2 * width**2))).sum(1)
    hull.vertices = o3d.utility.Vector3dVector(v * (radius * scale_r)[:, None])
    return hull


def _relief_wall(
    corner: np.ndarray, a: np.ndarray, b: np.ndarray, rng: np.random.Generator, spacing: float = 0.08
) -> o3d.geometry.TriangleMesh:
    """The rectangle ``corner + s*a + t*b`` (s, t in [0, 1]) as a grid mesh with random relief (bumps
    and dents up to ~8 cm, 0.15-0.5 m wide) along its normal, fading to flat at the border so that
    adjacent walls still meet. Flat walls have identical FPFH descriptors everywhere; relief makes
    most of a scan's points distinctive."""
    la, lb = np.linalg.norm(a), np.linalg.norm(b)
    na, nb = max(int(la / spacing), 2) + 1, max(int(lb / spacing), 2) + 1
    s, t = np.meshgrid(np.linspace(0, 1, na), np.linspace(0, 1, nb), indexing="ij")
    uv = np.stack([s.ravel() * la, t.ravel() * lb], axis=1)
    count = int(la * lb * 6)
    centers = rng.uniform(0, 1, (count, 2)) * [la, lb]
    widths = rng.uniform(0.15, 0.5, count)
    heights = rng.uniform(-0.08, 0.08, count)
    d2 = ((uv[:, None, :] - centers[None]) ** 2).sum(-1)
    relief = (heights * np.exp(-d2 / (2 * widths**2))).sum(1)
    border = np.minimum.reduce([uv[:, 0], la - uv[:, 0], uv[:, 1], lb - uv[:, 1]])
    relief *= np.clip(border / 0.3, 0, 1)
    normal = np.cross(a, b) / (la * lb)
    vertices = corner + np.outer(uv[:, 0] / la, a) + np.outer(uv[:, 1] / lb, b) + np.outer(relief, normal)
    k = np.arange(na * nb).reshape(na, nb)[:-1, :-1].ravel()
    triangles = np.concatenate([np.stack([k, k + nb, k + 1], 1), np.stack([k + 1, k + nb, k + nb + 1], 1)])
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices), o3d.utility.Vector3iVector(triangles))


def _clutter(rng: np.random.Generator, size: float, base: np.ndarray) -> o3d.geometry.TriangleMesh:
    """One random object of about ``size`` standing on the point ``base``: a tilted box, a cone, a
    torus, a lying or standing cylinder, or a rock (varied shapes, so that local features differ)."""
    kind = rng.integers(5)
    if kind == 0:
        mesh = _box(rng.uniform(0.4, 1.0, 3) * size, np.zeros(3), _random_rotation(rng))
    elif kind == 1:
        mesh = o3d.geometry.TriangleMesh.create_cone(size * rng.uniform(0.3, 0.5), size, resolution=20)
    elif kind == 2:
        mesh = o3d.geometry.TriangleMesh.create_torus(size * 0.4, size * rng.uniform(0.1, 0.2), 20, 10)
        mesh.rotate(_random_rotation(rng), center=np.zeros(3))
    elif kind == 3:
        mesh = o3d.geometry.TriangleMesh.create_cylinder(size * rng.uniform(0.15, 0.3), size, resolution=20)
        mesh.rotate(_random_rotation(rng), center=np.zeros(3))
    else:
        mesh = _blob(rng, size / 2)
    lowest = np.asarray(mesh.vertices)[:, 2].min()
    return mesh.translate(base - [0.0, 0.0, lowest])


ROOM_SIZE = (5.0, 4.0, 2.5)
"""Metres: ``_room``'s length (x), width (y) and height (z)."""
DOOR_HEIGHT = 2.1


def _room(
    rng: np.random.Generator, door: tuple[float, float] | None = None, size: tuple[float, float, float] = ROOM_SIZE
) -> o3d.geometry.TriangleMesh:
    """A 5 x 4 x 2.5 m room (``size``; corners at (+-2.5, +-2, 0..2.5)) with uneven walls, furniture against
    them, a table with things on it in the middle, wall fixtures and clutter on the floor. Sizes,
    shapes, placements and angles are random, so that no local shape repeats exactly.
    ``door``: an opening from x = door[0] to door[1], ``DOOR_HEIGHT`` high, in the wall at y = -W/2, kept clear of
    furniture, fixtures and clutter; None (a closed room) draws the same random numbers as before doors existed."""
    L, W, H = size
    x, y, z = np.array([L, 0.0, 0.0]), np.array([0.0, W, 0.0]), np.array([0.0, 0.0, H])
    origin, far = np.array([-L / 2, -W / 2, 0.0]), np.array([L / 2, W / 2, H])
    mesh = o3d.geometry.TriangleMesh()
    walls = [(origin, x, y), (far, -x, -y), (origin, x, z), (far, -x, -z), (origin, y, z), (far, -y, -z)]
    if door is not None:  # the wall at y = -2 in three pieces around the opening
        ex, ez = x / L, z / H
        lo, hi = door[0] + L / 2, door[1] + L / 2
        walls[2:3] = [
            (origin, lo * ex, z),
            (origin + hi * ex, (L - hi) * ex, z),
            (origin + lo * ex + DOOR_HEIGHT * ez, (hi - lo) * ex, (H - DOOR_HEIGHT) * ez),
        ]

    def blocks_door(wall: int, along: float, half_width: float) -> bool:
        """Whether something ``half_width`` either side of ``along`` on ``wall`` stands in the doorway."""
        return (
            door is not None and wall == 3 and abs(along - sum(door) / 2) < (door[1] - door[0]) / 2 + half_width + 0.3
        )

    for corner, a, b in walls:  # floor, ceiling, four walls
        mesh += _relief_wall(corner, a, b, rng)
    for wall in range(4):
        normal_angle = wall * np.pi / 2  # the walls at +x, +y, -x, -y
        n = np.array([np.cos(normal_angle), np.sin(normal_angle), 0.0])
        t = np.array([-n[1], n[0], 0.0])
        dist, half_length = (L / 2, W / 2) if wall % 2 == 0 else (W / 2, L / 2)
        # Two pieces of furniture, not quite flush with the wall, sometimes with a step on top.
        for s in (np.array([-0.5, 0.5]) + rng.uniform(-0.15, 0.15, 2)) * half_length:
            depth, width, height = rng.uniform(0.3, 0.55), rng.uniform(0.5, 1.0), rng.uniform(0.4, 2.0)
            if blocks_door(wall, s, width / 2):
                continue
            center = n * (dist - depth / 2 - 0.05) + t * s + [0.0, 0.0, height / 2]
            R = _rot_z(normal_angle + rng.uniform(-0.2, 0.2))
            mesh += _box((depth, width, height), center, R)
            top = center + [0.0, 0.0, height / 2]
            if height < 1.2:
                mesh += _clutter(rng, rng.uniform(0.15, 0.35), top)
            elif rng.random() < 0.5:
                step = rng.uniform(0.1, 0.3)
                mesh += _box((depth * 0.8, width * 0.5, step), top + t * width / 5 + [0.0, 0.0, step / 2], R)
        # Wall fixtures: thin panels above the furniture (pictures, a clock, a radiator).
        for _ in range(2):
            w, h = rng.uniform(0.3, 0.9), rng.uniform(0.2, 0.6)
            along, up = rng.uniform(-0.8, 0.8) * half_length, rng.uniform(1.5, 2.2)
            if blocks_door(wall, along, w / 2):
                continue
            mesh += _box((0.06, w, h), n * (dist - 0.03) + t * along + [0.0, 0.0, up], _rot_z(normal_angle))
        # Things on the floor between the furniture and the sensors' loop.
        for _ in range(2):
            inset, along = rng.uniform(0.7, 0.85), rng.uniform(-0.7, 0.7) * half_length
            base = n * (dist - inset) + t * along
            size = rng.uniform(0.2, 0.35)
            if not blocks_door(wall, along, size):
                mesh += _clutter(rng, size, base)

    # A table (random size and angle, four legs) with things on it.
    tx, ty, th = rng.uniform(0.8, 1.2), rng.uniform(0.6, 0.9), rng.uniform(0.7, 0.8)
    R = _rot_z(rng.uniform(0, np.pi))
    mesh += _box((tx, ty, 0.05), (0.0, 0.0, th - 0.025), R)
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = R @ [sx * (tx / 2 - 0.05), sy * (ty / 2 - 0.05), 0.0]
            mesh += _box((0.05, 0.05, th), leg + [0.0, 0.0, th / 2])
    for _ in range(4):
        spot = R @ [rng.uniform(-0.35, 0.35) * tx, rng.uniform(-0.35, 0.35) * ty, 0.0]
        mesh += _clutter(rng, rng.uniform(0.1, 0.3), spot + [0.0, 0.0, th])
    return mesh


ROOM_PATH = (1.5, 1.1)
"""Semi-axes (x, y; metres) of the ellipse the room's sensors stand on, between the table and the furniture."""


def _room_sensors(n: int, rng: np.random.Generator) -> _Sensor:
    """Sensors on an ellipse between the table and the furniture (clear of both), at most 45 degrees
    apart (60 leaves some consecutive pairs at 30% overlap), each looking across the room towards a
    point near the centre, so consecutive views share the middle and part of the walls while the
    wall behind each sensor stays unseen."""
    angles = np.radians(min(360.0 / n, 45.0)) * np.arange(n) + rng.uniform(-0.08, 0.08, n)
    a, b = ROOM_PATH
    eyes = np.stack([a * np.cos(angles), b * np.sin(angles), rng.uniform(1.2, 1.7, n)], axis=1)
    targets = np.concatenate([rng.uniform(-0.3, 0.3, (n, 2)), rng.uniform(0.5, 1.0, (n, 1))], axis=1)
    # Roll kept small as for a scanner on a tripod: rolled 90 degrees, the wide field would look at
    # floor and ceiling instead of along the walls and consecutive views would overlap much less.
    return _Sensor(eyes, targets, fov_deg=(120.0, 80.0), grid=(150, 100), max_roll=0.4)


DEPTH_CAMERA = _Sensor(np.zeros((0, 3)), np.zeros((0, 3)), fov_deg=(58.0, 45.0), grid=(80, 60), max_roll=0.0)
"""One frame of a handheld depth camera (a Kinect's field of view, fewer rays): ``_fragment`` fuses many."""
FRAMES = 25
"""Depth frames fused into one fragment."""
TRAVEL = (0.2, 0.6)
"""How far (metres) the camera walks while it takes one fragment's frames, uniform in this range."""
SWEEP_DEG = 30.0
"""The camera turns from up to this far left of its start direction to as far right while it walks."""


def _fragment(
    scene: o3d.t.geometry.RaycastingScene,
    eye: np.ndarray,
    target: np.ndarray,
    voxel: float,
    noise: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """An RGB-D fragment: ``FRAMES`` depth frames of a camera that walks ``TRAVEL`` along the ellipse of
    ``_room_sensors`` (``ROOM_PATH``, clear of table and furniture) from ``eye`` while sweeping its view across
    ``target``, fused into the first frame's camera frame (as 3DMatch's fragments are) on a grid of half the scene's
    ``voxel``. Returns the points and the first frame's pose. Its frame's origin is one viewpoint of many: seen from
    there, surfaces that later frames saw around an object lie where the first frame saw nothing."""
    a, b = ROOM_PATH
    tangent = np.array([-eye[1] / b**2, eye[0] / a**2, 0.0])
    tangent *= rng.choice([-1.0, 1.0]) * rng.uniform(*TRAVEL) / np.linalg.norm(tangent)
    sweep = np.radians(rng.uniform(-SWEEP_DEG, SWEEP_DEG))
    points, first = [], None
    for s in np.linspace(0.0, 1.0, FRAMES):
        at, turn = eye + s * tangent, _rot_z(sweep * (2 * s - 1))
        T = _look_at(at, at + turn @ (target - eye), 0.0)
        first = T if first is None else first
        move = np.linalg.solve(first, T)
        points.append(_scan(scene, T, DEPTH_CAMERA, noise, rng) @ move[:3, :3].T + move[:3, 3])
    fused = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.concatenate(points))).voxel_down_sample(voxel / 2)
    return np.asarray(fused.points), first


def _object(rng: np.random.Generator) -> o3d.geometry.TriangleMesh:
    """A closed irregular object about 1 m across: a rock with smaller rocks, blocks and pegs stuck
    into it at random points of its surface. A lone rock is still round enough for a flipped view
    to fit it; the lopsided parts remove that, and their edges give FPFH something to see."""
    mesh = _blob(rng, 0.35)
    surface = np.asarray(mesh.vertices).copy()
    for k, center in enumerate(surface[rng.choice(len(surface), 10, replace=False)]):
        if k % 3 == 0:
            part = _blob(rng, rng.uniform(0.12, 0.22))
        elif k % 3 == 1:
            part = _box(rng.uniform(0.06, 0.25, 3), np.zeros(3), _random_rotation(rng))
        else:
            part = o3d.geometry.TriangleMesh.create_cylinder(rng.uniform(0.02, 0.06), rng.uniform(0.15, 0.4), 16)
            part.rotate(_random_rotation(rng), center=np.zeros(3))
        mesh += part.translate(center)  # centred on the surface: about half sticks out
    return mesh


def _object_sensors(n: int, rng: np.random.Generator) -> _Sensor:
    """Sensors on a rising spiral around the object (azimuth steps of at most 45 degrees, elevation
    -10 to 25 degrees, distance 1.8-2.6 m), looking near its centre. Larger steps leave consecutive
    views of a roundish object too different for FPFH."""
    angles = np.radians(min(360.0 / n, 45.0)) * np.arange(n) + rng.uniform(-0.1, 0.1, n)
    elevation = np.linspace(-0.17, 0.44, n) + rng.uniform(-0.05, 0.05, n)
    directions = np.stack(
        [np.cos(angles) * np.cos(elevation), np.sin(angles) * np.cos(elevation), np.sin(elevation)], axis=1
    )
    eyes = rng.uniform(1.8, 2.6, (n, 1)) * directions
    return _Sensor(eyes, rng.uniform(-0.15, 0.15, (n, 3)), fov_deg=(40.0, 40.0), grid=(220, 220), max_roll=np.pi)


# --- scanning ------------------------------------------------------------------------------------


def _look_at(eye: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    """Sensor pose T (scene <- sensor): z towards the target, then rolled about z, so that GT
    rotations are general, not just yaw and pitch."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=1) @ _rot_z(roll)
    return make_T(R, eye)


def _scan(
    scene: o3d.t.geometry.RaycastingScene, T: np.ndarray, sensor: _Sensor, noise: float, rng: np.random.Generator
) -> np.ndarray:
    """Ray-cast one scan from pose T; points in the sensor frame, range noise along each ray."""
    nx, ny = sensor.grid
    half_x, half_y = np.tan(np.radians(sensor.fov_deg) / 2)
    # Sub-pixel jitter so that no two scans sample the surface on the same grid.
    u = (np.arange(nx)[None, :] + rng.uniform(0, 1, (ny, nx))) / nx * 2 - 1
    v = (np.arange(ny)[:, None] + rng.uniform(0, 1, (ny, nx))) / ny * 2 - 1
    d = np.stack([u * half_x, v * half_y, np.ones_like(u)], axis=-1).reshape(-1, 3)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rays = np.concatenate([np.broadcast_to(T[:3, 3], d.shape), d @ T[:3, :3].T], axis=1).astype(np.float32)
    hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
    ok = np.isfinite(hit)
    ranges = hit[ok] + rng.normal(0.0, noise, ok.sum())
    return d[ok] * ranges[:, None]
