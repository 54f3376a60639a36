"""Speed of full synchronization (M = 50 IRLS iterations with history reweighting + the polish: by default
the loop polish, ``sync.cycles``; ``--polish robust`` for the former consensus + gtsam GNC + consensus + LM,
``--polish lm`` for LM alone). Columns: seconds by stage, the worst scan of the largest part, and the share of
all node pairs within 5° / 0.2 m of the truth, and that of the oracle (gtsam LM told the inliers; not timed);
``--outliers`` sets the outlier ratio.

Scenes: N scans at random positions, random orientations; each scan is linked to its k = 10 nearest
scans, as SGHR's top-k overlap graph links scans that see the same place. Layout ``plane`` (default): the
scans are spread over a floor (one per ~4 m², 1 m of height jitter), as a sensor carried through a
building; ``cube``: filled in 3-D (one per ~8 m³), a harder case for the sparse solvers (larger separators).
Uniformly random partners are not realistic, and their factor graphs have no sparse elimination order
(gtsam needs 7 s per LM iteration at N = 1000). Measurements: inliers with 1° rotation noise per
axis and 2 cm translation noise, 20 % outliers (random rotations, 2 m translations) with lower initial
weights on average, as overlap × inlier count gives them.

BLAS threads are set to 1 unless OPENBLAS_NUM_THREADS / OMP_NUM_THREADS is already set: the dense
blocks are tiny, and a multithreaded BLAS on a busy 2-core machine spends its time synchronising threads.

Run from the repository root (installed, or with ``PYTHONPATH=.``):
``python benchmarks/bench_sync_speed.py [--sizes 50 200 1000 5000] [--reweight authors] [--polish loops] [--outliers
0.2]``;
a real graph: ``--run-dir <output of sghr_gtsam run> --gt <scene>/gt_poses.txt`` (every polish).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", "1"))

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # data_tools

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from benchmarks._results import save  # noqa: E402
from data_tools.resync import run_graph  # noqa: E402
from data_tools.scene_gt import placement_groups  # noqa: E402
from sghr_gtsam.evaluate import fragment_id  # noqa: E402
from sghr_gtsam.io.poses import read_poses  # noqa: E402
from sghr_gtsam.se3 import inv_T, make_T, relative_errors  # noqa: E402
from sghr_gtsam.sync import POLISHES, synchronize  # noqa: E402
from sghr_gtsam.sync.baselines import oracle  # noqa: E402
from sghr_gtsam.types import PoseGraph  # noqa: E402

K = 10
OUTLIERS = 0.2
ROT_NOISE_DEG = 1.0
TRANS_NOISE = 0.02


def make_scene(
    n: int, seed: int, layout: str = "plane", outliers: float = OUTLIERS
) -> tuple[np.ndarray, PoseGraph, np.ndarray]:
    """Ground-truth poses, the measured k-nearest-neighbour graph and its outlier mask."""
    rng = np.random.default_rng(seed)
    if layout == "plane":
        side = 2.0 * np.sqrt(n)
        positions = rng.uniform(0.0, 1.0, (n, 3)) * [side, side, 1.0]
    else:
        positions = rng.uniform(0.0, 2.0 * n ** (1 / 3), (n, 3))
    poses = make_T(Rotation.random(n, random_state=rng).as_matrix(), positions)
    _, near = cKDTree(positions).query(positions, K + 1)
    pairs = np.unique(np.sort(np.stack([np.repeat(np.arange(n), K), near[:, 1:].ravel()], 1), axis=1), axis=0)
    i, j = pairs[:, 0], pairs[:, 1]
    E = len(i)
    T = inv_T(poses[i]) @ poses[j]
    noise = Rotation.from_rotvec(rng.normal(scale=np.radians(ROT_NOISE_DEG), size=(E, 3))).as_matrix()
    T[:, :3, :3] = T[:, :3, :3] @ noise
    T[:, :3, 3] += rng.normal(scale=TRANS_NOISE, size=(E, 3))
    outlier = rng.random(E) < outliers
    T[outlier] = make_T(
        Rotation.random(int(outlier.sum()), random_state=rng).as_matrix(),
        rng.normal(scale=2.0, size=(int(outlier.sum()), 3)),
    )
    overlap = np.where(outlier, rng.uniform(0.2, 0.7, E), rng.uniform(0.4, 1.0, E))
    inliers = np.where(outlier, rng.uniform(10, 100, E), rng.uniform(50, 500, E))
    return poses, PoseGraph(n=n, i=i, j=j, T=T, weight=overlap * inliers), outlier


def real_graph(run_dir: Path, gt_file: Path, polishes: list[str], repeats: int) -> None:
    """Median seconds and all-pairs recall (5° / 0.2 m against ``gt_file``, fragment k = ``cloud_bin_k``) of
    every polish on a real run's graph."""
    graph, scans, _ = run_graph(run_dir)
    if (np.linalg.eigvalsh(graph.information)[:, 0] <= 0).any():
        graph.information = None  # older runs wrote zero information for edges synchronization dropped
    ids = [fragment_id(name) for name in scans]
    names, P = read_poses(gt_file)
    gt = {fragment_id(name): T for name, T in zip(names, P)}
    truth = np.stack([gt[k] for k in ids])
    synchronize(graph, iters=2)
    print(f"{run_dir}: {graph.n} scans, {graph.num_edges} edges; load average {os.getloadavg()[0]:.1f}")
    print(
        "| polish | median s | median CPU s | all pairs (5° / 0.2 m) | kept edges | groups placed rigidly "
        "(scans: fragments (turn)) |\n|---|---:|---:|---:|---:|---|"
    )
    for polish in polishes:
        seconds, cpu = [], []
        for _ in range(repeats):
            start, cpu_start = time.perf_counter(), time.process_time()
            result = synchronize(graph, polish=polish)
            seconds.append(time.perf_counter() - start)
            cpu.append(time.process_time() - cpu_start)
        print(
            f"| {polish} | {np.median(seconds):.3f} | {np.median(cpu):.3f} | {all_pairs(result.poses, truth):.3f} | "
            f"{int((result.weights > 0).sum())} | {'; '.join(placement_groups(result.poses, truth, ids))} |"
        )


