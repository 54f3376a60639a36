"""The results folder of a run. File names are fixed because other tools read them:
poses.txt, poses_kitti.txt, graph.g2o, edges.csv, merged.ply, report.json, config.json, recording.rrd."""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..result import peak_memory_mb
from .atomic import atomic_write
from .g2o import write_g2o
from .poses import write_kitti, write_poses
from .scans import write_ply

if TYPE_CHECKING:
    from ..config import Config
    from ..result import RunResult

EDGE_COLUMNS = ["i", "j", "overlap_score", "inliers", "initial_weight", "final_weight", "residual_deg"]


def write_edges_csv(path: Path, result: "RunResult") -> None:
    g, s = result.graph, result.sync
    with atomic_write(path, newline="") as f:
        w = csv.writer(f)
        w.writerow(EDGE_COLUMNS)
        for e in range(g.num_edges):
            a, b = int(g.i[e]), int(g.j[e])
            w.writerow([a, b, f"{result.scores[a, b]:.6f}", result.pairs[e].inliers, f"{g.weight[e]:.6g}",
                        f"{s.weights[e]:.6g}", f"{s.residual_deg[e]:.4f}"])


def write_results(out: Path, result: "RunResult", config: "Config", started: float,
                  merged: np.ndarray) -> None:
    """Write every output; report.json goes last so its presence means the folder is complete.

    Only registered scans get a pose in poses.txt / poses_kitti.txt / merged.ply: an unregistered
    scan has no reliable pose, and it is listed in report.json and in a comment of poses.txt.
    """
    t0 = time.perf_counter()
    keep = result.registered
    names = [result.names[k] for k in keep]
    header = ("unregistered (no pose): " + ", ".join(result.unregistered)) if result.unregistered else None
    write_poses(out / "poses.txt", names, result.poses[keep], comment=header)
    write_kitti(out / "poses_kitti.txt", result.poses[keep])
    write_g2o(out / "graph.g2o", list(range(len(result.names))), result.poses, result.graph)
    write_edges_csv(out / "edges.csv", result)
    write_ply(out / "merged.ply", merged)
    with atomic_write(out / "config.json") as f:
        f.write(config.to_json())
    result.timings["write"] = time.perf_counter() - t0
    result.timings["total"] = time.perf_counter() - started

    n = len(result.names)
    report = {
        "scans": result.names,
        "registered": names,
        "unregistered": result.unregistered,
        "unverified": result.unverified,
        "skipped": result.skipped,
        "voxel": result.voxel,
        "global_feature": result.global_feature,
        "pairs_registered": result.graph.num_edges,
        "pairs_exhaustive": n * (n - 1) // 2,
        "edges_kept": int((result.sync.weights > 0).sum()),
        "seconds": {k: round(v, 3) for k, v in result.timings.items()},
        "peak_memory_mb": round(peak_memory_mb(), 1),
        "parameters": asdict(config),
        "kitti_order": names,
    }
    with atomic_write(out / "report.json") as f:
        json.dump(report, f, indent=2)
