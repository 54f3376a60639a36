"""End to end with precomputed features: the SGHR authors' YOHO keypoints + descriptors and their NetVLAD
overlap head on 3DMatch kitchen fragments 0-5, scored against GT and against the authors' own poses.

    python benchmarks/bench_precomputed.py [--data ../shared/data]

Runs the command line once on the kitchen folder (fragments 6, 21 and 34 have no features, so they are
skipped); the wall time includes Python's imports. Prints per-scan errors relative to cloud_bin_0, the
worst error over all 15 pairs, the per-stage seconds of report.json and the largest difference between
our overlap scores (in the authors' form) and theirs (multi_reg/overlap.txt).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from sghr_gtsam.evaluate import scan_errors
from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.se3 import inv_T, relative_errors

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # data_tools
from data_tools.scene_gt import data_root  # noqa: E402


def worst_pair(poses: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    i, j = np.triu_indices(len(poses), 1)
    rot, trans = relative_errors(inv_T(poses[i]) @ poses[j], inv_T(gt[i]) @ gt[j])
    return float(rot.max()), float(trans.max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=data_root())
    args = ap.parse_args()
    ref = args.data / "sghr-reference"
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        cmd = [
            sys.executable,
            "-m",
            "sghr_gtsam",
            "run",
            str(args.data / "kitchen"),
            "--out",
            str(out),
            "--features",
            str(ref),
            "--overlap-head",
            str(ref / "netvlad_overlap_model_best.pth"),
        ]
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        wall = time.perf_counter() - t0
        if proc.returncode:
            sys.exit(f"run failed: {proc.stderr.strip()}")
        report = json.loads((out / "report.json").read_text())
        names, poses = read_poses(out / "poses.txt")
        with open(out / "edges.csv") as f:
            edges = list(csv.DictReader(f))

    gt_names, gt = read_poses(args.data / "kitchen" / "gt" / "gt_poses.txt")
    gt = gt[[gt_names.index(n) for n in names]]
    theirs = np.stack([np.loadtxt(ref / "multi_reg" / f"{Path(n).stem}.pose.txt") for n in names])
    ours_gt, theirs_gt = scan_errors(names, poses, gt), scan_errors(names, theirs, gt)
    ours_theirs = scan_errors(names, poses, theirs)

    print("| scan | ours vs GT | authors vs GT | ours vs authors |")
    print("|---|---|---|---|")

    def cell(r: float, t: float) -> str:
        return f"{r:.2f}° / {100 * t:.1f} cm"

    for k, n in enumerate(names[1:], 1):
        cells = [cell(e.rotation_deg[k], e.translation[k]) for e in (ours_gt, theirs_gt, ours_theirs)]
        print(f"| {Path(n).stem} | " + " | ".join(cells) + " |")
    worst = [worst_pair(poses, gt), worst_pair(theirs, gt), worst_pair(poses, theirs)]
    print("| worst of the 15 pairs | " + " | ".join(cell(*w) for w in worst) + " |")

    overlap = np.loadtxt(ref / "multi_reg" / "overlap.txt")
    diff = max(abs(1.0 - np.sqrt(1.0 - float(e["overlap_score"])) - overlap[int(e["i"]), int(e["j"])]) for e in edges)
    seconds = ", ".join(f"{k} {v:.2f}" for k, v in report["seconds"].items())
    print(
        f"\nregistered {len(names)}/{len(report['scans'])}, skipped {', '.join(report['skipped'])}; "
        f"edges kept {report['edges_kept']}/{len(edges)}; overlap scores vs the authors' max |diff| {diff:.1e}"
    )
    print(f"seconds: {seconds}; command wall time {wall:.1f} s; peak {report['peak_memory_mb']:.0f} MB")


if __name__ == "__main__":
    main()