def run(truth: np.ndarray, graph: PoseGraph, outlier: np.ndarray, reweight: str, polish: str) -> dict[str, float]:
    stamps: list[tuple[str, float]] = []
    start, cpu = time.perf_counter(), time.process_time()
    result = synchronize(
        graph, reweight=reweight, polish=polish, on_iteration=lambda r: stamps.append((r.stage, time.perf_counter()))
    )
    total, cpu = time.perf_counter() - start, time.process_time() - cpu
    irls_end = max(t for stage, t in stamps if stage == "irls")
    robust_end = max(
        (t for stage, t in stamps if stage in ("consensus", "gnc") or stage.startswith("loops")), default=irls_end
    )
    main = result.component == 0
    anchor = np.flatnonzero(main)[0]
    rel = inv_T(result.poses[anchor]) @ result.poses[main]
    rot, trans = relative_errors(rel, inv_T(truth[anchor]) @ truth[main])
    return {
        "edges": graph.num_edges,
        "total": total,
        "cpu": cpu,
        "irls": irls_end - start,
        "robust": robust_end - irls_end,
        "lm": total - (robust_end - start),
        "lm_iters": sum(stage == "lm" for stage, _ in stamps),
        "rot_max": rot.max(),
        "trans_max": trans.max(),
        "registered": int(main.sum()),
        "outliers_kept": int((result.weights[outlier] > 0).sum()),
        "all_pairs": all_pairs(result.poses, truth),
        "oracle": all_pairs(oracle(graph, ~outlier).poses, truth),
    }


_PAIR_ROWS = 250
"""``all_pairs`` scores the pairs of this many rows at a time."""


