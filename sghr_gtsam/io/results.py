"""The results folder of a run. File names are fixed because other tools read them:
poses.txt, poses_kitti.txt, poses_tum.txt, graph.g2o, graph_rejected.g2o, edges.csv, merged.ply, summary.png,
report.json, config.json, recording.rrd.

graph.g2o is what a SLAM stack loads as it is: one vertex per registered scan (id = the scan's index in
``report.json["scans"]``, mapped to its name in ``report.json["g2o_vertices"]``) at its final pose, and the
edges the result rests on (kept by synchronization, both ends registered) with their calibrated information.
graph_rejected.g2o holds the other registered pairs as ``EDGE_SE3:QUAT`` lines only (no vertices: not meant to
be optimized). edges.csv lists every pair with its ``status`` (``registration.edges.EDGE_STATUS``).

The folder is replaced as a whole (``io.atomic.staged_folder``): a run writes into a temporary folder beside it and swaps it
in at the end, so a run stopped at any point (SIGINT, SIGTERM, SIGKILL, a failure) leaves the previous results
complete and untouched, and a finished one leaves no file of an older run (an old recording beside a run made
with ``--no-record``). ``OUT/cache`` is the exception: the resume cache, written during the run in place and
carried across the swap."""

from __future__ import annotations

import csv
import errno
import json
import math
import os
import re
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..gtsam_api import graph_information, pose_covariances, sigmas, variance_factor
from ..plots import write_summary
from ..registration.edges import EDGE_STATUS, edge_status
from ..result import peak_memory_mb
from ..types import InputError, PoseGraph
from .atomic import atomic_write, mounted
from .g2o import write_g2o
from .poses import write_kitti, write_poses, write_tum
from .scans import write_ply

if TYPE_CHECKING:
    from ..config import Config
    from ..result import RunResult

RESULT_FILES = ("poses.txt", "poses_kitti.txt", "poses_tum.txt", "graph.g2o", "graph_rejected.g2o", "edges.csv",
                "merged.ply", "report.json", "config.json", "recording.rrd", "summary.png")
"""Every file a run may write (an output added to ``write_results`` belongs here too: a folder holding anything
else is not replaced, ``check_output_folder``)."""
CACHE = "cache"
"""``OUT/cache``: state a run writes in place to resume from (kept across the swap, never staged)."""
_LEGACY = ("recording.rrd.partial",)  # left by runs from before the swap
_OURS_HIDDEN = re.compile(r"^\.(" + "|".join(map(re.escape, RESULT_FILES)) + r")\..*\.tmp|^\.DS_Store$")
"""Hidden names a results folder may hold: an output's temporary (``io.atomic``) left by a run from before the swap,
and the Finder's metadata. Any other (``.git``, ``.env``) is the user's: the swap would delete it."""

EDGE_COLUMNS = ["i", "j", "overlap_score", "inliers", "initial_weight", "final_weight", "residual_deg", "status",
                "origin", "free_space_conflict"]
def write_edges_csv(path: Path, result: "RunResult", status: list[str]) -> None:
    g, s = result.graph, result.sync
    conflict = np.full(g.num_edges, np.nan) if result.edge_conflict is None else result.edge_conflict
    with atomic_write(path, newline="") as f:
        w = csv.writer(f)
        w.writerow(EDGE_COLUMNS)
        for e in range(g.num_edges):
            a, b = int(g.i[e]), int(g.j[e])
            w.writerow([a, b, f"{result.scores[a, b]:.6f}", result.pairs[e].inliers, f"{g.weight[e]:.6g}",
                        f"{s.weights[e]:.6g}", f"{s.residual_deg[e]:.4f}", status[e],
                        result.edge_origin[e] if result.edge_origin else "top-k",
                        "" if np.isnan(conflict[e]) else f"{conflict[e]:.4f}"])


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
        "ambiguous": result.ambiguous,
        "contradicted": result.contradicted,
        "underdetermined": result.underdetermined,
        # the pairs the result rests on: a failed or rejected registration's free directions say nothing of the scene
        "degenerate_pairs": [[result.names[i], result.names[j], p.free] for i, j, p, s
                             in zip(result.graph.i, result.graph.j, result.pairs, status) if p.free and s == "kept"],
        "front_end": result.densify,
        "cache": result.cache,
        "skipped": result.skipped,
        "voxel": result.voxel,
        "global_feature": result.global_feature,
        "pairs_registered": result.graph.num_edges,
        "pairs_exhaustive": n * (n - 1) // 2,
        "edges_kept": int((result.sync.weights > 0).sum()),
        "edge_status": {key: status.count(key) for key in EDGE_STATUS},
        "g2o_vertices": {str(k): result.names[k] for k in keep},
        "variance_factor": round(factor, 4),
        "pose_covariances": covariance_report(result),
        "seconds": {k: round(v, 3) for k, v in result.timings.items()},
        "peak_memory_mb": round(peak_memory_mb(), 1),
        "parameters": asdict(config),
        "kitti_order": names,
    }
    with atomic_write(out / "report.json") as f:
        json.dump(_strict(report), f, indent=2, allow_nan=False)


def _strict(value: Any) -> Any:
    """``value`` with every non-finite float as None: JSON has no NaN or Infinity (Python writes them, strict
    readers refuse the file); a covariance gtsam could not compute is unknown, null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _strict(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_strict(v) for v in value]
    return value


# --- what may be replaced ------------------------------------------------------------------------------------


def check_output_path(out: Path) -> None:
    """``InputError`` when no folder can be made at ``out``: a symbolic link loop on the way, or a file where a
    folder should be ("File exists" said of ``file/sub``)."""
    try:
        os.stat(out)
    except FileNotFoundError:
        return
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise InputError(f"output folder {out} is, or lies through, a symbolic link loop") from None
        if e.errno == errno.ENOTDIR:
            file = next((p for p in reversed(out.parents) if p.exists() and not p.is_dir()), out.parent)
            raise InputError(f"output folder {out} cannot be made: {file} is a file, not a folder") from None
        raise InputError(f"output folder {out}: {e.strerror or e}") from None


def check_output_folder(out: Path, scene_dir: Path) -> None:
    """``InputError`` unless ``out`` can be replaced as a whole: a new or empty folder, or an earlier run's results
    (anything else in it would be lost by the swap, and scans read from it would mix with the outputs)."""
    check_output_path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"output folder {out} is an existing file, not a folder")
    scene, target = scene_dir.resolve(), out.resolve()
    if target == scene:
        raise InputError(f"output folder {out} is the scan folder: its results would be read as scans by the next "
                         f"run (use e.g. --out {out / 'results'})")
    if target in scene.parents:
        raise InputError(f"output folder {out} holds the scan folder {scene_dir}: replacing it with the results "
                         f"would delete the scans")
    mount = mounted(out, CACHE)  # said now, not after the run's work
    if mount:
        raise InputError(mount)
    if out.is_dir():
        foreign = sorted(p.name for p in out.iterdir()
                         if p.name not in RESULT_FILES + _LEGACY + (CACHE,) and not _OURS_HIDDEN.match(p.name))
        if foreign:
            shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
            raise InputError(f"output folder {out} holds files that are not a run's results ({shown}): the new "
                             f"results replace the folder as a whole, so choose a new or empty one")
