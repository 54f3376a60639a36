"""The results folder of a run. File names are fixed because other tools read them:
poses.txt, poses_kitti.txt, poses_tum.txt, graph.g2o, graph_rejected.g2o, edges.csv, merged.ply, summary.png,
report.json, config.json, recording.rrd.

graph.g2o is what a SLAM stack loads as it is: one vertex per registered scan (id = the scan's index in
``report.json["scans"]``, mapped to its name in ``report.json["g2o_vertices"]``) at its final pose, and the
edges the result rests on (kept by synchronization, both ends registered) with their calibrated information.
graph_rejected.g2o holds the other registered pairs as ``EDGE_SE3:QUAT`` lines only (no vertices: not meant to
be optimized). edges.csv lists every pair with its ``status`` (``EDGE_STATUS``)."""

from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..gtsam_api import graph_information, pose_covariances, sigmas, variance_factor
from ..plots import write_summary
from ..result import peak_memory_mb
from ..types import PoseGraph
from .atomic import atomic_write
from .g2o import write_g2o
from .poses import write_kitti, write_poses, write_tum
from .scans import write_ply

if TYPE_CHECKING:
    from ..config import Config
    from ..result import RunResult

EDGE_COLUMNS = ["i", "j", "overlap_score", "inliers", "initial_weight", "final_weight", "residual_deg", "status",
                "origin"]
EDGE_STATUS = {
    "kept": "in graph.g2o: synchronization kept it and both scans are registered",
    "rejected": "registered, but inconsistent with the result (graph_rejected.g2o)",
    "failed": "the registration failed (too few inliers): no measurement (graph_rejected.g2o)",
    "unplaced": "kept, but between scans outside the largest part, which have no pose (graph_rejected.g2o)",
}


def edge_status(result: "RunResult") -> list[str]:
    """The ``EDGE_STATUS`` key of every edge of ``result.graph``."""
    g = result.graph
    placed = np.zeros(len(result.names), dtype=bool)
    placed[result.registered] = True
    return ["failed" if g.weight[e] <= 0 else "rejected" if result.sync.weights[e] <= 0
            else "kept" if placed[g.i[e]] and placed[g.j[e]] else "unplaced" for e in range(g.num_edges)]


def write_edges_csv(path: Path, result: "RunResult", status: list[str]) -> None:
    g, s = result.graph, result.sync
    with atomic_write(path, newline="") as f:
        w = csv.writer(f)
        w.writerow(EDGE_COLUMNS)
        for e in range(g.num_edges):
            a, b = int(g.i[e]), int(g.j[e])
            w.writerow([a, b, f"{result.scores[a, b]:.6f}", result.pairs[e].inliers, f"{g.weight[e]:.6g}",
                        f"{s.weights[e]:.6g}", f"{s.residual_deg[e]:.4f}", status[e],
                        result.edge_origin[e] if result.edge_origin else "top-k"])


def write_graphs(out: Path, result: "RunResult", status: list[str]) -> None:
    """graph.g2o (registered scans, kept edges) and graph_rejected.g2o (every other pair), module doc."""
    g, nodes = result.graph, result.registered
    kept = np.array([s == "kept" for s in status], dtype=bool)
    index = np.full(len(result.names), -1)
    index[nodes] = np.arange(len(nodes))
    sub = PoseGraph(n=len(nodes), i=index[g.i[kept]], j=index[g.j[kept]], T=g.T[kept], weight=g.weight[kept],
                    information=graph_information(g, kept)[kept])
    write_g2o(out / "graph.g2o", list(nodes), result.poses[nodes], sub)
    everyone = list(range(len(result.names)))
    rest = PoseGraph(n=len(everyone), i=g.i[~kept], j=g.j[~kept], T=g.T[~kept], weight=g.weight[~kept],
                     information=None if g.information is None else g.information[~kept])
    write_g2o(out / "graph_rejected.g2o", everyone, None, rest)


def covariance_report(result: "RunResult") -> dict[str, dict]:
    """Per registered scan: its pose covariance (6×6, [rotation rad, translation], at the pose) and the
    longest axes of its rotation (degrees) and translation (scene units) ellipsoids."""
    C = result.covariances
    rot, trans = sigmas(C)
    return {result.names[k]: {"sigma_rotation_deg": float(rot[k]), "sigma_translation": float(trans[k]),
                              "covariance": C[k].tolist()} for k in result.registered}


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
    write_tum(out / "poses_tum.txt", result.poses[keep], keep)  # timestamp = scan index
    if result.covariances is None:
        result.covariances = pose_covariances(result)
    status = edge_status(result)
    factor = variance_factor(result)
    write_graphs(out, result, status)
    write_edges_csv(out / "edges.csv", result, status)
    write_ply(out / "merged.ply", merged)
    write_summary(out / "summary.png", result, status)
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
        "contested": result.contested,
        "underdetermined": result.underdetermined,
        "degenerate_pairs": [[result.names[i], result.names[j], p.free] for i, j, p
                             in zip(result.graph.i, result.graph.j, result.pairs) if p.free],
        "front_end": result.densify,
        "skipped": result.skipped,
        "voxel": result.voxel,
        "global_feature": result.global_feature,
        "pairs_registered": result.graph.num_edges,
        "pairs_exhaustive": n * (n - 1) // 2,
        "edges_kept": int((result.sync.weights > 0).sum()),
        "edge_status": {key: status.count(key) for key in EDGE_STATUS},
        "g2o_vertices": {str(k): result.names[k] for k in keep},
        "variance_factor": None if np.isnan(factor) else round(factor, 4),
        "pose_covariances": covariance_report(result),
        "seconds": {k: round(v, 3) for k, v in result.timings.items()},
        "peak_memory_mb": round(peak_memory_mb(), 1),
        "parameters": asdict(config),
        "kitti_order": names,
    }
    with atomic_write(out / "report.json") as f:
        json.dump(report, f, indent=2)
