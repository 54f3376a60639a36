"""How `python -m sghr_gtsam sync` scales with the size of a g2o pose graph: seconds and peak memory (the
command's own process, ``ru_maxrss``) per graph, as a table on the terminal and as JSON in
``benchmarks/results/sync_scaling.json`` (with the command, the commit and the machine).

Graphs: N poses along a random walk (1 m steps, turning up to 30° per step), an odometry edge between
consecutive poses and random loop closures between uniformly random pairs of poses, E edges in all (1° rotation
and 2 cm translation noise per axis, and that noise as each edge's information). Uniformly random closures are
the hard case for a sparse solver: their graph is an expander, whose elimination has no small separators (a
direct solver's fill grows as N³). Rows ``isolated``: a 1,000-pose graph of 5,000 edges and as many more
vertices without any edge as make up N (each is a part of its own).

``sync`` runs in a subprocess of its own per graph, with ``--timeout`` seconds; a run that is stopped or fails is
a row with its outcome (``sync``'s one line). Other agents may share the machine: the seconds are wall-clock.

Run from the repository root: ``python benchmarks/bench_sync_scaling.py [--sizes 500:2500 1000:5000 ...]
[--isolated 8000 24000 100000] [--timeout 900]``.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks._results import save  # noqa: E402
from sghr_gtsam.io.g2o import write_g2o  # noqa: E402
from sghr_gtsam.se3 import inv_T, make_T  # noqa: E402
from sghr_gtsam.types import PoseGraph  # noqa: E402

SIZES = ("500:2500", "1000:5000", "2000:10000", "4000:20000", "10000:50000", "20000:100000")
ISOLATED = (8000, 24000, 100000)
ROT_NOISE_DEG = 1.0
TRANS_NOISE = 0.02
NOTES = (
    "A random walk with uniformly random loop closures (`random`), and a 1,000-pose graph with vertices without "
    "edges making up the rest (`isolated`); seconds are wall-clock, with the load average in the machine line."
)


def random_graph(n: int, edges: int, seed: int = 0) -> tuple[np.ndarray, PoseGraph]:
    """True poses (N, 4, 4) of a random walk and its measured graph: odometry plus random loop closures."""
    rng = np.random.default_rng(seed)
    turns = Rotation.from_rotvec(rng.normal(0.0, np.radians(15.0), (n - 1, 3))).as_matrix()
    steps = make_T(turns, np.tile([1.0, 0.0, 0.0], (n - 1, 1)))
    poses = np.empty((n, 4, 4))
    poses[0] = np.eye(4)
    for k, step in enumerate(steps):
        poses[k + 1] = poses[k] @ step
    closures = edges - (n - 1)
    i = rng.integers(0, n, closures)
    j = (i + rng.integers(1, n, closures)) % n
    i, j = np.r_[np.arange(n - 1), i], np.r_[np.arange(1, n), j]
    noise = make_T(
        Rotation.from_rotvec(rng.normal(0.0, np.radians(ROT_NOISE_DEG), (len(i), 3))).as_matrix(),
        rng.normal(0.0, TRANS_NOISE, (len(i), 3)),
    )
    information = np.diag(np.r_[np.full(3, np.radians(ROT_NOISE_DEG) ** -2), np.full(3, TRANS_NOISE**-2)])
    graph = PoseGraph(
        n=n,
        i=i,
        j=j,
        T=inv_T(poses[i]) @ poses[j] @ noise,
        weight=np.ones(len(i)),
        information=np.tile(information, (len(i), 1, 1)),
    )
    return poses, graph


def with_isolated(n: int) -> tuple[np.ndarray, PoseGraph]:
    """A 1,000-pose, 5,000-edge ``random_graph`` and ``n`` − 1,000 vertices without edges (identity poses)."""
    poses, graph = random_graph(1000, 5000)
    everything = np.concatenate([poses, np.tile(np.eye(4), (n - 1000, 1, 1))])
    graph.n = n
    return everything, graph


def run_sync(path: Path, timeout: float) -> dict:
    """`sync` on the g2o file ``path`` in a subprocess: its seconds, peak memory (MB), exit code and last line."""
    command = [sys.executable, "-m", "sghr_gtsam", "sync", str(path), "--out", str(path.with_suffix(".out.g2o"))]
    started = time.perf_counter()
    proc = subprocess.Popen(
        command,
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        start_new_session=True,
    )
    try:
        output, _ = proc.communicate(timeout=timeout)
        outcome = "done" if proc.returncode == 0 else "refused" if proc.returncode == 2 else "failed"
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        outcome = f"stopped after {timeout:.0f} s"
    seconds = time.perf_counter() - started
    lines = [line for line in output.splitlines() if line.strip()]
    return {
        "seconds": round(seconds, 2),
        "outcome": outcome,
        "exit_code": proc.returncode,
        "last_line": lines[-1][:300] if lines else "",
    }


def _measured(kind: str, n: int, edges: int, timeout: float) -> dict:
    """One row, measured in a fresh interpreter so that ``ru_maxrss`` of its children is this run's peak."""
    script = (
        f"import json, resource, sys; sys.path.insert(0, {str(ROOT / 'benchmarks')!r}); "
        f"from bench_sync_scaling import _row; "
        f"row = _row({kind!r}, {n}, {edges}, {timeout}); "
        f"row['peak_mb'] = round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024, 1); "
        f"print(json.dumps(row))"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=ROOT)
    if done.returncode:
        raise SystemExit(done.stderr)
    return json.loads(done.stdout.strip().splitlines()[-1])


def _row(kind: str, n: int, edges: int, timeout: float) -> dict:
    poses, graph = random_graph(n, edges) if kind == "random" else with_isolated(n)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "graph.g2o"
        write_g2o(path, list(range(n)), poses, graph)
        return {"graph": kind, "poses": n, "edges": graph.num_edges, **run_sync(path, timeout)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", nargs="*", default=list(SIZES), help="POSES:EDGES of the random graphs")
    parser.add_argument(
        "--isolated", nargs="*", type=int, default=list(ISOLATED), help="poses of the rows with vertices without edges"
    )
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds before a run is stopped")
    args = parser.parse_args()
    plan = [("random", *map(int, size.split(":"))) for size in args.sizes]
    plan += [("isolated", n, 5000) for n in args.isolated]
    rows = []
    print(f"{'graph':<10}{'poses':>8}{'edges':>9}{'seconds':>10}{'peak MB':>10}  outcome")
    for kind, n, edges in plan:
        row = _measured(kind, n, edges, args.timeout)
        rows.append(row)
        print(
            f"{row['graph']:<10}{row['poses']:>8}{row['edges']:>9}{row['seconds']:>10.1f}{row['peak_mb']:>10.0f}  "
            f"{row['outcome']}" + (f": {row['last_line']}" if row["outcome"] != "done" else ""),
            flush=True,
        )
    columns = ["graph", "poses", "edges", "seconds", "peak MB", "outcome"]
    cells = [
        [r["graph"], r["poses"], r["edges"], round(r["seconds"], 2), round(r["peak_mb"], 1), r["outcome"]] for r in rows
    ]
    path = save(
        "sync_scaling", cells, columns, section="Scale and speed", title="`sync` on large g2o graphs", notes=NOTES
    )
    print(f"-> {path}")


if __name__ == "__main__":
    main()
