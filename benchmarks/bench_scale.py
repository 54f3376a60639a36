"""Scale: generated buildings of N scans end to end; how the seconds grow with N·k, the memory, and how
many scans land on GT.

    python benchmarks/bench_scale.py [--scans 100 500 2000] [--kind building] [--workers 2] [--workdir DIR] [--keep]

For each N: ``synthetic.make_scene(kind, N)`` written scan by scan (``synthetic.building``: rooms along corridors,
each scan overlapping a bounded number of others), then one ``python -m sghr_gtsam run SCENE --out OUT --workers W
--no-record --quiet`` measured as ``benchmarks/bench_memory.py`` measures (``/usr/bin/time -v`` for the largest
process, the process tree's RSS and PSS sampled every 0.2 s, CPU seconds of every process). From OUT/report.json:
the seconds of each stage and the pairs. Against GT (``evaluate.score_run``): scans placed, scans within 5° / 0.2 m
after one rigid alignment fitted to the positions of the trusted scans (the verified scans of the world part,
``Verdict.trusted``; ``SceneScore.certain``; to every placed scan when fewer than 3 are trusted), trusted scans outside
that (``SceneScore.unflagged_wrong``: placed wrongly as if certain), ATE rmse and median rotation error of the scans
aligned on, and the doubts by reason. The parts: how many, the scans in parts of two or more, the largest, and the
scans outside the largest rigid piece of their own part (``evaluate.score_parts`` at 5° / 0.2 m) with those of them
the run verified.
Then a log-log fit of the total seconds against N·k (the exponent: 1 is linear) and, for a multi-machine plan, the
cost of a pair (pairwise seconds × workers / pairs registered by the pairwise stage) and the data volumes (scan files,
OUT/cache).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_memory import measured_run  # noqa: E402

from benchmarks._results import save  # noqa: E402
from sghr_gtsam.evaluate import score_parts, score_run  # noqa: E402
from sghr_gtsam.io.poses import read_poses  # noqa: E402
from sghr_gtsam.result import DOUBTS  # noqa: E402
from sghr_gtsam.synthetic import make_scene, write_scene  # noqa: E402
from sghr_gtsam.verify import Verdict  # noqa: E402

MAX_DEG, MAX_TRANS = 5.0, 0.2
STAGES = (
    "features",
    "global_graph",
    "pairwise",
    "free_space",
    "sync",
    "refine",
    "loops",
    "retry",
    "groups",
    "verify",
    "write",
)


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _score(scene: Path, out: Path, report: dict) -> dict:
    """The run's poses against GT (module doc)."""
    gt_names, gt = read_poses(scene / "gt_poses.txt")
    names, poses = read_poses(out / "poses.txt")
    score = score_run(
        names,
        poses,
        gt_names,
        gt,
        unregistered=report["unregistered"],
        flagged=set(names) - set(Verdict.from_dict(report).trusted()),
        max_deg=MAX_DEG,
        max_trans=MAX_TRANS,
    )
    parts = [p["scans"] for p in report["parts"]]
    gt_by_name = dict(zip(gt_names, gt))
    truth = np.stack([gt_by_name[n] for n in names])
    by_part = score_parts(names, poses, truth, parts, report["doubts"], MAX_DEG, MAX_TRANS)
    whole = score.certain or score.whole  # every placed scan flagged: aligned on all of them
    basis = np.array([n not in set(score.flagged) for n in score.placed]) if score.certain else slice(None)
    return {
        "placed": len(score.placed),
        "within": int(whole.within(MAX_DEG, MAX_TRANS).sum()),
        "wrong_unflagged": len(score.unflagged_wrong),
        "ate": float(np.sqrt(np.mean(whole.translation[basis] ** 2))),
        "median_deg": float(np.median(whole.rotation_deg[basis])),
        "flags": {reason: list(report["doubts"].values()).count(reason) for reason in DOUBTS},
        "parts": len(parts),
        "in_parts": sum(len(p) for p in parts if len(p) > 1),
        "largest_part": max((len(p) for p in parts), default=0),
        "misplaced": len(by_part.misplaced),
        "misplaced_verified": len(set(by_part.misplaced) - set(by_part.doubted)),
    }


