"""Free space (registration.visibility): how the conflict separates right registrations from wrong ones, and which
scans the check can see at all.

    python benchmarks/bench_free_space.py --run SCENE OUT [--run SCENE OUT ...] [--real DATA]

``--run``: a generated scene (``gt_poses.txt`` beside its scans) and a finished run of it (OUT with edges.csv,
graph.g2o, graph_rejected.g2o, report.json; with or without the check). Every registered pair (status other than
failed) is scored against GT (right: within 5° / 0.2 m) and its ``free_space_conflict`` computed on the scans' grids
at the run's voxel; the table gives the conflict's quantiles for right and wrong pairs, and how many of each lie above
``visibility.CONFLICT``. ``--real``: the shared data folder; per scene, how many scans ``seen_from_origin`` accepts
and the fraction of its own points each hides (the test the check needs before it says anything).
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

from sghr_gtsam.io.poses import read_poses  # noqa: E402
from sghr_gtsam.io.scans import list_scans, load_scan  # noqa: E402
from sghr_gtsam.registration.visibility import (  # noqa: E402
    CONFLICT,
    SELF_HIDDEN,
    free_space_conflict,
    hidden_fraction,
)
from sghr_gtsam.se3 import inv_T, relative_errors  # noqa: E402

MAX_DEG, MAX_TRANS = 5.0, 0.2
REAL = (
    ("kitchen", 0.025),
    ("bunny", 0.002),
    ("3dmatch-scenes/home_at", 0.025),
    ("3dmatch-scenes/hotel_uc", 0.025),
    ("3dmatch-scenes/studyroom", 0.025),
)


def _grid(path: Path, voxel: float) -> np.ndarray:
    P = np.asarray(load_scan(path), dtype=np.float64)
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
            grids[k] = _grid(scene / names[k], voxel)
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
    h = np.array([hidden_fraction(_grid(path, voxel), voxel) for path in list_scans(data / folder)])
    return (
        f"| {folder} | {len(h)} | {h.min():.3f} / {np.median(h):.3f} / {h.max():.3f} | "
        f"{int((h <= SELF_HIDDEN).sum())} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", nargs=2, action="append", default=[], metavar=("SCENE", "OUT"))
    ap.add_argument("--real", type=Path)
    args = ap.parse_args()
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
