"""Generated ground truth for large pose graphs: a hand-held depth camera walking through one floor of a building.

``make_building(n, seed)`` returns a ``data_tools.scene_gt.SceneGT`` (named ``gen<n>``) that the
robustness benchmark corrupts exactly as it corrupts the real 3DMatch scenes; only GT is made, no point clouds
beyond the samples that measure overlap.

- **Floor**: a grid of rooms 3.5–6 m a side, 2.5–3 m high, in blocks of two room rows with a corridor
  (1.8–2.4 m wide, open along its length) between them; about one room per 25 scans (``SCANS_PER_ROOM``):
  200 scans walk through 6 rooms and a corridor (3 × 3 cells, ~13 × 12 m), 1,000 through 32 rooms and two
  corridors (8 × 6 cells, ~39 × 20 m, seed 0). Every room has a door (0.9–1.2 m) to the corridor with
  probability 0.7 and to each neighbouring room with probability 0.25, plus the doors of a random spanning
  tree, so the floor is connected and has loops of several rooms.
- **Walk**: from cell to cell through the doors, preferring cells visited least and not going straight back,
  via 0–2 random points inside each cell (0.7 m from its walls); a scan every 0.2–0.4 m along the path (the real
  scenes' median step is 0.25–0.32 m), with 5 cm of hand jitter. A cell is typically seen again after a long
  detour, so the graph has long cycles instead of being one dense blob.
- **Camera** (3DMatch's frame: x right, y down, z forward): 1.2–1.8 m high, the body turning towards the
  walk's direction by at most 20° a scan, plus a slowly wandering look-around offset (stationary sd ~23°),
  pitch −10° ± 8°, roll ± 3°; depth 0.5–3.5 m. The field of view is 80° × 60°, wider than one depth frame,
  because a 3DMatch fragment fuses 50 frames of a moving camera: with 60° × 47°, 2 % of the top-10 edges
  joined scans with no overlap at all, and ``top_k_edges`` breaks those ties towards scans 0–9, a hub of
  true long-range edges (80° × 60°: 0.1–0.8 %; the real scenes: 0–0.6 % in six of eight, 1.9 % in
  mit_lab_hj, 13 % in hotel_umd3). A view that sees a surface on fewer than half its rays
  (a wall in front of the camera) is turned away and taken again. On 200 scans this reads like the real
  scenes: median step 0.30 m and 17° (real 0.25–0.32 m, 13–23°), consecutive overlap 0.59 (0.50–0.69),
  12.0 edges a scan in the top-10 graph (11.5–12.7).
- **Scan points**: ``POINTS`` rays a scan at random pixels, cast (open3d) onto the walls, floor and ceiling;
  the hits within the depth range are the scan's surface samples.
- **Overlap** ``o(i → j)``: the fraction of scan i's points inside j's frustum and not hidden from j's camera by
  a wall; the symmetric overlap is the mean of both directions (``gt_overlap.combine``), 0 on the diagonal.
- **gt.log pairs**: every pair with overlap > 0.3 (3DMatch's rule), ``T_ij = inv(T_i) @ T_j``; the 6×6
  information as 3DMatch's gt.info: ``Σ_p GᵀG`` with ``G = [I, −[p]×]`` over the overlapping points p in
  scan i's frame (i's points that j sees and j's points that i sees), order [translation, rotation], so
  ``Info[0, 0]`` is their count. The 3DMatch files fit exactly this form (the kitchen pairs'
  ``Info[0, 4] / Info[0, 0]`` is the mean depth of the overlapping points, 2.2–2.5 m, as measured on
  fragments 0–3): ``evaluate.registration_recall`` applies it to ``[t, q.xyz]``.

Everything depends on (n, seed) only; ``make_building`` is cached, so callers must not modify the arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import open3d as o3d

from data_tools.gt_overlap import combine
from data_tools.scene_gt import SceneGT
from sghr_gtsam.se3 import inv_T, make_T

SCANS_PER_ROOM = 25
ROOM_SIDE = (3.5, 6.0)  # metres
CORRIDOR_WIDTH = (1.8, 2.4)
HEIGHT = (2.5, 3.0)
DOOR_WIDTH = (0.9, 1.2)
P_CORRIDOR_DOOR, P_ROOM_DOOR = 0.7, 0.25
WALL_MARGIN = 0.7  # metres between a walk's interior point and a wall
STEP = (0.2, 0.4)  # metres between scans
JITTER = 0.05
MAX_TURN = np.radians(20.0)  # of the walker's body between scans
CAMERA_HEIGHT = (1.2, 1.8)
HEIGHT_KEEP, HEIGHT_STEP = 0.95, 0.03  # AR(1) about 1.5 m: stationary sd 0.1 m, clipped to CAMERA_HEIGHT
LOOK_KEEP, LOOK_STEP = 0.9, np.radians(10.0)  # look-around offset: AR(1), stationary sd 10°/√(1−0.9²) ≈ 23°
PITCH, PITCH_SD, ROLL_SD = np.radians(-10.0), np.radians(8.0), np.radians(3.0)
FOV_X, FOV_Y = np.radians(80.0), np.radians(60.0)
DEPTH = (0.5, 3.5)
POINTS = 1200  # rays a scan
MIN_SEEN = 0.5  # share of a scan's rays that must hit a surface in the depth range
OCCLUSION_SLACK = 0.05  # metres: a point counts as seen by j when j's ray hits no wall this much before it
GT_OVERLAP = 0.3


@dataclass
class _Floor:
    xs: np.ndarray  # (C + 1,) column boundaries, metres
    ys: np.ndarray  # (R + 1,) row boundaries
    corridor: np.ndarray  # (R,) row is a corridor
    height: float
    doors: dict[tuple[tuple[int, int], tuple[int, int]], tuple[float, float]]  # cell pair -> opening (from, to)

    def neighbours(self, cell: tuple[int, int]) -> list[tuple[int, int]]:
        return [b for a, b in self.doors if a == cell] + [a for a, b in self.doors if b == cell]


def make_building(n: int, seed: int) -> SceneGT:
    """The ground truth of ``n`` scans walked through a generated floor (module doc); cached."""
    if n < 20:
        raise ValueError(f"a generated building needs at least 20 scans, got {n}")
    return _make_building(int(n), int(seed))


@lru_cache(maxsize=4)
def _make_building(n: int, seed: int) -> SceneGT:
    rng = np.random.default_rng([seed, n, 0xB11D])
    floor = _floor(rng, max(2, round(n / SCANS_PER_ROOM)))
    caster = o3d.t.geometry.RaycastingScene()
    vertices, triangles = _mesh(floor)
    caster.add_triangles(o3d.core.Tensor(vertices, o3d.core.float32), o3d.core.Tensor(triangles, o3d.core.uint32))
    positions, headings = _walk(rng, floor, n)
    poses, points = _scans(rng, caster, positions, headings)
    seen = _seen_by(caster, poses, points)  # seen[a][b]: which points of a scan b sees
    directed = np.zeros((n, n))
    for a, row in seen.items():
        for b, mask in row.items():
            directed[a, b] = mask.mean()
    overlap = combine(directed, "mean")
    np.fill_diagonal(overlap, 0.0)
    gt_log, gt_info = {}, {}
    for a, b in zip(*np.nonzero(np.triu(overlap, 1) > GT_OVERLAP)):
        a, b = int(a), int(b)
        gt_log[(a, b)] = inv_T(poses[a]) @ poses[b]
        # The overlapping surface seen from both sides, in scan a's frame (one direction may hold few points).
        back = points[b][seen[b][a]] if a in seen[b] else np.zeros((0, 3))
        mine = points[a][seen[a][b]] if b in seen[a] else np.zeros((0, 3))
        gt_info[(a, b)] = _information(np.concatenate([mine, back @ gt_log[(a, b)][:3, :3].T + gt_log[(a, b)][:3, 3]]))
    return SceneGT(f"gen{n}", list(range(n)), poses, overlap, np.array([0.0, 0.0, 1.0]), gt_log, gt_info)


def _information(p: np.ndarray) -> np.ndarray:
    """3DMatch's gt.info of a pair from its overlapping points p (K, 3) in its first scan's frame: Σ GᵀG with
    G = [I, −[p]×]."""
    G = np.zeros((len(p), 3, 6))
    G[:, :, :3] = np.eye(3)
    x, y, z = p.T
    G[:, 0, 4], G[:, 0, 5] = z, -y
    G[:, 1, 3], G[:, 1, 5] = -z, x
    G[:, 2, 3], G[:, 2, 4] = y, -x
    G = G.reshape(-1, 6)
    return G.T @ G


def _floor(rng: np.random.Generator, rooms: int) -> _Floor:
    """Rows of rooms in blocks [room, corridor, room], about ``rooms`` rooms in all, and their doors."""
    cols = max(2, round(np.sqrt(rooms * 1.5)))
    blocks = max(1, round(rooms / (2 * cols)))
    corridor = np.array([False, True, False] * blocks)
    depth = np.where(corridor, rng.uniform(*CORRIDOR_WIDTH, len(corridor)), rng.uniform(*ROOM_SIDE, len(corridor)))
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(*ROOM_SIDE, cols))])
    ys = np.concatenate([[0.0], np.cumsum(depth)])
    R, C = len(corridor), cols
    pairs = [((r, c), (r, c + 1)) for r in range(R) for c in range(C - 1)]
    pairs += [((r, c), (r + 1, c)) for r in range(R - 1) for c in range(C)]
    # A random spanning tree (Kruskal on shuffled pairs) keeps every cell reachable.
    parent = {(r, c): (r, c) for r in range(R) for c in range(C)}

    def root(cell: tuple[int, int]) -> tuple[int, int]:
        while parent[cell] != cell:
            cell = parent[cell]
        return cell

    tree = set()
    for k in rng.permutation(len(pairs)):
        a, b = pairs[k]
        if root(a) != root(b):
            parent[root(a)] = root(b)
            tree.add(pairs[k])
    doors = {}
    for a, b in pairs:
        horizontal = a[0] == b[0]
        if horizontal and corridor[a[0]]:
            opening = (ys[a[0]], ys[a[0] + 1])  # a corridor is open along its length
        else:
            p = P_CORRIDOR_DOOR if corridor[a[0]] or corridor[b[0]] else P_ROOM_DOOR
            if (a, b) not in tree and rng.random() >= p:
                continue
            lo, hi = (ys[a[0]], ys[a[0] + 1]) if horizontal else (xs[a[1]], xs[a[1] + 1])
            width = rng.uniform(*DOOR_WIDTH)
            start = rng.uniform(lo + 0.3, hi - 0.3 - width)
            opening = (start, start + width)
        doors[(a, b)] = opening
    return _Floor(xs, ys, corridor, float(rng.uniform(*HEIGHT)), doors)


def _mesh(floor: _Floor) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of the walls (with their openings cut out), the floor and the ceiling."""
    xs, ys, H = floor.xs, floor.ys, floor.height
    R, C = len(ys) - 1, len(xs) - 1
    segments = []  # (x0, y0, x1, y1) wall pieces

    def wall(fixed: float, lo: float, hi: float, vertical: bool, gap: tuple[float, float] | None) -> None:
        pieces = [(lo, hi)] if gap is None else [(lo, gap[0]), (gap[1], hi)]
        for a, b in pieces:
            if b - a > 1e-9:
                segments.append((fixed, a, fixed, b) if vertical else (a, fixed, b, fixed))

    for r in range(R):
        for c in range(C + 1):  # walls x = xs[c] between cells (r, c - 1) and (r, c)
            gap = floor.doors.get(((r, c - 1), (r, c))) if 0 < c < C else None
            wall(xs[c], ys[r], ys[r + 1], True, gap)
    for r in range(R + 1):
        for c in range(C):  # walls y = ys[r] between cells (r - 1, c) and (r, c)
            gap = floor.doors.get(((r - 1, c), (r, c))) if 0 < r < R else None
            wall(ys[r], xs[c], xs[c + 1], False, gap)
    quads = [[(x0, y0, 0.0), (x1, y1, 0.0), (x1, y1, H), (x0, y0, H)] for x0, y0, x1, y1 in segments]
    for z in (0.0, H):
        quads.append([(xs[0], ys[0], z), (xs[-1], ys[0], z), (xs[-1], ys[-1], z), (xs[0], ys[-1], z)])
    vertices = np.array(quads, dtype=float).reshape(-1, 3)
    base = 4 * np.arange(len(quads))[:, None]
    triangles = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return vertices, triangles


