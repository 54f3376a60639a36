"""A generated building that grows with its number of scans: furnished rooms along corridors (``make_building``),
for ``python -m sghr_gtsam demo --scans N`` at any N and the scale benchmark, and its look-alike, the hotel,
whose rooms are all one room.

**Floor plan** (metres, z up, floor at z = 0). A *branch* is a corridor ``CORRIDOR`` wide along +x from x = 0 with
rooms on both sides, about sqrt(R / 2) a side for R rooms in all; branch b runs along y = b · ``BRANCH_PITCH``. With
more than one branch, a *spine* corridor as wide runs along y at x < 0 and joins them, so the floor grows in both
directions with N. A room is ``synthetic.geometry._room`` (4–5 × 3.4–4 × 2.5 m, furniture and clutter of its own) with a
doorway 1.2–1.6 m wide through the ``WALL`` between it and the corridor; rooms stand at least ``GAP`` apart. Walls
have a thickness, so that no surface is seen from both sides (a wall's two faces would count as overlap). Corridor
and spine segments have uneven walls, floor and ceiling, cabinets, things on the floor and panels on the walls,
random in every segment. The hotel (``identical_rooms``): every room is the same room, doorway included (turned
to face its corridor); only the corridors differ.

**Scans** (as ``synthetic``'s room: 120° × 80° views of 150 × 100 rays, range noise ``noise``, ranges cut at
``MAX_RANGE``; 5–15k points a scan, voxel 5 cm):

- in each room, 3–8 (about 5) views from an ellipse around the table looking across it (the room kind's);
- in each doorway, two views along the wall, one each way: half of such a view is the room, half the corridor,
  so rooms and corridors register to each other;
- in the corridors and the spine, stations ``STATION`` apart with a view across to either wall: each sees a few
  metres of the opposite wall face on, and through its doorways into the rooms, sharing about half of that wall
  with the next station's view (views along a corridor see its walls at a grazing angle, and two of them share
  little FPFH can match); at each junction one more view, half into the branch and half along the spine.

So a scan overlaps the views of its room and of the corridor within ``MAX_RANGE``: a bounded number whatever N.

**Streaming.** The scans of a building scene are made when read: ``SyntheticScene.scans`` is a sequence that
ray-casts scan k on access (from a seed of its own, so the order of access does not matter), against the cells
(rooms and segments) within ``MAX_RANGE`` of the sensors of its cell only, which is exact because nothing
further away can be hit within range. Generation is linear in N, and ``synthetic.write_scene`` holds one scan
and one neighbourhood's geometry at a time.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from math import ceil

import numpy as np
import open3d as o3d

from sghr_gtsam.synthetic.geometry import (
    DOOR_HEIGHT,
    ROOM_SIZE,
    SyntheticScene,
    _box,
    _clutter,
    _look_at,
    _relief_wall,
    _room,
    _rot_z,
    _scan,
    _Sensor,
)

CORRIDOR = 2.4  # width of the corridors and the spine
WALL = 0.25  # between a room and its corridor
GAP = 0.4  # between neighbouring rooms, and back to back across branches
SEGMENT = ROOM_SIZE[0] + GAP  # a corridor segment: one room a side
BRANCH_PITCH = CORRIDOR + 2 * (WALL + ROOM_SIZE[1]) + GAP
STATION = SEGMENT / 2  # between views across a corridor
DOOR_WIDTH = (1.2, 1.6)
ROOM_SHRINK = (0.8, 0.85)  # a room's length and width: at least these fractions of ``ROOM_SIZE``'s
MAX_RANGE = 6.0
ROOM_VIEWS = (3, 8, 5)  # views from a room's ellipse: fewest, most, preferred
MARGIN = 0.15  # relief and clutter reach this far outside a cell's walls
# Every view's field and rays (``_scan`` reads nothing else of a ``_Sensor``: the poses are the building's).
VIEW = _Sensor(np.zeros((0, 3)), np.zeros((0, 3)), fov_deg=(120.0, 80.0), grid=(150, 100), max_roll=0.4)
_LAYOUT, _ROOM, _SEGMENT, _SPINE, _SCAN = range(5)  # seed tags: each random stream is a function of (seed, tag, ...)
_MESHES_KEPT = 24  # cell meshes kept between neighbourhoods (0.3-0.7 MB each): a branch's rooms are built once

View = Callable[[int, np.ndarray, np.ndarray, np.ndarray, float], None]


@dataclass
class Cell:
    """A piece of the building with geometry of its own: a ``room``, a ``corridor`` segment of a branch or a
    ``spine`` segment. ``frame`` maps the cell's own frame into the world: a room's is ``synthetic.geometry._room``'s
    (doorway in its wall at y = -2); a segment's has x along its corridor, y across it, origin on the corridor's
    centre line, and spans x in [``start``, ``start + length``]."""

    kind: str
    branch: int
    index: int  # the segment along the branch (a room: the segment it opens on)
    side: int  # a room: +1 or -1, the side of its corridor it stands on; 0 for segments
    frame: np.ndarray  # (4, 4)
    lo: np.ndarray  # (3,) world bounding box
    hi: np.ndarray
    door: tuple[float, float] | None = None  # a room: its doorway's x range in its own frame
    size: tuple[float, float, float] = ROOM_SIZE  # a room: length, width, height
    start: float = 0.0
    length: float = 0.0


@dataclass
class Building:
    """A generated building and its scans' sensors: ``poses[k]`` of scan k (``p_world = T @ p_scan``) standing in
    ``cells[cell_of_scan[k]]``."""

    seed: int
    identical_rooms: bool
    noise: float
    cells: list[Cell]
    poses: np.ndarray  # (N, 4, 4)
    cell_of_scan: np.ndarray  # (N,)
    rooms_at: dict[tuple[int, int, int], Cell] = field(init=False)  # (branch, segment, side) -> room

    def __post_init__(self) -> None:
        self.rooms_at = {(c.branch, c.index, c.side): c for c in self.cells if c.kind == "room"}

    @property
    def spine(self) -> bool:
        return any(c.kind == "spine" for c in self.cells)


def make_building(n_scans: int, seed: int = 0, noise: float = 0.003, identical_rooms: bool = False) -> SyntheticScene:
    """A building of ``n_scans`` scans (at least 9; module doc) whose scans are ray-cast when read; deterministic
    for ``seed``."""
    building = building_layout(n_scans, seed, noise, identical_rooms)
    width = max(2, len(str(n_scans - 1)))
    return SyntheticScene([f"scan_{k:0{width}d}.ply" for k in range(n_scans)], _Scans(building), building.poses, 0.05)


def building_layout(n_scans: int, seed: int = 0, noise: float = 0.003, identical_rooms: bool = False) -> Building:
    """The floor plan and the sensors of ``make_building``'s scene, without any scan."""
    per_branch, views = _plan(n_scans)
    rng = np.random.default_rng([seed, _LAYOUT, n_scans])
    rooms = _rooms(rng, len(views), identical_rooms)
    cells: list[Cell] = []
    eyes, targets, rolls, where = [], [], [], []

    def view(cell: int, frame: np.ndarray, eye: np.ndarray, target: np.ndarray, max_roll: float) -> None:
        eyes.append(frame[:3, :3] @ eye + frame[:3, 3])
        targets.append(frame[:3, :3] @ target + frame[:3, 3])
        rolls.append(rng.uniform(-max_roll, max_roll))
        where.append(cell)

    room = 0
    for b, rooms_here in enumerate(per_branch):
        y = b * BRANCH_PITCH
        if len(per_branch) > 1:
            cells.append(_spine_cell(b, y))
            _junction_view(rng, len(cells) - 1, cells[-1], view)
            _views_across(rng, len(cells) - 1, cells[-1], view)
        segments = ceil(rooms_here / 2)
        for c in range(segments):
            cells.append(_corridor_cell(b, c, y, last=c == segments - 1))
            _views_across(rng, len(cells) - 1, cells[-1], view)
            for side in (1, -1)[: min(2, rooms_here - 2 * c)]:
                cells.append(_room_cell(b, c, side, y, *rooms[room]))
                _room_views(rng, len(cells) - 1, cells[-1], views[room], view)
                room += 1
    poses = np.stack([_look_at(e, t, r) for e, t, r in zip(eyes, targets, rolls)])
    return Building(seed, identical_rooms, noise, cells, poses, np.array(where))