def _case(n: int, args: argparse.Namespace, work: Path) -> dict:
    scene, out = work / f"scene_{n}", work / f"out_{n}"
    started = time.perf_counter()
    write_scene(make_scene(args.kind, n, seed=args.seed), scene)
    generated = time.perf_counter() - started
    run = measured_run(scene, out, "--workers", str(args.workers))
    report = json.loads((out / "report.json").read_text())
    # The pairwise stage's (top-k) pairs: the cache's pair registrations but the retry stage's.
    stage_pairs = sum(report["cache"]["pairs"].values()) - report["front_end"]["retry_tried"]
    row = {
        "n": n,
        "k": report["parameters"]["k"],
        "generate_s": generated,
        **run,
        **_score(scene, out, report),
        "stage_pairs": stage_pairs,
        "pair_s": run["seconds"]["pairwise"] * args.workers / max(stage_pairs, 1),
        "scan_mb": _bytes(scene) / 1e6,
        "cache_mb": _bytes(out / "cache") / 1e6,
    }
    if not args.keep:
        shutil.rmtree(scene)
        shutil.rmtree(out)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, nargs="+", default=[100, 500, 2000])
    ap.add_argument("--kind", default="building", help="synthetic.make_scene kind")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--workdir", type=Path, default=None, help="where scenes and runs go (default: a temporary folder)")
    ap.add_argument("--keep", action="store_true", help="keep the scenes and the runs' results")
    args = ap.parse_args()
    if args.workdir:
        args.workdir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(dir=args.workdir, prefix="bench_scale-"))
    print(
        f"load before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}; {args.kind}, seed {args.seed}, "
        f"{args.workers} workers"
    )
    try:
        rows = [_case(n, args, work) for n in args.scans]
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print(f"load after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}" + (f"; kept in {work}" if args.keep else ""))
    print()
    header = [
        "scans",
        "k",
        "generate s",
        "run wall s",
        "CPU s",
        *STAGES,
        "top-k pairs",
        "pairs registered",
        "placed",
        f"within {MAX_DEG:g}°/{MAX_TRANS:g} m",
        "unflagged wrong",
        "parts",
        "scans in parts of 2+",
        "largest part",
        "misplaced in its part",
        "of them verified",
        *DOUBTS,
        "ATE m",
        "median °",
        "largest process GB",
        "all processes PSS GB",
        "s a pair × worker",
        "scans MB",
        "cache MB",
    ]
    table = [
        [
            r["n"],
            r["k"],
            round(r["generate_s"], 1),
            round(r["wall"]),
            round(r["cpu"]),
            *(round(r["seconds"].get(s, 0.0), 1) for s in STAGES),
            r["stage_pairs"],
            r["pairs"],
            f"{r['placed']}/{r['n']} ({r['placed'] / r['n']:.0%})",
            r["within"],
            r["wrong_unflagged"],
            r["parts"],
            r["in_parts"],
            r["largest_part"],
            r["misplaced"],
            r["misplaced_verified"],
            *(r["flags"][f] for f in DOUBTS),
            round(r["ate"], 3),
            round(r["median_deg"], 2),
            round(r["max_process_gb"], 2),
            round(r["tree_pss_gb"], 2),
            round(r["pair_s"], 3),
            round(r["scan_mb"]),
            round(r["cache_mb"]),
        ]
        for r in rows
    ]
    print("| " + " | ".join(header) + " |\n" + "|---" * len(header) + "|")
    for row in table:
        print("| " + " | ".join(str(x) for x in row) + " |")
    fit = ""
    if len(rows) > 1:  # seconds = c · (N·k)^e: e from a least-squares line through the logs
        nk = np.array([r["n"] * r["k"] for r in rows], float)
        series = {
            "run wall": [r["wall"] for r in rows],
            "CPU": [r["cpu"] for r in rows],
            **{stage: [r["seconds"].get(stage, 0.0) for r in rows] for stage in ("total", *STAGES)},
        }
        exponents = [
            f"{label} {np.polyfit(np.log(nk), np.log(seconds), 1)[0]:.2f}"
            for label, seconds in series.items()
            if min(seconds) >= 0.1  # a stage that did (almost) nothing somewhere has no exponent
        ]
        fit = f"Fitted exponent e of seconds ∝ (N·k)^e over N·k = {', '.join(f'{x:g}' for x in nk)}: " + ", ".join(
            exponents
        )
        print(f"\n{fit}")
    save(
        f"scale_{args.kind}s",
        table,
        header,
        notes=fit,
        section="Scale and speed",
        title=f"Generated {args.kind}s end to end (seed {args.seed})",
    )


if __name__ == "__main__":
    main()
