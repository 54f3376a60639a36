"""Free space (registration.visibility): how the conflict separates right registrations from wrong ones, and which
scans the check can see at all.

    python benchmarks/bench_free_space.py --run SCENE OUT [--run SCENE OUT ...] [--real DATA]
    python benchmarks/bench_free_space.py --placements [--draws 20]
    python benchmarks/bench_free_space.py --viewpoints

``--run``: a generated scene (``gt_poses.txt`` beside its scans) and a finished run of it (OUT with edges.csv,
graph.g2o, graph_rejected.g2o, report.json; with or without the check). Every registered pair (status other than
failed) is scored against GT (right: within 5° / 0.2 m) and its ``free_space_conflict`` computed on the scans' grids
at the run's voxel; the table gives the conflict's quantiles for right and wrong pairs, and how many of each lie above
``visibility.CONFLICT``. ``--real``: the shared data folder; per scene, how many scans ``seen_from_origin`` accepts
and the fraction of its own points each hides (the test the check needs before it says anything).
``--placements``: the placement test of verification (``visibility.placement_conflicts``) on generated scenes: in how
many draws it blames a scan of a right model whose every scan is turned by up to 1°, 2.5° or 5° about its viewpoint
(any two then up to twice that apart; the loop test accepts 10°), and in how many it blames a scan misplaced on
purpose (turned about the vertical through its viewpoint, or moved 1 m sideways) in the true model. Saved as the
table ``free_space_placements``.
``--viewpoints``: which generated scans the test takes as seen from their origin (``seen_from_origin``): stations
(rooms, buildings, hotels: one sensor each) and RGB-D fragments (``make_scene("fragments")``: frames of a walking
camera fused in the first frame's camera frame, whose origin is one viewpoint of many). Per kind the fraction of
its own points a scan hides, and under ``visibility.SELF_HIDDEN`` and a looser bar how many pass, and at the ground
truth the pairs of passing scans in conflict (``placement_conflicts``) and the scans blamed: every such blame is a
false alarm. The bar the stations calibrate: the hidden fraction ``STATIONS_PASSING`` of them stay within, rounded up
to 0.1 % (table ``free_space_viewpoints``). Then the fragments' own free space, which only the overrule reads: per
ordered pair of generated fragments the fraction of one's points in front of the other's surface, right (true pose)
and wrong (turned 90° or 180° about the viewpoint), on the per-pair check's range image and on the overrule's coarser
one (table ``free_space_fragments``).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._results import save  # noqa: E402
from sghr_gtsam.io.poses import read_poses  # noqa: E402
from sghr_gtsam.io.scans import list_scans, load_scan  # noqa: E402
from sghr_gtsam.registration.overrule import COARSE_BIN_DEG, COARSE_MARGIN_VOXELS  # noqa: E402
from sghr_gtsam.registration.visibility import (  # noqa: E402
    BIN_DEG,
    CONFLICT,
    MARGIN_VOXELS,
    MIN_IN_VIEW,
    SELF_HIDDEN,
    contradicted_scans,
    free_space_conflict,
    hidden_fraction,
    placement_conflicts,
    range_image,
    seen_in_front_of,
)
from sghr_gtsam.se3 import inv_T, relative_errors  # noqa: E402
from sghr_gtsam.synthetic import make_scene  # noqa: E402

MAX_DEG, MAX_TRANS = 5.0, 0.2
REAL = (
    ("kitchen", 0.025),
    ("bunny", 0.002),
    ("3dmatch-scenes/home_at", 0.025),
    ("3dmatch-scenes/hotel_uc", 0.025),
    ("3dmatch-scenes/studyroom", 0.025),
)


def _grid(P: np.ndarray, voxel: float) -> np.ndarray:
    """Scan points ``P`` on the features' voxel grid."""
    P = np.asarray(P, dtype=np.float64)
    return np.asarray(o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P)).voxel_down_sample(voxel).points)


