"""A run's final pose graph synchronized again from its results folder: the back end alone, in seconds.

A run writes every registered pair: the kept ones in ``graph.g2o``, the others in ``graph_rejected.g2o``, and
in ``edges.csv`` each pair's initial weight ``w⁰`` as its last synchronization saw it (0 for a failed,
contradicted or overruled registration) and its status. ``run_graph`` rebuilds that ``PoseGraph``, with the
information the files carry, so that a change to synchronization can be measured on real runs' graphs without
running their front ends again (docs/BENCHMARKS.md, "Votes between counts and weights": 25 runs' graphs, each
synchronized with the head's rules and the change's, in a few minutes).

Command line: ``python -m data_tools.resync RUN_DIR [--method M] [--polish P] [--out POSES]`` synchronizes the
graph (``sync.synchronize``'s defaults, as a run uses them) and prints how many edges it keeps and how many of them
the run kept; ``--out`` writes the largest part's poses as a ``poses.txt`` (``io.poses``), for
``evaluate.score_run`` or ``bench_3dmatch``'s scoring.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from sghr_gtsam.io.g2o import read_g2o
from sghr_gtsam.io.poses import write_poses
from sghr_gtsam.sync import synchronize
from sghr_gtsam.types import PoseGraph

KEPT = ("kept", "unplaced")
"""``edges.csv`` statuses of the edges the run's last synchronization kept (``registration.edges.EDGE_STATUS``)."""


def run_graph(run: Path) -> tuple[PoseGraph, list[str], list[str]]:
    """The pose graph of the run in folder ``run`` (every registered pair, ``w⁰`` from ``edges.csv``), the names of
    its scans (node ``k`` is ``report.json["scans"][k]``) and each edge's status in the run."""
    scans = json.loads((run / "report.json").read_text())["scans"]
    with open(run / "edges.csv", newline="") as f:
        rows = {(int(r["i"]), int(r["j"])): r for r in csv.DictReader(f)}
    i, j, T, weight, information, status = [], [], [], [], [], []
    for name in ("graph.g2o", "graph_rejected.g2o"):
        ids, _, graph = read_g2o(run / name)
        for e in range(graph.num_edges):
            a, b = ids[graph.i[e]], ids[graph.j[e]]
            row = rows[(a, b)]
            i.append(a)
            j.append(b)
            T.append(graph.T[e])
            weight.append(float(row["initial_weight"]))
            information.append(graph.information[e])
            status.append(row["status"])
    graph = PoseGraph(
        n=len(scans),
        i=np.array(i, dtype=np.int64),
        j=np.array(j, dtype=np.int64),
        T=np.array(T).reshape(-1, 4, 4),
        weight=np.array(weight),
        information=np.array(information).reshape(-1, 6, 6),
    )
    return graph, scans, status


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a run's results folder")
    ap.add_argument("--method", default="history")
    ap.add_argument("--polish", default="loops")
    ap.add_argument("--out", type=Path, help="write the largest part's poses here (poses.txt format)")
    args = ap.parse_args(argv)
    graph, scans, status = run_graph(args.run)
    result = synchronize(graph, method=args.method, polish=args.polish)
    kept, before = result.weights > 0, np.isin(status, KEPT)
    print(
        f"{args.run}: {graph.num_edges} edges; the run kept {int(before.sum())}, kept now {int(kept.sum())}, "
        f"{int(np.sum(kept != before))} changed"
    )
    if args.out:
        main_part = np.flatnonzero(result.component == 0)
        write_poses(args.out, [scans[k] for k in main_part], result.poses[main_part])
    return 0


if __name__ == "__main__":
    sys.exit(main())
