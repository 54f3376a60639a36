"""The executors against each other: in this process, the process pool and a local Ray instance.

    python benchmarks/bench_executors.py [--scans 20] [--scene DIR] [--repeats 1]

Runs ``pipeline.run`` on one scene (default: a generated room of ``--scans`` scans; ``--scene``: a folder of
scans) once per backend, each in a fresh process so that every row pays its own start-up (the fork server's
imports, ``ray.init`` and the actors' imports). Prints per backend the wall seconds of the run (without the
command's Python imports), the seconds of the stages that run on the executor, and the largest difference of
any pose entry to the in-process run (0: bit-identical). ``--workers 1`` runs the stages in this process (there
is no pool of one), so the rows are: in-process, pool of 2, Ray with 1 CPU and Ray with 2 CPUs.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PARALLEL = (
    "features",
    "pairwise",
    "pyramids",
    "refine",
    "loops",
    "retry",
)  # the stages that run through executor.parallel_map

CHILD = r"""
import json, sys, time
from sghr_gtsam.config import Config
from sghr_gtsam.pipeline import run

scene, out, workers, ray = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] or None
started = time.perf_counter()
res = run(scene, out, Config(workers=workers, ray=ray, record=False), log=lambda m: None)
wall = time.perf_counter() - started
print(json.dumps({"wall": wall, "timings": res.timings, "poses": res.poses.tolist(), "names": res.names}))
"""

BACKENDS = [
    ("in-process (--workers 1)", 1, ""),
    ("process pool, 2 workers", 2, ""),
    ("Ray local, 1 CPU", 1, "local"),
    ("Ray local, 2 CPUs", 2, "local"),
]


def _load() -> str:
    return f"{os.getloadavg()[0]:.1f}"


def _run(scene: Path, workers: int, ray: str) -> dict:
    with tempfile.TemporaryDirectory() as out:
        env = {**os.environ, "PYTHONPATH": str(ROOT)}
        proc = subprocess.run(
            [sys.executable, "-c", CHILD, str(scene), str(Path(out) / "out"), str(workers), ray],
            capture_output=True,
            text=True,
            cwd=ROOT,
            env=env,
        )
    if proc.returncode:
        raise SystemExit(f"{workers} workers, ray={ray!r} failed: {proc.stderr.strip()[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=20, help="scans of the generated room (without --scene)")
    ap.add_argument("--scene", type=Path, help="a folder of scans instead of the generated room")
    ap.add_argument("--repeats", type=int, default=1, help="runs per backend; the table gives the median")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        scene = args.scene
        if scene is None:
            from sghr_gtsam.synthetic import make_scene, write_scene

            scene = Path(tmp) / "scene"
            write_scene(make_scene("room", args.scans), scene)
        print(f"scene: {args.scene or f'generated room, {args.scans} scans'}; {os.cpu_count()} cores")
        print(
            "| backend | wall s | executor stages s (" + " + ".join(PARALLEL) + ") | max pose difference "
            "to in-process | load before / after |"
        )
        print("|---|---|---|---|---|")
        reference = None
        for label, workers, ray in BACKENDS:
            load = _load()
            rows = [_run(scene, workers, ray) for _ in range(args.repeats)]
            poses = np.array(rows[0]["poses"])
            if any(not np.array_equal(np.array(r["poses"]), poses) for r in rows[1:]):
                print(f"| {label} | runs of one backend differ |")
            reference = poses if reference is None else reference
            wall = np.median([r["wall"] for r in rows])
            stages = np.median([sum(r["timings"].get(s, 0.0) for s in PARALLEL) for r in rows])
            diff = float(np.abs(poses - reference).max())
            print(f"| {label} | {wall:.1f} | {stages:.1f} | {diff:.3g} | {load} / {_load()} |", flush=True)


if __name__ == "__main__":
    main()