def _registered(out: Path) -> list[tuple[int, int, np.ndarray, str]]:
    """(i, j, T_ij, status) of every pair of the run that registered: the EDGE lines of both g2o files (their
    vertex ids are the scans' indices; graph_rejected.g2o has no vertices, so it is read here line by line)."""
    status = {(int(r["i"]), int(r["j"])): r["status"] for r in csv.DictReader(open(out / "edges.csv"))}
    pairs = []
    for name in ("graph.g2o", "graph_rejected.g2o"):
        for line in (out / name).read_text().splitlines():
            tok = line.split()
            if not tok or tok[0] != "EDGE_SE3:QUAT":
                continue
            i, j, x = int(tok[1]), int(tok[2]), np.array(tok[3:10], dtype=float)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = Rotation.from_quat(x[3:]).as_matrix(), x[:3]
            s = status.get((i, j), status.get((j, i)))
            if s != "failed":
                pairs.append((i, j, T, s))
    return pairs


def _run_row(scene: Path, out: Path) -> dict:
    names, gt = read_poses(scene / "gt_poses.txt")
    voxel = json.loads((out / "report.json").read_text())["voxel"]
    grids: dict[int, np.ndarray] = {}

    def grid(k: int) -> np.ndarray:
        if k not in grids:
            grids[k] = _grid(load_scan(scene / names[k]), voxel)
        return grids[k]

    right, wrong = [], []
    for i, j, T, _ in _registered(out):
        rot, trans = relative_errors(T, inv_T(gt[i]) @ gt[j])
        (right if rot <= MAX_DEG and trans <= MAX_TRANS else wrong).append(
            free_space_conflict(grid(i), grid(j), T, voxel)
        )
    return {"run": f"{scene.name} / {out.name}", "right": np.array(right), "wrong": np.array(wrong)}


def _quantiles(x: np.ndarray) -> str:
    return " / ".join(f"{q:.3f}" for q in np.quantile(x, [0.1, 0.5, 0.9, 1.0])) if len(x) else "-"


def _real_row(data: Path, folder: str, voxel: float) -> str:
    h = np.array([hidden_fraction(_grid(load_scan(path), voxel), voxel) for path in list_scans(data / folder)])
    return (
        f"| {folder} | {len(h)} | {h.min():.3f} / {np.median(h):.3f} / {h.max():.3f} | "
        f"{int((h <= SELF_HIDDEN).sum())} |"
    )


PLACEMENT_SCENES = (("room", 10, 0), ("building", 12, 1), ("building", 20, 0))
"""Generated scenes (kind, scans, seed) of the placement table: seen from their origins, unlike hotels' identical
rooms, which the free space cannot tell apart."""
RIGHT_TURNS = (1.0, 2.5, 5.0)
"""The largest turn of each scan of a right model (degrees): a good registration's error is about 2°."""
MISPLACED = (("turned 30°", 30.0, 0.0), ("turned 90°", 90.0, 0.0), ("turned 180°", 180.0, 0.0), ("moved 1 m", 0.0, 1.0))
"""The misplacements of one scan: a turn about the vertical through its viewpoint (degrees), a sideways move (m)."""


VIEWPOINT_SCENES = (("room", 10, 8), ("building", 20, 4), ("hotel", 16, 4), ("fragments", 12, 8))
"""Generated scenes (kind, scans, seeds) of the viewpoint table."""
STATIONS_PASSING = 0.99
"""The share of generated stations the calibrated bar keeps as seen from their origin."""
LOOSER_BAR = 0.05
"""A looser bar on the hidden fraction, for comparison: what generated stations alone would suggest."""