def _rooms_per_branch(rooms: int) -> int:
    """Twice the rooms a side of a branch: about sqrt(2 · rooms), so that the floor grows in both directions."""
    return 2 * ceil(np.sqrt(rooms / 2))


def _stations(length: float) -> int:
    return round(length / STATION)


def _plan(n: int) -> tuple[list[int], list[int]]:
    """Rooms per branch and views per room such that the scans add up to ``n``: the number of rooms whose views
    come closest to ``ROOM_VIEWS[2]`` a room (more than ``ROOM_VIEWS[1]`` only where the spine's views make one
    more room too many, as at 50 scans)."""
    fewest, most, preferred = ROOM_VIEWS
    best = None
    for rooms in range(1, n // fewest + 1):
        branches = ceil(rooms / _rooms_per_branch(rooms))
        per_branch = [rooms // branches + (b < rooms % branches) for b in range(branches)]
        corridors = 2 * sum(_stations(SEGMENT) * ceil(r / 2) for r in per_branch)
        spine = branches * (1 + 2 * _stations(BRANCH_PITCH)) if branches > 1 else 0
        free = n - corridors - spine - 2 * rooms
        score = (free > most * rooms, abs(free / rooms - preferred))
        if free >= fewest * rooms and (best is None or score < best[0]):
            best = (score, per_branch, [free // rooms + (r < free % rooms) for r in range(rooms)])
    if best is None:
        raise ValueError(f"a building needs at least 9 scans, got {n}")
    return best[1], best[2]


def _rooms(
    rng: np.random.Generator, count: int, identical: bool
) -> list[tuple[tuple[float, float, float], tuple[float, float]]]:
    """Each room's size (rooms differ, as they do: same-sized shells would line up by their corners and edges
    across rooms) and doorway (x range in its frame); one for all in a hotel."""
    L, W, H = ROOM_SIZE
    out = []
    for _ in range(1 if identical else count):
        size = (L * rng.uniform(ROOM_SHRINK[0], 1.0), W * rng.uniform(ROOM_SHRINK[1], 1.0), H)
        width = rng.uniform(*DOOR_WIDTH)
        start = rng.uniform(-size[0] / 2 + 0.6, size[0] / 2 - 0.6 - width)
        out.append((size, (start, start + width)))
    return out * count if identical else out


def _frame(angle: float, origin: Sequence[float]) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = _rot_z(angle), origin
    return T


def _box_of(frame: np.ndarray, lo: Sequence[float], hi: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """World bounding box of the cell-frame box [lo, hi], widened by ``MARGIN``."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    world = corners @ frame[:3, :3].T + frame[:3, 3]
    return world.min(0) - MARGIN, world.max(0) + MARGIN


def _room_cell(
    b: int, c: int, side: int, y: float, size: tuple[float, float, float], door: tuple[float, float]
) -> Cell:
    """A room of ``size`` on ``side`` of segment c of branch b (at y), in the middle of its place along the
    corridor, its doorway wall on the corridor's."""
    L, W, H = size
    frame = _frame(
        0.0 if side > 0 else np.pi,
        (c * SEGMENT + GAP + ROOM_SIZE[0] / 2, y + side * (CORRIDOR / 2 + WALL + W / 2), 0.0),
    )
    lo, hi = _box_of(frame, (-L / 2, -W / 2, 0.0), (L / 2, W / 2, H))
    return Cell("room", b, c, side, frame, lo, hi, door, size)


def _corridor_cell(b: int, c: int, y: float, last: bool) -> Cell:
    """Segment c of branch b; it holds the corridor's side of the walls and the doorways through them."""
    length = SEGMENT + (GAP if last else 0.0)  # the last one reaches past its rooms to the end wall
    frame = _frame(0.0, (c * SEGMENT, y, 0.0))
    lo, hi = _box_of(frame, (0.0, -CORRIDOR / 2 - WALL, 0.0), (length, CORRIDOR / 2 + WALL, ROOM_SIZE[2]))
    return Cell("corridor", b, c, 0, frame, lo, hi, length=length)


def _spine_cell(b: int, y: float) -> Cell:
    """The spine segment at branch b's junction: x along world +y, y towards world -x (the branch at y < 0)."""
    frame = _frame(np.pi / 2, (-CORRIDOR / 2, y, 0.0))
    half = BRANCH_PITCH / 2
    lo, hi = _box_of(frame, (-half, -CORRIDOR / 2, 0.0), (half, CORRIDOR / 2, ROOM_SIZE[2]))
    return Cell("spine", b, 0, 0, frame, lo, hi, start=-half, length=BRANCH_PITCH)


def _room_views(rng: np.random.Generator, cell: int, room: Cell, count: int, view: View) -> None:
    """``count`` views from the ellipse around the table (as ``synthetic.geometry._room_sensors``), then one each way
    along the wall from the middle of the doorway (the jambs take the middle of the view)."""
    L, W, _ = room.size
    angles = 2 * np.pi / count * np.arange(count) + rng.uniform(0, 2 * np.pi) + rng.uniform(-0.08, 0.08, count)
    for a in angles:
        eye = np.array([0.3 * L * np.cos(a), 0.275 * W * np.sin(a), rng.uniform(1.2, 1.7)])
        view(cell, room.frame, eye, np.array([*rng.uniform(-0.3, 0.3, 2), rng.uniform(0.5, 1.0)]), 0.4)
    middle = sum(room.door) / 2
    for direction in (1.0, -1.0):
        eye = np.array(
            [middle + rng.uniform(-0.1, 0.1), -W / 2 - WALL / 2 + rng.uniform(-0.05, 0.05), rng.uniform(1.3, 1.6)]
        )
        ahead = np.array([direction * 3.0, 3.0 * np.tan(np.radians(rng.uniform(-15, 15))), rng.uniform(-0.5, -0.2)])
        view(cell, room.frame, eye, eye + ahead, 0.2)


def _views_across(rng: np.random.Generator, cell: int, segment: Cell, view: View) -> None:
    """Stations about ``STATION`` apart, evenly along the segment (and so across segments of one length), each with
    a view across to either wall."""
    stations = _stations(segment.length)
    for k in range(stations):
        x = segment.start + (k + 0.5) * segment.length / stations
        for side in (1.0, -1.0):
            eye = np.array([x + rng.uniform(-0.2, 0.2), -side * rng.uniform(0.0, 0.4), rng.uniform(1.2, 1.7)])
            yaw = side * np.pi / 2 + np.radians(rng.uniform(-10, 10))
            view(cell, segment.frame, eye, eye + [4 * np.cos(yaw), 4 * np.sin(yaw), rng.uniform(-0.8, -0.2)], 0.3)


def _junction_view(rng: np.random.Generator, cell: int, segment: Cell, view: View) -> None:
    """From the middle of a junction, half into the branch and half along the spine."""
    eye = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(1.2, 1.7)])
    turn = rng.choice((-1.0, 1.0)) * np.radians(rng.uniform(30, 50))
    view(cell, segment.frame, eye, eye + [4.0 * np.sin(turn), -4.0 * np.cos(turn), rng.uniform(-0.8, -0.2)], 0.3)


# --- geometry ------------------------------------------------------------------------------------


def _quad(corner: np.ndarray, a: np.ndarray, b: np.ndarray) -> o3d.geometry.TriangleMesh:
    """The flat rectangle ``corner + s*a + t*b``, s, t in [0, 1]."""
    v = np.array([corner, corner + a, corner + a + b, corner + b])
    return o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector([[0, 1, 2], [0, 2, 3]]))


def _segment_mesh(
    rng: np.random.Generator,
    x0: float,
    x1: float,
    openings: dict[int, list[tuple[float, float]]],
    doors: dict[int, list[tuple[float, float]]],
    ends: tuple[bool, bool],
) -> o3d.geometry.TriangleMesh:
    """A corridor segment from x0 to x1 in its own frame: uneven floor, ceiling and walls at y = ±CORRIDOR / 2,
    the walls open over ``openings[side]`` (x ranges, floor to ceiling) and ``doors[side]`` (floor to
    ``DOOR_HEIGHT``, each with its passage through the ``WALL``), end walls where ``ends`` says, and things along
    the walls kept clear of the openings and doorways."""
    w, H = CORRIDOR / 2, ROOM_SIZE[2]
    ex, ey, ez = np.eye(3)
    mesh = _relief_wall(np.array([x0, -w, 0.0]), (x1 - x0) * ex, 2 * w * ey, rng)
    mesh += _relief_wall(np.array([x1, w, H]), -(x1 - x0) * ex, -2 * w * ey, rng)
    for side in (1, -1):
        holes = sorted(openings.get(side, []) + doors.get(side, []))
        edges = [x0, *[x for hole in holes for x in hole], x1]
        y = side * w * ey
        for a, b in zip(edges[::2], edges[1::2]):
            mesh += _relief_wall(a * ex + y, (b - a) * ex, H * ez, rng)
        for a, b in doors.get(side, []):
            mesh += _relief_wall(a * ex + y + DOOR_HEIGHT * ez, (b - a) * ex, (H - DOOR_HEIGHT) * ez, rng)
            through = side * WALL * ey
            mesh += _quad(a * ex + y, (b - a) * ex, through)  # threshold
            mesh += _quad(a * ex + y + DOOR_HEIGHT * ez, (b - a) * ex, through)  # lintel
            for x in (a, b):  # jambs
                mesh += _quad(x * ex + y, through, DOOR_HEIGHT * ez)
    for x, closed in zip((x0, x1), ends):
        if closed:
            mesh += _relief_wall(np.array([x, -w, 0.0]), 2 * w * ey, H * ez, rng)

    def free(side: int, along: float, half: float) -> bool:
        holes = openings.get(side, []) + doors.get(side, [])
        return all(abs(along - (a + b) / 2) > (b - a) / 2 + half + 0.3 for a, b in holes)

    for _ in range(round((x1 - x0) * rng.uniform(0.6, 1.3))):  # 3-7 things a room's length
        side, along, what = rng.choice((-1, 1)), rng.uniform(x0 + 0.4, x1 - 0.4), rng.integers(3)
        angle = rng.uniform(-0.15, 0.15)
        if what == 0:  # a cabinet against the wall
            depth, width, height = rng.uniform(0.25, 0.45), rng.uniform(0.5, 1.1), rng.uniform(0.5, 1.8)
            if free(side, along, width / 2):
                mesh += _box((width, depth, height), (along, side * (w - depth / 2 - 0.05), height / 2), _rot_z(angle))
        elif what == 1:  # something on the floor by the wall
            size = rng.uniform(0.25, 0.5)
            if free(side, along, size / 2):
                mesh += _clutter(rng, size, np.array([along, side * (w - 0.3 - size / 2), 0.0]))
        else:  # a panel on the wall
            width, height, z = rng.uniform(0.3, 1.0), rng.uniform(0.2, 0.7), rng.uniform(1.3, 2.0)
            if free(side, along, width / 2):
                mesh += _box((width, 0.06, height), (along, side * (w - 0.03), z), _rot_z(angle / 5))
    return mesh


def _corridor_mesh(building: Building, cell: Cell) -> o3d.geometry.TriangleMesh:
    """A branch's segment: its walls with the doorways of the rooms beside it, closed at the branch's end (and at
    its start when there is no spine)."""
    rng = np.random.default_rng([building.seed, _SEGMENT, cell.branch, cell.index])
    doors = {}
    for side in (1, -1):
        room = building.rooms_at.get((cell.branch, cell.index, side))
        if room is not None:  # the doorway in this frame: a room on the -1 side is turned by 180 degrees
            a, b = (GAP + ROOM_SIZE[0] / 2 + side * d for d in room.door)
            doors[side] = [(min(a, b), max(a, b))]
    last = cell.length > SEGMENT
    return _segment_mesh(rng, 0.0, cell.length, {}, doors, (cell.index == 0 and not building.spine, last))


def _spine_mesh(building: Building, cell: Cell) -> o3d.geometry.TriangleMesh:
    """A spine segment: the outer wall whole, the inner one open onto the branch, closed at the spine's ends."""
    rng = np.random.default_rng([building.seed, _SPINE, cell.branch])
    branches = sum(c.kind == "spine" for c in building.cells)
    w = CORRIDOR / 2
    return _segment_mesh(
        rng, cell.start, cell.start + cell.length, {-1: [(-w, w)]}, {}, (cell.branch == 0, cell.branch == branches - 1)
    )


def _arrays(mesh: o3d.geometry.TriangleMesh, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices float32 in the world, triangles uint32) of a cell-frame mesh."""
    v = np.asarray(mesh.vertices) @ frame[:3, :3].T + frame[:3, 3]
    return v.astype(np.float32), np.asarray(mesh.triangles).astype(np.uint32)


class _Scans(Sequence):
    """A building's scans, each ray-cast when read (module doc: streaming); keeps the ray caster of the last cell's
    neighbourhood and the last ``_MESHES_KEPT`` cell meshes."""

    def __init__(self, building: Building):
        self.building = building
        cells = building.cells
        self._lo, self._hi = np.array([c.lo for c in cells]), np.array([c.hi for c in cells])
        self._branch = np.array([-1 if c.kind == "spine" else c.branch for c in cells])
        self._meshes: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()
        self._caster: tuple[int, o3d.t.geometry.RaycastingScene] | None = None
        self._hotel_room: o3d.geometry.TriangleMesh | None = None

    def __len__(self) -> int:
        return len(self.building.poses)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[i] for i in range(*k.indices(len(self)))]
        if not -len(self) <= k < len(self):
            raise IndexError(k)
        k %= len(self)
        b = self.building
        rng = np.random.default_rng([b.seed, _SCAN, k])
        points = _scan(self._raycaster(int(b.cell_of_scan[k])), b.poses[k], VIEW, b.noise, rng)
        return points[np.linalg.norm(points, axis=1) <= MAX_RANGE]

    def __iter__(self) -> Iterator[np.ndarray]:
        return (self[k] for k in range(len(self)))

    def _raycaster(self, cell: int) -> o3d.t.geometry.RaycastingScene:
        if self._caster is None or self._caster[0] != cell:
            scene = o3d.t.geometry.RaycastingScene()
            for near in self._neighbourhood(cell):
                vertices, triangles = self._mesh(int(near))
                scene.add_triangles(o3d.core.Tensor(vertices), o3d.core.Tensor(triangles))
            self._caster = (cell, scene)
        return self._caster[1]

    def _neighbourhood(self, cell: int) -> np.ndarray:
        """The cells a sensor of ``cell`` can see within range: of its own branch and the spine (a ray leaves a
        branch only into the spine, at x < 0, and never comes back to x >= 0), or any from the spine; those whose
        box is within ``MAX_RANGE`` of one of the cell's sensors."""
        eyes = self.building.poses[self.building.cell_of_scan == cell, :3, 3]
        gap = np.maximum(np.maximum(self._lo[None] - eyes[:, None], eyes[:, None] - self._hi[None]), 0.0)
        near = np.linalg.norm(gap, axis=2).min(0) <= MAX_RANGE
        if self._branch[cell] >= 0:
            near &= (self._branch == self._branch[cell]) | (self._branch < 0)
        return np.flatnonzero(near)

    def _mesh(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        if k in self._meshes:
            self._meshes.move_to_end(k)
            return self._meshes[k]
        b, cell = self.building, self.building.cells[k]
        if cell.kind == "room" and b.identical_rooms:
            if self._hotel_room is None:
                self._hotel_room = _room(np.random.default_rng([b.seed, _ROOM]), cell.door, cell.size)
            mesh = self._hotel_room
        elif cell.kind == "room":
            rng = np.random.default_rng([b.seed, _ROOM, cell.branch, cell.index, cell.side > 0])
            mesh = _room(rng, cell.door, cell.size)
        elif cell.kind == "corridor":
            mesh = _corridor_mesh(b, cell)
        else:
            mesh = _spine_mesh(b, cell)
        self._meshes[k] = _arrays(mesh, cell.frame)
        if len(self._meshes) > _MESHES_KEPT:
            self._meshes.popitem(last=False)
        return self._meshes[k]