def all_pairs(poses: np.ndarray, truth: np.ndarray) -> float:
    """Share of all node pairs within 5° / 0.2 m of their true relative pose, a block of rows at a time (all pairs
    at once held 8 GB at N = 5,000, and mapping it was most of the benchmark's process time)."""
    n, within = len(truth), 0
    for start in range(0, n, _PAIR_ROWS):
        rows = np.arange(start, min(start + _PAIR_ROWS, n))
        a = np.repeat(rows, n - 1 - rows)
        b = np.concatenate([np.arange(r + 1, n) for r in rows])
        rot, trans = relative_errors(inv_T(poses[a]) @ poses[b], inv_T(truth[a]) @ truth[b])
        within += int(np.sum((rot <= 5.0) & (trans <= 0.2)))
    return within / (n * (n - 1) / 2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[50, 200, 1000, 5000])
    parser.add_argument("--reweight", default="authors", choices=["authors", "paper"])
    parser.add_argument("--polish", default="loops", choices=list(POLISHES))
    parser.add_argument("--layout", default="plane", choices=["plane", "cube"])
    parser.add_argument("--outliers", type=float, default=OUTLIERS, help=f"outlier ratio (default {OUTLIERS})")
    parser.add_argument("--repeats", type=int, default=3, help="best of this many runs (1 for N >= 1000)")
    parser.add_argument("--run-dir", type=Path, help="time a real graph instead: a run's output directory")
    parser.add_argument("--gt", type=Path, help="with --run-dir: the scene's gt_poses.txt")
    args = parser.parse_args()
    if args.run_dir:
        real_graph(args.run_dir, args.gt, list(POLISHES), args.repeats)
        return

    synchronize(make_scene(20, 0)[1], iters=2)  # imports gtsam and warms caches outside the timings
    print(
        f"layout = {args.layout}, k = {K}, {args.outliers:.0%} outliers, "
        f"noise {ROT_NOISE_DEG}°/axis + {TRANS_NOISE} m, M = 50, reweight = {args.reweight}, polish = {args.polish}, "
        f"BLAS threads = {os.environ['OPENBLAS_NUM_THREADS']}, "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    print(
        f"{'N':>6} {'edges':>7} {'total s':>8} {'CPU s':>7} {'IRLS s':>8} {'robust s':>8} {'LM s':>7} {'LM it':>5} "
        f"{'rot max°':>8} {'trans max':>9} {'registered':>10} {'outl. kept':>10} {'all pairs':>9} {'oracle':>6}"
    )
    edges, totals, rows = [], [], []
    for n in args.sizes:
        scene = make_scene(n, seed=n, layout=args.layout, outliers=args.outliers)
        repeats = args.repeats if n < 1000 else 1
        best = min((run(*scene, args.reweight, args.polish) for _ in range(repeats)), key=lambda r: r["total"])
        edges.append(best["edges"])
        totals.append(best["total"])
        print(
            f"{n:>6} {best['edges']:>7} {best['total']:>8.3f} {best['cpu']:>7.3f} {best['irls']:>8.3f} "
            f"{best['robust']:>8.3f} {best['lm']:>7.3f} "
            f"{best['lm_iters']:>5} {best['rot_max']:>8.3f} {best['trans_max']:>9.4f} "
            f"{best['registered']:>6}/{n:<3} {best['outliers_kept']:>10} {best['all_pairs']:>9.3f} "
            f"{best['oracle']:>6.3f}"
        )
        rows.append(
            [
                f"{n:,}",
                f"{best['edges']:,}",
                f"{best['total']:.3f}",
                f"{best['irls']:.3f}",
                f"{best['robust']:.3f}",
                f"{best['lm']:.3f}",
                f"{best['all_pairs']:.3f}",
                f"{best['oracle']:.3f}",
            ]
        )
    defaults = (args.reweight, args.polish, args.layout, args.outliers) == ("authors", "loops", "plane", OUTLIERS)
    if defaults:  # the benchmarks page's table: the default synchronization only
        goals = {60: 0.1, 5000: 10.0}
        timed = dict(zip(args.sizes, totals))
        said = [
            f"{'met' if timed[n] <= bound else 'missed'} at N = {n:,} ({timed[n]:.3g} s, goal ≤ {bound:g} s)"
            for n, bound in goals.items()
            if n in timed
        ]
        save(
            "sync_speed",
            rows,
            ["N", "edges", "total s", "IRLS s", "loop polish s", "LM s", "all pairs", "oracle"],
            notes=f"Best of {args.repeats} below N = 1,000, one run above; load {os.getloadavg()[0]:.1f}. Goals: "
            + ("; ".join(said) or "none of their sizes run")
            + ".",
            section="Synchronization",
            title="Synchronization alone on generated graphs (20 % outliers, k = 10)",
        )
    if len(edges) > 1:
        slope = np.polyfit(np.log(edges), np.log(totals), 1)[0]
        print(f"fitted exponent (least squares on log-log, all sizes): total time ∝ edges^{slope:.2f}")


if __name__ == "__main__":
    main()
