"""End-to-end runs on the real scenes: per-stage seconds, peak memory and accuracy against GT.

    python benchmarks/bench_pipeline.py [--data ../shared/data] [--scenes kitchen bunny]

Each scene runs in its own process so peak memory is the scene's own. Targets: ≤ 15 s and
≤ 3 GB per scene; kitchen: registration recall 100 %, ≥ 8/9 scans within 5°/0.2 m; bunny: 10/10 within 1°/1 mm.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # data_tools
from data_tools.scene_gt import data_root  # noqa: E402

CHILD = r"""
import json, sys
from pathlib import Path
from sghr_gtsam.config import Config
from sghr_gtsam.evaluate import fragment_id, registration_recall, scan_errors
from sghr_gtsam.io.poses import read_gt_info, read_gt_log, read_poses
from sghr_gtsam.pipeline import run
from sghr_gtsam.result import peak_memory_mb

scene_dir, gt_dir, out = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
res = run(scene_dir, out, Config(), log=lambda m: None)
names, gt = read_poses(gt_dir / "gt_poses.txt")
err = scan_errors(res.names, res.poses, gt[[names.index(n) for n in res.names]])
row = {"timings": res.timings, "peak_mb": peak_memory_mb(), "n": len(res.names),
       "pairs": res.graph.num_edges, "unregistered": res.unregistered,
       "rot": err.rotation_deg.tolist(), "trans": err.translation.tolist(),
       "registered": res.registered}
if (gt_dir / "gt.log").exists():
    keep = res.registered
    rr = registration_recall([fragment_id(res.names[k]) for k in keep], res.poses[keep],
                             read_gt_log(gt_dir / "gt.log"), read_gt_info(gt_dir / "gt.info"))
    row["recall"] = rr.recall
print(json.dumps(row))
"""

SCENES = {"kitchen": ("kitchen", "kitchen/gt", 5.0, 0.2), "bunny": ("bunny", "bunny", 1.0, 0.001)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=data_root())
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    args = ap.parse_args()
    stages = ["load", "features", "global_graph", "pairwise", "sync", "write", "total"]
    print(
        "| scene | scans | pairs | "
        + " | ".join(f"{s} s" for s in stages)
        + " | peak MB | within tol | worst rot ° | worst trans | recall | unregistered |"
    )
    print("|---" * (len(stages) + 9) + "|")
    for name in args.scenes:
        scene, gt, max_deg, max_t = SCENES[name]
        with tempfile.TemporaryDirectory() as out:
            proc = subprocess.run(
                [sys.executable, "-c", CHILD, str(args.data / scene), str(args.data / gt), out],
                capture_output=True,
                text=True,
                cwd=ROOT,
            )
        if proc.returncode:
            print(f"| {name} | failed: {proc.stderr.strip().splitlines()[-1]} |")
            continue
        r = json.loads(proc.stdout.strip().splitlines()[-1])
        reg = r["registered"]
        ok = sum(r["rot"][k] <= max_deg and r["trans"][k] <= max_t for k in range(r["n"]))
        worst_rot = max(r["rot"][k] for k in reg)
        worst_t = max(r["trans"][k] for k in reg)
        t = r["timings"]
        print(
            f"| {name} | {r['n']} | {r['pairs']} | "
            + " | ".join(f"{t.get(s, 0):.2f}" for s in stages)
            + f" | {r['peak_mb']:.0f} | {ok}/{r['n']} | {worst_rot:.3f} | {worst_t:.4f} | "
            f"{r.get('recall', float('nan')):.3f} | {', '.join(r['unregistered']) or '-'} |"
        )


if __name__ == "__main__":
    main()
