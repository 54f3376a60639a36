"""Peak memory of whole runs on large scans: does it stay under 4 GB, and does it
grow with the number of scans N?

    python benchmarks/bench_memory.py [--quick] [--workdir DIR] [--keep]

Scenes are generated into a temporary folder (nothing is committed): ``synthetic.make_scene`` rooms whose scans are
densified by jittering, each point repeated with 3 mm Gaussian noise (the scene's own range noise) until the scan
holds the wanted count. Cases: (a) one 5-million-point scan among five normal ones (8-10 thousand points), (b) 100
scans of 1 million points, and the first 20 and 50 of those 100 for peak memory against N. ``--quick``: 1 million
and 20 scans of 100 thousand points (a check of the benchmark itself).

Each case is one ``python -m sghr_gtsam run`` (default workers: every core; ``--no-record``) under
``/usr/bin/time -v``, which gives the largest single process's peak (``ru_maxrss`` over the run's processes).
The machine needs the sum over the run's processes at once: that is sampled every 0.2 s with psutil, as RSS (shared
pages counted in every process: an upper bound) and PSS (shared pages split between the processes sharing them), with
the CPU seconds of every process of the run (the workers included, to within a sampling interval each).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import psutil

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sghr_gtsam.io.scans import write_scan  # noqa: E402
from sghr_gtsam.synthetic import make_scene  # noqa: E402

TARGET_GB = 4.0
JITTER = 0.003  # metres: the scenes' range noise


def _dense(points: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points: ``points`` repeated, each copy jittered by ``JITTER``."""
    picks = np.resize(np.arange(len(points)), count)
    return points[picks] + rng.normal(scale=JITTER, size=(count, 3))


def _write_scene(folder: Path, n_scans: int, counts: list[int | None], seed: int) -> int:
    """Write a room of ``n_scans`` scans, scan k densified to ``counts[k]`` points (None: as generated) as binary PLY
    (float64); returns the number of points written."""
    scene = make_scene(kind="room", n_scans=n_scans, seed=seed)
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True)
    total = 0
    for name, points, count in zip(scene.names, scene.scans, counts):
        P = points if count is None else _dense(points, count, rng)
        write_scan(folder / name, P)
        total += len(P)
    return total


def _subset(source: Path, folder: Path, n: int) -> None:
    """The first ``n`` scans of ``source``, linked."""
    folder.mkdir(parents=True)
    for path in sorted(source.glob("*.ply"))[:n]:
        os.symlink(path, folder / path.name)


def _tree_memory(proc: psutil.Process, cpu: dict[int, float]) -> tuple[float, float]:
    """Sum of RSS and of PSS (bytes) over ``proc`` and its descendants now; each one's CPU seconds so far into
    ``cpu`` (by pid: the workers are not the run's own children, so ``time`` does not count them)."""
    rss = pss = 0.0
    for p in [proc, *proc.children(recursive=True)]:
        try:
            with p.oneshot():
                info, times = p.memory_full_info(), p.cpu_times()
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
        rss += info.rss
        pss += getattr(info, "pss", info.rss)
        cpu[p.pid] = times.user + times.system
    return rss, pss


def measured_run(scene: Path, out: Path, *options: str) -> dict:
    """One ``run`` of ``scene`` into ``out`` (with ``options``) under ``/usr/bin/time -v``, its tree's memory
    sampled; peaks in GB, wall and CPU seconds, and from its report.json the scans, those registered, the pairs
    and the seconds of each stage (``benchmarks/bench_scale.py`` measures with it too)."""
    cmd = [
        "/usr/bin/time",
        "-v",
        sys.executable,
        "-m",
        "sghr_gtsam",
        "run",
        str(scene),
        "--out",
        str(out),
        "--no-record",
        "--quiet",
        *options,
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    started = time.perf_counter()
    with tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, env=env)
        watched = psutil.Process(proc.pid)
        peak_rss = peak_pss = 0.0
        cpu: dict[int, float] = {}
        while proc.poll() is None:
            rss, pss = _tree_memory(watched, cpu)
            peak_rss, peak_pss = max(peak_rss, rss), max(peak_pss, pss)
            time.sleep(0.2)
        wall = time.perf_counter() - started
        err.seek(0)
        log = err.read()
    if proc.returncode:
        raise SystemExit(f"run on {scene} failed ({proc.returncode}):\n{log[-2000:]}")
    max_rss_kb = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", log).group(1))
    report = json.loads((out / "report.json").read_text())
    return {
        "wall": wall,
        "cpu": sum(cpu.values()),
        "max_process_gb": max_rss_kb / 2**20,
        "tree_rss_gb": peak_rss / 2**30,
        "tree_pss_gb": peak_pss / 2**30,
        "registered": len(report["registered"]),
        "scans": len(report["scans"]),
        "pairs": report["pairs_registered"],
        "seconds": report["seconds"],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small cases: a check of the benchmark")
    ap.add_argument("--workdir", type=Path, default=None, help="where the scenes go (default: a temporary folder)")
    ap.add_argument("--keep", action="store_true", help="keep the generated scenes")
    args = ap.parse_args()
    big, many, per_scan, sweep = (
        (1_000_000, 20, 100_000, (10, 20)) if args.quick else (5_000_000, 100, 1_000_000, (20, 50, 100))
    )
    work = Path(tempfile.mkdtemp(dir=args.workdir, prefix="bench_memory-"))
    print(
        f"machine: {psutil.cpu_count()} cores, {psutil.virtual_memory().total / 2**30:.1f} GB; "
        f"load before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}"
    )
    rows = []
    try:
        points = _write_scene(work / "one_large", 6, [big] + [None] * 5, seed=0)
        rows.append(
            (f"1 scan of {big / 1e6:g} M + 5 of ~10 k", 6, points, measured_run(work / "one_large", work / "out_a"))
        )
        _write_scene(work / "many", many, [per_scan] * many, seed=1)
        for n in sweep:
            scene = work / "many" if n == many else work / f"many_{n}"
            if n != many:
                _subset(work / "many", scene, n)
            label = f"{n} scans of {per_scan / 1e6:g} M"
            rows.append((label, n, n * per_scan, measured_run(scene, work / f"out_{n}")))
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    print(f"load after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print()
    print(
        "| case | scans | points | registered | pairs | wall s | CPU s | largest process GB | all processes RSS GB "
        "| all processes PSS GB | ≤ 4 GB |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for label, n, points, r in rows:
        ok = "yes" if r["tree_pss_gb"] <= TARGET_GB else "**no**"
        print(
            f"| {label} | {n} | {points / 1e6:.1f} M | {r['registered']}/{r['scans']} | {r['pairs']} | "
            f"{r['wall']:.0f} | {r['cpu']:.0f} | {r['max_process_gb']:.2f} | {r['tree_rss_gb']:.2f} | "
            f"{r['tree_pss_gb']:.2f} | {ok} |"
        )
    sweep_rows = [(n, r) for label, n, _, r in rows[1:]]
    if len(sweep_rows) > 1:
        n = np.array([s for s, _ in sweep_rows], dtype=float)
        for column in ("max_process_gb", "tree_pss_gb"):
            slope = np.polyfit(n, [r[column] for _, r in sweep_rows], 1)[0]
            print(f"\n{column}: grows {slope * 1024:.1f} MB per scan over N = {', '.join(f'{s:g}' for s in n)}")
    print("\nstage seconds:")
    for label, _, _, r in rows:
        print(f"- {label}: " + ", ".join(f"{k} {v:.1f}" for k, v in r["seconds"].items()))


if __name__ == "__main__":
    main()