def _door_point(rng: np.random.Generator, floor: _Floor, a: tuple[int, int], b: tuple[int, int]) -> np.ndarray:
    """A point in the opening between neighbouring cells a and b, 0.2 m inside its edges where it can."""
    lo, hi = floor.doors[(a, b) if (a, b) in floor.doors else (b, a)]
    t = rng.uniform(lo + min(0.2, (hi - lo) / 3), hi - min(0.2, (hi - lo) / 3))
    if a[0] == b[0]:
        return np.array([floor.xs[max(a[1], b[1])], t])
    return np.array([t, floor.ys[max(a[0], b[0])]])


def _inside(rng: np.random.Generator, floor: _Floor, cell: tuple[int, int]) -> np.ndarray:
    r, c = cell
    mx = min(WALL_MARGIN, (floor.xs[c + 1] - floor.xs[c]) / 3)
    my = min(WALL_MARGIN, (floor.ys[r + 1] - floor.ys[r]) / 3)
    return np.array(
        [rng.uniform(floor.xs[c] + mx, floor.xs[c + 1] - mx), rng.uniform(floor.ys[r] + my, floor.ys[r + 1] - my)]
    )


def _walk(rng: np.random.Generator, floor: _Floor, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` camera positions (n, 2) along a walk through the floor and the walker's heading (n,) at each."""
    cells = [(r, c) for r in range(len(floor.ys) - 1) for c in range(len(floor.xs) - 1)]
    cell = cells[rng.integers(len(cells))]
    previous = None
    visits = {c: 0 for c in cells}
    waypoints = [_inside(rng, floor, cell)]
    length = 0.0
    while length < n * STEP[1] + 1.0:  # enough path for n steps of at most STEP[1]
        visits[cell] += 1
        options = [c for c in floor.neighbours(cell) if c != previous] or floor.neighbours(cell)
        weight = 1.0 / (1.0 + np.array([visits[c] for c in options], float)) ** 2
        nxt = options[rng.choice(len(options), p=weight / weight.sum())]
        inner = rng.integers(0 if floor.corridor[cell[0]] else 1, 3)
        for point in [_inside(rng, floor, cell) for _ in range(inner)] + [_door_point(rng, floor, cell, nxt)]:
            length += np.linalg.norm(point - waypoints[-1])
            waypoints.append(point)
        previous, cell = cell, nxt
    waypoints = np.array(waypoints)
    seg = np.linalg.norm(np.diff(waypoints, axis=0), axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    at = np.cumsum(rng.uniform(*STEP, n))
    k = np.clip(np.searchsorted(arc, at, side="right") - 1, 0, len(seg) - 1)
    direction = np.diff(waypoints, axis=0)[k] / np.maximum(seg[k], 1e-9)[:, None]
    positions = waypoints[k] + (at - arc[k])[:, None] * direction + rng.normal(0.0, JITTER, (n, 2))
    # The body turns towards the path's direction by at most MAX_TURN a scan (no jumps at waypoints).
    path = np.arctan2(direction[:, 1], direction[:, 0])
    heading = path.copy()
    for s in range(1, n):
        turn = (path[s] - heading[s - 1] + np.pi) % (2 * np.pi) - np.pi
        heading[s] = heading[s - 1] + np.clip(turn, -MAX_TURN, MAX_TURN)
    return positions, heading


def _camera(position: np.ndarray, height: float, yaw: float, pitch: float, roll: float) -> np.ndarray:
    """T (4, 4) of a camera (x right, y down, z forward) in the world (z up)."""
    forward = np.array([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = np.cos(roll), np.sin(roll)
    R = np.stack([c * right + s * down, -s * right + c * down, forward], axis=1)
    return make_T(R, np.array([position[0], position[1], height]))


def _rays(rng: np.random.Generator, k: int) -> np.ndarray:
    """(k, 3) unit ray directions at random pixels of the camera's image, camera frame."""
    u = rng.uniform(-np.tan(FOV_X / 2), np.tan(FOV_X / 2), k)
    v = rng.uniform(-np.tan(FOV_Y / 2), np.tan(FOV_Y / 2), k)
    d = np.stack([u, v, np.ones(k)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _cast(caster: o3d.t.geometry.RaycastingScene, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
    return caster.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(float)


def _scans(
    rng: np.random.Generator, caster: o3d.t.geometry.RaycastingScene, positions: np.ndarray, headings: np.ndarray
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Each scan's pose (n, 4, 4) and its surface points (K_i, 3) in its own frame."""
    n = len(positions)
    poses, points = np.zeros((n, 4, 4)), []
    look, height = 0.0, 0.0
    for k in range(n):
        look = LOOK_KEEP * look + rng.normal(0.0, LOOK_STEP)
        height = HEIGHT_KEEP * height + rng.normal(0.0, HEIGHT_STEP)
        for _ in range(8):
            T = _camera(
                positions[k],
                np.clip(np.mean(CAMERA_HEIGHT) + height, *CAMERA_HEIGHT),
                headings[k] + look,
                PITCH + rng.normal(0.0, PITCH_SD),
                rng.normal(0.0, ROLL_SD),
            )
            d = _rays(rng, POINTS)
            t = _cast(caster, np.tile(T[:3, 3], (POINTS, 1)), d @ T[:3, :3].T)
            p = d * t[:, None]
            ok = np.isfinite(t) & (p[:, 2] >= DEPTH[0]) & (p[:, 2] <= DEPTH[1])
            if ok.mean() >= MIN_SEEN:
                break
            look += rng.choice((-1.0, 1.0)) * rng.uniform(np.pi / 3, np.pi)  # a wall ahead: turn away
        poses[k], points = T, points + [p[ok]]
    return poses, points


def _seen_by(
    caster: o3d.t.geometry.RaycastingScene, poses: np.ndarray, points: list[np.ndarray]
) -> dict[int, dict[int, np.ndarray]]:
    """For every scan a and every other scan b that sees any of its points: the mask of a's points b sees."""
    centres = poses[:, :3, 3]
    half = np.tan([FOV_X / 2, FOV_Y / 2])
    seen: dict[int, dict[int, np.ndarray]] = {}
    for a in range(len(poses)):
        world = points[a] @ poses[a, :3, :3].T + poses[a, :3, 3]
        near = np.linalg.norm(centres - centres[a], axis=1) < 2 * DEPTH[1]
        near[a] = False
        others = np.flatnonzero(near)
        q = (world[None] - centres[others, None]) @ poses[others, :3, :3]  # a's points in each b's frame
        inside = (q[..., 2] >= DEPTH[0]) & (q[..., 2] <= DEPTH[1])
        inside &= (np.abs(q[..., 0]) <= half[0] * q[..., 2]) & (np.abs(q[..., 1]) <= half[1] * q[..., 2])
        b_idx, k_idx = np.nonzero(inside)
        ray = world[k_idx] - centres[others[b_idx]]
        dist = np.linalg.norm(ray, axis=1)
        hit = _cast(caster, centres[others[b_idx]], ray / dist[:, None])
        inside[b_idx, k_idx] = hit >= dist - OCCLUSION_SLACK  # not hidden behind a wall
        seen[a] = {int(b): mask for b, mask in zip(others, inside) if mask.any()}
    return seen
