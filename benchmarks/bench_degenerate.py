"""Degenerate pairs (``registration.information.free_directions``): how many directions the test leaves free on
pairs aligned at their ground truth, by geometry.

    python benchmarks/bench_degenerate.py [--data ../shared/data] [--rooms 4] [--buildings 2] [--max-pairs 60]

Every pair of a scene whose GT overlap (mean of both directions, points within 2 voxels) is at least 0.3, 3DMatch's
own threshold for a benchmark pair (at most ``--max-pairs`` a scene, evenly spaced), is aligned by the refinement a
run uses (``refine.multiscale_icp`` from the GT relative pose) and ``registration_information`` counts its free
directions on the finest level, as a refined edge's are counted in a run. The voxel is a run's default
(``features.local.default_voxel``). Generated: furnished rooms (every direction fixed by the furniture) and
buildings (rooms along bare corridors: a corridor segment seen alone leaves its axis free); real: the kitchen, the
bunny and the three 3DMatch scenes of ``--data``. The table: pairs, and how many leave 0, 1, 2, or 3 and more
directions free, with the commit of the ``sghr_gtsam`` imported (run it with ``PYTHONPATH`` set to another checkout
to measure that one's rule).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import sghr_gtsam  # noqa: E402
from benchmarks._results import commit, save  # noqa: E402
from data_tools.gt_overlap import overlap_matrix  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402
from sghr_gtsam.features.local import default_voxel  # noqa: E402
from sghr_gtsam.io.poses import read_poses  # noqa: E402
from sghr_gtsam.io.scans import load_scan  # noqa: E402
from sghr_gtsam.registration.information import registration_information  # noqa: E402
from sghr_gtsam.registration.refine import LEVEL_DISTANCE, build_pyramid, multiscale_icp  # noqa: E402
from sghr_gtsam.se3 import inv_T  # noqa: E402
from sghr_gtsam.synthetic import make_scene  # noqa: E402

MIN_OVERLAP = 0.3
REAL = ("kitchen", "bunny", "3dmatch-scenes/home_at", "3dmatch-scenes/hotel_uc", "3dmatch-scenes/studyroom")


def free_counts(scans: list[np.ndarray], poses: np.ndarray, max_pairs: int) -> list[int]:
    """Free directions of each overlapping pair (module doc) of ``scans`` (own frames) at GT ``poses``."""
    voxel = default_voxel(scans)
    overlap = overlap_matrix(scans, poses, 2 * voxel, voxel, "mean", max_points=2000)
    i, j = np.nonzero(np.triu(overlap >= MIN_OVERLAP, 1))
    pick = np.unique(np.linspace(0, len(i) - 1, min(len(i), max_pairs)).round().astype(int)) if len(i) else []
    pyramids = {}
    counts = []
    for a, b in zip(i[pick].tolist(), j[pick].tolist()):
        for k in (a, b):
            if k not in pyramids:
                pyramids[k] = build_pyramid(scans[k], voxel)
        target, source = pyramids[a], pyramids[b]
        T, _, _ = multiscale_icp(target, source, inv_T(poses[a]) @ poses[b])
        finest = min(len(target.voxels), len(source.voxels)) - 1
        info = registration_information(
            target.level(finest), source.level(finest), T, LEVEL_DISTANCE[finest] * target.voxels[finest]
        )
        counts.append(-1 if info is None else info.free)
    return counts


def _real(folder: Path) -> tuple[list[np.ndarray], np.ndarray]:
    gt = folder / "gt_poses.txt" if (folder / "gt_poses.txt").exists() else folder / "gt" / "gt_poses.txt"
    names, poses = read_poses(gt)
    return [np.asarray(load_scan(folder / n), dtype=np.float64) for n in names], poses


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=data_root())
    ap.add_argument("--rooms", type=int, default=4, help="generated rooms of 8 scans (seeds 0, 1, ...)")
    ap.add_argument("--buildings", type=int, default=2, help="generated buildings of 30 scans (seeds 0, 1, ...)")
    ap.add_argument("--max-pairs", type=int, default=60, help="pairs a scene at most")
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args(argv)
    sets: list[tuple[str, list[list[int]]]] = []
    rooms = [make_scene("room", 8, seed) for seed in range(args.rooms)]
    sets.append(
        (
            f"generated rooms ({args.rooms} × 8 scans)",
            [free_counts(list(s.scans), s.poses, args.max_pairs) for s in rooms],
        )
    )
    buildings = [make_scene("building", 30, seed) for seed in range(args.buildings)]
    sets.append(
        (
            f"generated buildings ({args.buildings} × 30 scans)",
            [free_counts([np.asarray(p) for p in s.scans], s.poses, args.max_pairs) for s in buildings],
        )
    )
    for name in REAL:
        if (args.data / name).is_dir():
            sets.append((Path(name).name, [free_counts(*_real(args.data / name), args.max_pairs)]))
        else:
            print(f"{name}: not in {args.data}, skipped", file=sys.stderr)
    rule = commit(Path(sghr_gtsam.__file__).resolve().parents[1])
    columns = ["set", "rule at", "pairs", "0 free", "1 free", "2 free", "3+ free", "no information"]
    rows = []
    for label, per_scene in sets:
        c = np.concatenate([np.asarray(x, dtype=int) for x in per_scene]) if per_scene else np.zeros(0, int)
        rows.append(
            [
                label,
                rule,
                int(len(c)),
                *(int(np.sum(c == k)) for k in (0, 1, 2)),
                int(np.sum(c >= 3)),
                int(np.sum(c < 0)),
            ]
        )
    print("| " + " | ".join(columns) + " |\n|" + "---|" * len(columns))
    for row in rows:
        print("| " + " | ".join(str(x) for x in row) + " |")
    if not args.no_save:
        save(
            "degenerate",
            rows,
            columns,
            section="Covariances",
            title="Free directions of pairs aligned at their ground truth",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