def _viewpoint_rows() -> tuple[list[list], float]:
    """The viewpoint table's rows, and the bar the stations calibrate (module doc)."""
    rows, hidden = [], {}
    for kind, n, seeds in VIEWPOINT_SCENES:
        fractions, counts = [], np.zeros((2, 3), dtype=int)  # per bar: passing, pairs in conflict, blamed
        for seed in range(seeds):
            scene = make_scene(kind, n, seed=seed)
            grids = [_grid(P, scene.voxel) for P in scene.scans]
            h = np.array([hidden_fraction(g, scene.voxel) for g in grids])
            fractions += h.tolist()
            for row, bar in zip(counts, (LOOSER_BAR, SELF_HIDDEN)):
                clash = placement_conflicts(grids, scene.poses, h <= bar, scene.voxel)
                row += [(h <= bar).sum(), clash.sum() // 2, contradicted_scans(clash).sum()]
        hidden[kind] = np.array(fractions)
        q = np.quantile(hidden[kind], [0.01, 0.5, 0.99]) * 100
        cells = [f"{c[0]}/{len(fractions)} · {c[1]} · {c[2]}" for c in counts]
        rows.append([f"{kind} {n} × {seeds} seeds", len(fractions), " / ".join(f"{x:.1f}" for x in q), *cells])
        print(rows[-1], flush=True)
    stations = np.concatenate([h for kind, h in hidden.items() if kind != "fragments"])
    return rows, float(np.ceil(np.quantile(stations, STATIONS_PASSING) * 1000) / 1000)


FRAGMENT_SEEDS = 6
"""Generated 12-fragment scenes of the fragments' range-image table."""


def _fragment_image_rows() -> list[list]:
    """Every ordered pair of generated fragments (``FRAGMENT_SEEDS`` scenes) with ``MIN_IN_VIEW`` points of one in
    cells the other observed: the fraction in front of its surface at the true pose (right) and with the second
    turned 90° or 180° about the vertical through the first's viewpoint (wrong), on the per-pair check's range image
    and on the overrule's coarser one."""
    images = (("per-pair check", BIN_DEG, MARGIN_VOXELS), ("overrule", COARSE_BIN_DEG, COARSE_MARGIN_VOXELS))
    found = {(name, kind): [] for name, _, _ in images for kind in ("right", "wrong")}
    rng = np.random.default_rng(0)
    for seed in range(FRAGMENT_SEEDS):
        scene = make_scene("fragments", 12, seed=seed)
        grids = [_grid(P, scene.voxel) for P in scene.scans]
        for a in range(len(grids)):
            built = {name: range_image(grids[a], bins) for name, bins, _ in images}
            for b in range(len(grids)):
                if a == b:
                    continue
                T = np.linalg.solve(scene.poses[a], scene.poses[b])
                vertical = inv_T(scene.poses[a])[:3, :3] @ np.array([0.0, 0.0, np.radians(rng.choice([90.0, 180.0]))])
                for kind, T_ab in (("right", T), ("wrong", _turned(np.eye(4), vertical, np.zeros(3)) @ T)):
                    moved = grids[b] @ T_ab[:3, :3].T + T_ab[:3, 3]
                    for name, bins, margin in images:
                        seen, fraction = seen_in_front_of(built[name], moved, scene.voxel, margin, bins)
                        if seen >= MIN_IN_VIEW:
                            found[name, kind].append(fraction)
    rows = []
    for name, bins, margin in images:
        row = [f"{name}: {bins:g}° cells, {margin:g} voxels"]
        for kind in ("right", "wrong"):
            x = np.array(found[name, kind])
            row += [
                len(x),
                " / ".join(f"{q:.3f}" for q in np.quantile(x, [0.5, 0.9, 0.99])),
                f"{np.mean(x > CONFLICT):.3f}",
            ]
        rows.append(row)
        print(rows[-1], flush=True)
    return rows


def _turned(T: np.ndarray, rotvec: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Pose ``T`` turned by ``rotvec`` about its own origin (the viewpoint) and moved by ``shift`` in the world."""
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(rotvec).as_matrix()
    out[:3, 3] += shift
    return out


def _placement_row(kind: str, n: int, seed: int, draws: int) -> list:
    scene = make_scene(kind, n, seed=seed)
    grids = [_grid(P, scene.voxel) for P in scene.scans]
    checked = np.ones(n, dtype=bool)

    def blamed(poses: np.ndarray) -> np.ndarray:
        return contradicted_scans(placement_conflicts(grids, poses, checked, scene.voxel))

    rng = np.random.default_rng(0)
    cells = []
    for most in RIGHT_TURNS:
        hits = 0
        for _ in range(draws):
            axes = rng.normal(size=(n, 3))
            axes *= np.radians(rng.uniform(0, most, n) / np.linalg.norm(axes, axis=1))[:, None]
            hits += bool(blamed(np.stack([_turned(T, a, np.zeros(3)) for T, a in zip(scene.poses, axes)])).any())
        cells.append(f"{hits}/{draws}")
    for _, angle, move in MISPLACED:
        hits = 0
        for _ in range(draws):
            k, heading = int(rng.integers(n)), rng.uniform(0, 2 * np.pi)
            poses = scene.poses.copy()
            vertical = inv_T(poses[k])[:3, :3] @ np.array([0.0, 0.0, np.radians(angle)])
            poses[k] = _turned(poses[k], vertical, move * np.array([np.cos(heading), np.sin(heading), 0.0]))
            hits += bool(blamed(poses)[k])
        cells.append(f"{hits}/{draws}")
    return [f"{kind} {n}/{seed}", *cells]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", nargs=2, action="append", default=[], metavar=("SCENE", "OUT"))
    ap.add_argument("--real", type=Path)
    ap.add_argument("--placements", action="store_true")
    ap.add_argument("--draws", type=int, default=20)
    ap.add_argument("--viewpoints", action="store_true")
    args = ap.parse_args()
    if args.viewpoints:
        rows, bar = _viewpoint_rows()
        columns = [
            "generated scans",
            "scans",
            "own points hidden % (1 / 50 / 99 % of scans)",
            *[
                f"hiding ≤ {b:.1%}: seen from origin · pairs in conflict at GT · scans blamed at GT"
                for b in (LOOSER_BAR, SELF_HIDDEN)
            ],
        ]
        print(f"the bar the stations calibrate: {bar:.1%} hidden ({STATIONS_PASSING:.0%} of them at or under it)")
        save(
            "free_space_viewpoints",
            rows,
            columns,
            section="Other",
            title="Which scans the free space can speak for: stations and fused RGB-D fragments",
        )
        save(
            "free_space_fragments",
            _fragment_image_rows(),
            [
                "range image",
                "right pairs",
                "right: in front 50 / 90 / 99 %",
                f"right: share above {CONFLICT}",
                "wrong pairs",
                "wrong: in front 50 / 90 / 99 %",
                f"wrong: share above {CONFLICT}",
            ],
            section="Other",
            title="Generated RGB-D fragments' free space on a fine and a coarse range image",
        )
    if args.placements:
        columns = [
            "scene",
            *[f"right model, every scan turned ≤ {most:g}°: draws with a scan blamed" for most in RIGHT_TURNS],
            *[f"one scan {what}: it is blamed" for what, _, _ in MISPLACED],
        ]
        rows = []
        for kind, n, seed in PLACEMENT_SCENES:
            rows.append(_placement_row(kind, n, seed, args.draws))
            print(rows[-1], flush=True)
        save(
            "free_space_placements",
            rows,
            columns,
            section="Other",
            title="The free space between placed scans: right models turned a little, misplaced scans",
        )
    if args.run:
        print(
            f"| run | right pairs | conflict of right: 10/50/90/100 % | right above {CONFLICT} | wrong pairs | "
            f"conflict of wrong: 10/50/90/100 % | wrong above {CONFLICT} |"
        )
        print("|---|---|---|---|---|---|---|")
        for scene, out in args.run:
            r = _run_row(Path(scene), Path(out))
            print(
                f"| {r['run']} | {len(r['right'])} | {_quantiles(r['right'])} | {(r['right'] > CONFLICT).sum()} | "
                f"{len(r['wrong'])} | {_quantiles(r['wrong'])} | {(r['wrong'] > CONFLICT).sum()} |"
            )
    if args.real:
        print("\n| scans | count | own points hidden: min / median / max | seen from origin (checked) |")
        print("|---|---|---|---|")
        for folder, voxel in REAL:
            if (args.real / folder).is_dir():
                print(_real_row(args.real, folder, voxel))


if __name__ == "__main__":
    main()
