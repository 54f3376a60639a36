"""Resume after SIGKILL on a large generated scene: how much work a killed run loses.

    python benchmarks/bench_resume.py [--scans 500] [--kind building] [--kill-at 0.5] [--workers 2] [--workdir DIR]
    python benchmarks/bench_resume.py --scene SCENE --reference OUT --kill-at 0.2   # a kept bench_scale run

Writes a generated scene (``synthetic.make_scene``), runs ``python -m sghr_gtsam run`` on it once uninterrupted
(the reference, into an empty folder), then again into another folder and kills that run's whole process group with
SIGKILL once ``--kill-at`` of the reference's pair registrations are finished entries of ``OUT/cache/pairs``, as a
job scheduler would; then starts it again. Prints the pairs done before the kill, the pairs the second run computed,
those it computed again although they were finished before the kill (the goal: under 5 % of all pairs), the seconds
of each run and whether the resumed poses equal the reference's byte for byte.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sghr_gtsam.io.results import CACHE  # noqa: E402
from sghr_gtsam.synthetic import make_scene, write_scene  # noqa: E402

ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}


def _cli(scene: Path, out: Path, workers: int, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "sghr_gtsam",
        "run",
        str(scene),
        "--out",
        str(out),
        "--workers",
        str(workers),
        "--no-record",
        "--quiet",
        *extra,
    ]


def _entries(folder: Path) -> int:
    """Finished entries (a write in progress has a hidden temporary name)."""
    return len([p for p in folder.glob("*.npz") if not p.name.startswith(".")]) if folder.is_dir() else 0


def _timed(cmd: list[str]) -> float:
    started = time.perf_counter()
    done = subprocess.run(cmd, env=ENV, capture_output=True, text=True)
    if done.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    return time.perf_counter() - started


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=500)
    ap.add_argument("--kind", default="building", help="synthetic.make_scene kind")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--kill-at", type=float, default=0.5, help="fraction of the pairs finished when the run is killed")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--workdir", type=Path, default=None, help="where the scene and runs go (default: a temporary folder)"
    )
    ap.add_argument("--scene", type=Path, help="an existing scene folder instead of generating one")
    ap.add_argument(
        "--reference",
        type=Path,
        help="with --scene: a finished run of it made with this benchmark's "
        "command and a fresh cache (bench_scale.py --keep writes one), instead of running it again",
    )
    args = ap.parse_args()
    if args.reference and not args.scene:
        ap.error("--reference needs --scene")
    if args.workdir:
        args.workdir.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(dir=args.workdir, prefix="bench_resume-"))
    print(f"load before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    try:
        scene = args.scene or work / "scene"
        if not args.scene:
            write_scene(make_scene(kind=args.kind, n_scans=args.scans, seed=args.seed), scene)
        ref = args.reference or work / "ref"
        reference_s = float("nan") if args.reference else _timed(_cli(scene, ref, args.workers))  # fresh cache
        total = json.loads((ref / "report.json").read_text())["cache"]["pairs"]["computed"]

        out = work / "out"
        pairs = out / CACHE / "pairs"
        started = time.perf_counter()
        proc = subprocess.Popen(
            _cli(scene, out, args.workers),
            env=ENV,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        try:
            while proc.poll() is None and _entries(pairs) < args.kill_at * total:
                time.sleep(0.05)
        finally:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        killed_s = time.perf_counter() - started
        done = _entries(pairs)
        resumed_s = _timed(_cli(scene, out, args.workers))
        cache = json.loads((out / "report.json").read_text())["cache"]
        same = (out / "poses.txt").read_bytes() == (ref / "poses.txt").read_bytes()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    computed = cache["pairs"]["computed"]
    again = computed - (total - done)
    print(f"load after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print(
        "| scans | pair registrations | finished before the kill | computed by the resumed run | computed "
        "again | reference s | killed after s | resumed s | poses identical |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    print(
        f"| {len(list(scene.glob('*.ply')))} | {total} | {done} | {computed} | {again} ({again / total:.1%}) | "
        f"{reference_s:.0f} | "
        f"{killed_s:.0f} | {resumed_s:.0f} | {'yes' if same else '**no**'} |"
    )
    print(f"\ncache of the resumed run: {json.dumps(cache)}")


if __name__ == "__main__":
    main()
