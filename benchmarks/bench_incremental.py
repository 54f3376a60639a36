"""The incremental session (``sghr_gtsam.incremental``): where it ends against the batch run, and what a scan costs.

    python benchmarks/bench_incremental.py --real kitchen bunny [--data ../shared/data]
    python benchmarks/bench_incremental.py --graphs 10 100 500 [--outliers 0.02]
    python benchmarks/bench_incremental.py --scans 10 30

``--real``: batch ``register`` and a ``Session`` fed the same scans one by one (both ``workers=1``); the
largest difference between their poses over the scans both placed, the batch run's σ of the scan turned most, and
the median seconds per added scan (the benchmarks page's table).
``--graphs``: the back end alone (``Session.add_node``) on simulated pose graphs of N scans: a random walk
(0.3 m steps, ~10° turns), each new scan linked to its 10 nearest earlier ones within 1.5 m (top-k by
overlap), edges with 0.1° / 2 mm Gaussian noise and that calibrated information, and a fraction replaced by
random poses (wrong registrations) that trigger the robust stage. ``--scans``: the whole session (front end:
features, overlap head, up to k = 10 registrations; back end) on ``synthetic.make_scene`` rooms of N scans.
Timings are wall seconds on a shared 2-core machine (other jobs running): medians.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import gtsam
import numpy as np
from scipy.spatial.transform import Rotation

from sghr_gtsam.config import Config
from sghr_gtsam.incremental import Session
from sghr_gtsam.se3 import inv_T, make_T, relative_errors

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # data_tools
from benchmarks._results import save  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402

SIGMA = np.r_[np.full(3, np.radians(0.1)), np.full(3, 0.002)]


def walk(n: int, rng: np.random.Generator) -> np.ndarray:
    poses = [np.eye(4)]
    for _ in range(n - 1):
        step = make_T(Rotation.from_rotvec(rng.normal(0, np.radians(10), 3)).as_matrix(), rng.normal(0, 0.3, 3))
        poses.append(poses[-1] @ step)
    return np.stack(poses)


def graphs(sizes: list[int], outliers: float, seed: int) -> None:
    print("| N | edges | robust re-runs | median s / scan | p95 s / scan | last 10 % median s / scan | total s |")
    print("|---|---|---|---|---|---|---|")
    for n in sizes:
        rng = np.random.default_rng(seed)
        truth = walk(n, rng)
        session = Session(Config(), voxel=0.01)
        seconds = []
        edges = 0
        for k in range(n):
            d = np.linalg.norm(truth[:k, :3, 3] - truth[k, :3, 3], axis=1)
            partners = [int(a) for a in np.argsort(d)[:10] if d[a] < 1.5] or ([k - 1] if k else [])
            found = []
            for a in partners:
                T = inv_T(truth[a]) @ truth[k]
                if rng.random() < outliers:
                    T = make_T(Rotation.random(random_state=rng).as_matrix(), rng.normal(0, 1, 3))
                else:
                    T = (gtsam.Pose3(T) * gtsam.Pose3.Expmap(rng.normal(0, SIGMA))).matrix()
                found.append((a, T, float(rng.uniform(50, 100)), np.diag(SIGMA**-2)))
            edges += len(found)
            t0 = time.perf_counter()
            session.add_node(str(k), found)
            seconds.append(time.perf_counter() - t0)
        s = np.array(seconds)
        rot, _ = relative_errors(session.poses, truth)
        tail = s[int(0.9 * n) :]
        print(
            f"| {n} | {edges} | {session.robust_runs} | {np.median(s):.4f} | {np.percentile(s, 95):.4f} | "
            f"{np.median(tail):.4f} | {s.sum():.1f} |  <!-- max rotation error {np.nanmax(rot):.2f}° -->"
        )


def _session(names, scans, cfg, voxel):
    session = Session(cfg, voxel)
    steps = [session.add_scan(name, points) for name, points in zip(names, scans)]
    return session, steps


REAL_COLUMNS = [
    "scene",
    "scans placed (batch / session)",
    "robust re-runs",
    "max Δ rotation [°]",
    "max Δ translation [mm]",
    "scan turned most",
    "its σ in the batch [° / mm]",
    "median s / scan (front + back)",
    "median back-end s / scan",
]


def real(names: list[str], data: Path) -> list[list]:
    """One row a scene (``REAL_COLUMNS``): how far the session's poses lie from the batch run's, and for the scan
    turned most, how well the batch run's own covariance says its pose is known (1σ of the rotation and of the
    translation, the root of each block's trace)."""
    from sghr_gtsam.pipeline import load_scene, register

    rows = []
    for scene in names:
        cfg = Config(record=False, workers=1)
        scans, _ = load_scene(data / scene, cfg, log=lambda m: None)
        batch = register(scans, cfg, log=lambda m: None)
        session, steps = _session([s.name for s in scans], [s.read()[0] for s in scans], cfg, batch.voxel)
        P = session.poses
        both = [k for k in batch.registered if np.isfinite(P[k]).all()]
        rot, trans = relative_errors(P[both], batch.poses[both])
        worst = both[int(np.argmax(rot))]
        sigma = "-"
        if batch.covariances is not None and np.isfinite(batch.covariances[worst]).all():
            C = batch.covariances[worst]
            sigma = f"{np.degrees(np.sqrt(np.trace(C[:3, :3]))):.2f} / {1e3 * np.sqrt(np.trace(C[3:, 3:])):.1f}"
        rows.append(
            [
                scene,
                f"{len(batch.registered)} / {int(np.isfinite(P[:, 0, 0]).sum())}",
                session.robust_runs,
                round(float(rot.max()), 4),
                round(float(1e3 * trans.max()), 3),
                batch.names[worst],
                sigma,
                round(float(np.median([s.front_seconds + s.back_seconds for s in steps])), 2),
                round(float(np.median([s.back_seconds for s in steps])), 4),
            ]
        )
        print("| " + " | ".join(map(str, rows[-1])) + " |", flush=True)
    return rows


def scans(sizes: list[int], seed: int) -> None:
    from sghr_gtsam.synthetic import make_scene

    print("| N (room) | scans placed | robust re-runs | median s / scan (front + back) | median back-end s / scan |")
    print("|---|---|---|---|---|")
    for n in sizes:
        scene = make_scene(kind="room", n_scans=n, seed=seed)
        session, steps = _session(scene.names, scene.scans, Config(record=False, workers=1), scene.voxel)
        print(
            f"| {n} | {int(np.isfinite(session.poses[:, 0, 0]).sum())} | {session.robust_runs} | "
            f"{np.median([s.front_seconds + s.back_seconds for s in steps]):.2f} | "
            f"{np.median([s.back_seconds for s in steps]):.4f} |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", nargs="*")
    parser.add_argument("--graphs", nargs="*", type=int)
    parser.add_argument("--scans", nargs="*", type=int)
    parser.add_argument("--outliers", type=float, default=0.02)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--data", type=Path, default=data_root())
    args = parser.parse_args()
    if args.real is not None:
        rows = real(args.real or ["kitchen", "bunny"], args.data)
        save(
            "incremental",
            rows,
            REAL_COLUMNS,
            section="Pose graphs",
            title="The incremental session against the batch run (scans fed one by one)",
        )
    if args.graphs is not None:
        graphs(args.graphs or [10, 100, 500], args.outliers, args.seed)
    if args.scans is not None:
        scans(args.scans or [10, 30], args.seed)


if __name__ == "__main__":
    main()
