"""Where refinement's GICP stops, for each step tolerance: the pairs it calls converged, and how far each stop lies
from the same ICP run to its fixed point.

    python benchmarks/bench_icp_stop.py [--data ../shared/data] [--scenes studyroom home_at] [--pairs 40]
        [--steps 0.0205 0.025 0.01 0.005] [--budgets 10] [--seed 0]

For a random sample of each scene's gt.log pairs, the GT relative pose ``T_i⁻¹ T_j`` turned by 1° and moved by
half a voxel in random directions (a synchronized guess's drift) is refined by ``refine.multiscale_icp`` with
``refine.STEP_VOXELS`` set to each step, and to small_gicp's own default (1e-3 in scene units, ``1 mm`` in the
table: on 3DMatch, metres). The fixed point is the same ICP with a step of 1e-6 voxels and 200 iterations a level.
The voxel is the run's default (``scene.scene_voxel``: 1/100 of the median scan's bounding-box diagonal).
Each step runs with each budget of iterations a level (``refine.LEVEL_ITERATIONS``; ``--budgets``). Columns: the
pairs called converged, those also within ``refine.stays_near`` of their guess (what refinement admitted until it
took a converged ICP wherever it moved, inliers aside), the pairs whose verdict differs from the 1 mm stop's at the
first budget, and the distance of each stop from the fixed point (rotation °, translation in voxels), median and 90 %.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_3dmatch, when imported from elsewhere
from bench_3dmatch import SCENES  # noqa: E402

from data_tools.scene_gt import data_root  # noqa: E402
from sghr_gtsam.evaluate import fragment_id  # noqa: E402
from sghr_gtsam.io.poses import read_gt_log, read_poses  # noqa: E402
from sghr_gtsam.io.scans import list_scans, load_scan  # noqa: E402
from sghr_gtsam.registration import refine  # noqa: E402
from sghr_gtsam.scene import scene_voxel  # noqa: E402
from sghr_gtsam.se3 import inv_T, relative_errors  # noqa: E402
from sghr_gtsam.types import ScanStats  # noqa: E402


def _stop(pyramid_i, pyramid_j, T0: np.ndarray, step: float, iterations: tuple[int, int]) -> tuple[np.ndarray, bool]:
    refine.STEP_VOXELS, refine.LEVEL_ITERATIONS = step, iterations
    T, converged, _ = refine.multiscale_icp(pyramid_i, pyramid_j, T0)
    return T, converged


def scene_rows(data: Path, name: str, pairs: int, steps: list[float], budgets: list[int], seed: int) -> list[str]:
    scene = SCENES[name]
    paths = list_scans(data / scene.folder)
    points = [load_scan(p) for p in paths]
    voxel = scene_voxel(None, [ScanStats.of(P) for P in points])
    gt_names, gt = read_poses(data / scene.gt_poses)
    poses = np.array([gt[gt_names.index(p.name)] for p in paths])
    rng = np.random.default_rng(seed)
    index = {fragment_id(p.name): k for k, p in enumerate(paths)}  # gt.log names fragments by number
    log = sorted(
        (index[a], index[b]) for a, b in read_gt_log(data / scene.gt_dir / "gt.log") if a in index and b in index
    )
    sample = [log[k] for k in rng.permutation(len(log))[:pairs]]
    pyramids = {}
    defaults = refine.STEP_VOXELS, refine.LEVEL_ITERATIONS
    labelled = [
        (f"{label}, {b}", step, b)
        for b in budgets
        for label, step in [("1 mm", 1e-3 / voxel)] + [(f"{s:g} v", s) for s in steps]
    ]
    stops = {label: [] for label, _, _ in labelled}
    for i, j in sample:
        for k in (i, j):
            if k not in pyramids:
                pyramids[k] = refine.build_pyramid(points[k], voxel)
        turn = Rotation.from_rotvec(np.radians(1.0) * _unit(rng)).as_matrix()
        drift = np.eye(4)
        drift[:3, :3], drift[:3, 3] = turn, 0.5 * voxel * _unit(rng)
        T0 = inv_T(poses[i]) @ poses[j] @ drift
        fixed, _ = _stop(pyramids[i], pyramids[j], T0, 1e-6, (200, 200))
        for label, step, budget in labelled:
            T, converged = _stop(pyramids[i], pyramids[j], T0, step, (budget, budget))
            deg, apart = relative_errors(T, fixed)
            stops[label].append((converged, converged and refine.stays_near(T, T0, voxel), deg, apart / voxel))
    refine.STEP_VOXELS, refine.LEVEL_ITERATIONS = defaults
    base = [c for c, _, _, _ in stops[labelled[0][0]]]
    rows = []
    for label, step, _ in labelled:
        r = np.array(stops[label], dtype=float)
        flips = sum(bool(c) != b for c, b in zip(r[:, 0], base))
        rows.append(
            f"| {name} | {label} | {step:.4f} | {int(r[:, 0].sum())}/{len(r)} | {int(r[:, 1].sum())} | {flips} | "
            f"{np.median(r[:, 2]):.3f} / {np.percentile(r[:, 2], 90):.3f} | "
            f"{np.median(r[:, 3]):.3f} / {np.percentile(r[:, 3], 90):.3f} |"
        )
    print(f"{name}: voxel {voxel:.4f}, {len(sample)} of {len(log)} gt.log pairs", file=sys.stderr)
    return rows


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=data_root())
    ap.add_argument(
        "--scenes", nargs="+", default=["studyroom", "home_at"], choices=[n for n, s in SCENES.items() if s.gt_dir]
    )
    ap.add_argument("--pairs", type=int, default=40)
    ap.add_argument("--steps", nargs="+", type=float, default=[0.0205, 0.025, 0.01, 0.005], help="in voxels")
    ap.add_argument("--budgets", nargs="+", type=int, default=[10], help="iterations a level")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    missing = [n for n in args.scenes if not (args.data / SCENES[n].folder).is_dir()]
    if missing:
        raise SystemExit(f"no scene folder for {', '.join(missing)} under {args.data}")
    print(
        "| scene | step, iterations a level | step (voxels) | converged | and near the guess | verdicts unlike the "
        "first row's | from the fixed point: ° median / 90 % | voxels median / 90 % |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name in args.scenes:
        for row in scene_rows(args.data, name, args.pairs, args.steps, args.budgets, args.seed):
            print(row, flush=True)


if __name__ == "__main__":
    main()
