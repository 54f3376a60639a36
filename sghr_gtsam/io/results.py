"""The results folder of a run. File names are fixed because other tools read them:
poses.txt, poses_kitti.txt, poses_tum.txt, graph.g2o, graph_rejected.g2o, edges.csv, merged.ply, summary.png,
report.json, config.json, recording.rrd. ``load_results`` reads a folder back into a ``RunResult``.

graph.g2o, poses_kitti.txt and poses_tum.txt are what a SLAM stack loads as they are, so they hold the world part
only (``report.json["parts"][0]``, ``verify``): nothing in them rests on a join that failed verification. graph.g2o
has one vertex per scan of that part (id = the scan's index in ``report.json["scans"]``, mapped to its name in
``report.json["g2o_vertices"]``) at its final pose, and the edges the result rests on inside it (kept by
synchronization) with their information as measured (``report.json["calibration"]`` times it is what the run's
errors bear out: ``gtsam_api.calibration``). graph_rejected.g2o holds the other registered pairs (the other parts'
edges and their joins among them) as ``EDGE_SE3:QUAT`` lines only (no vertices: not meant to be optimized).
poses.txt has every placed scan, the other parts where their best join puts them (report.json says which).
edges.csv lists every pair with its ``status`` (``registration.edges.EDGE_STATUS``).

The folder is replaced as a whole (``io.atomic.staged_folder``): a run writes into a temporary folder beside it and
swaps it
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

from sghr_gtsam.gtsam_api import calibration, graph_information, pose_covariances, sigmas, variance_factor
from sghr_gtsam.io.atomic import atomic_write, mounted
from sghr_gtsam.io.g2o import read_g2o, write_g2o
from sghr_gtsam.io.poses import read_poses, write_kitti, write_poses, write_tum
from sghr_gtsam.io.scans import write_ply
from sghr_gtsam.plots import write_summary
from sghr_gtsam.registration.edges import EDGE_STATUS, edge_status
from sghr_gtsam.result import peak_memory_mb
from sghr_gtsam.types import InputError, PoseGraph
from sghr_gtsam.verify import Verdict

if TYPE_CHECKING:
    from sghr_gtsam.config import Config
    from sghr_gtsam.result import RunResult

RESULT_FILES = (
    "poses.txt",
    "poses_kitti.txt",
    "poses_tum.txt",
    "graph.g2o",
    "graph_rejected.g2o",
    "edges.csv",
    "merged.ply",
    "report.json",
    "config.json",
    "recording.rrd",
    "summary.png",
)
"""Every file a run may write (an output added to ``write_results`` belongs here too: a folder holding anything
else is not replaced, ``check_output_folder``)."""
CACHE = "cache"
"""``OUT/cache``: state a run writes in place to resume from (kept across the swap, never staged)."""
_LEGACY = ("recording.rrd.partial",)  # left by runs from before the swap
_OURS_HIDDEN = re.compile(r"^\.(" + "|".join(map(re.escape, RESULT_FILES)) + r")\..*\.tmp|^\.DS_Store$")
"""Hidden names a results folder may hold: an output's temporary (``io.atomic``) left by a run from before the swap,
and the Finder's metadata. Any other (``.git``, ``.env``) is the user's: the swap would delete it."""

EDGE_COLUMNS = [
    "i",
    "j",
    "overlap_score",
    "inliers",
    "initial_weight",
    "final_weight",
    "residual_deg",
    "status",
    "origin",
    "free_space_conflict",
]


def write_edges_csv(path: Path, result: RunResult, status: list[str]) -> None:
    g, s = result.graph, result.sync
    conflict = np.full(g.num_edges, np.nan) if result.edge_conflict is None else result.edge_conflict
    with atomic_write(path, newline="") as f:
        w = csv.writer(f)
        w.writerow(EDGE_COLUMNS)
        for e in range(g.num_edges):
            a, b = int(g.i[e]), int(g.j[e])
            w.writerow(
                [
                    a,
                    b,
                    f"{result.scores[a, b]:.6f}",
                    result.pairs[e].inliers,
                    f"{g.weight[e]:.6g}",
                    f"{s.weights[e]:.6g}",
                    f"{s.residual_deg[e]:.4f}",
                    status[e],
                    result.edge_origin[e] if result.edge_origin else "top-k",
                    "" if np.isnan(conflict[e]) else f"{conflict[e]:.4f}",
                ]
            )


def world_part(result: RunResult) -> list[int]:
    """The scans of the world part (``verify``), in scan order; every registered scan before verification."""
    if result.verdict is None:
        return result.registered
    world = set(result.verdict.parts[0].scans) if result.verdict.parts else set()
    return [k for k, name in enumerate(result.names) if name in world]


def write_graphs(out: Path, result: RunResult, status: list[str]) -> None:
    """graph.g2o (the world part's scans and kept edges) and graph_rejected.g2o (every other pair), module doc."""
    g, nodes = result.graph, world_part(result)
    inside = np.zeros(len(result.names), dtype=bool)
    inside[nodes] = True
    kept = np.array([s == "kept" for s in status], dtype=bool) & inside[g.i] & inside[g.j]
    index = np.full(len(result.names), -1)
    index[nodes] = np.arange(len(nodes))
    sub = PoseGraph(
        n=len(nodes),
        i=index[g.i[kept]],
        j=index[g.j[kept]],
        T=g.T[kept],
        weight=g.weight[kept],
        information=graph_information(g, kept)[kept],
    )
    write_g2o(out / "graph.g2o", list(nodes), result.poses[nodes], sub)
    everyone = list(range(len(result.names)))
    rest = PoseGraph(
        n=len(everyone),
        i=g.i[~kept],
        j=g.j[~kept],
        T=g.T[~kept],
        weight=g.weight[~kept],
        information=None if g.information is None else g.information[~kept],
    )
    write_g2o(out / "graph_rejected.g2o", everyone, None, rest)


def covariance_report(result: RunResult) -> dict[str, dict]:
    """Per registered scan: its pose covariance (6×6, [rotation rad, translation], at the pose) and the
    longest axes of its rotation (degrees) and translation (scene units) ellipsoids."""
    C = result.covariances
    rot, trans = sigmas(C)
    return {
        result.names[k]: {
            "sigma_rotation_deg": float(rot[k]),
            "sigma_translation": float(trans[k]),
            "covariance": C[k].tolist(),
        }
        for k in result.registered
    }


def write_results(out: Path, result: RunResult, config: Config, started: float, merged: np.ndarray) -> None:
    """Write every output; report.json goes last so its presence means the folder is complete.

    Only registered scans get a pose in poses.txt / merged.ply: an unregistered scan has no reliable pose, and it
    is listed in report.json and in a comment of poses.txt. poses_kitti.txt and poses_tum.txt hold the world part
    (module doc).
    """
    t0 = time.perf_counter()
    keep, world = result.registered, world_part(result)
    names = [result.names[k] for k in keep]
    header = ("unregistered (no pose): " + ", ".join(result.unregistered)) if result.unregistered else None
    others = len(keep) - len(world)
    if others:
        joined = (
            f"{others} scan(s) outside the world part, placed by joins that failed verification (report.json parts)"
        )
        header = joined if header is None else header + "\n" + joined
    write_poses(out / "poses.txt", names, result.poses[keep], comment=header)
    write_kitti(out / "poses_kitti.txt", result.poses[world])
    write_tum(out / "poses_tum.txt", result.poses[world], world)  # timestamp = scan index
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
        **(result.verdict.as_dict() if result.verdict is not None else {}),
        # the pairs the result rests on: a failed or rejected registration's free directions say nothing of the scene
        "degenerate_pairs": [
            [result.names[i], result.names[j], p.free]
            for i, j, p, s in zip(result.graph.i, result.graph.j, result.pairs, status)
            if p.free and s == "kept"
        ],
        "front_end": result.densify,
        "cache": result.cache,
        "skipped": result.skipped,
        "voxel": result.voxel,
        "global_feature": result.global_feature,
        "pairs_registered": result.graph.num_edges,
        "pairs_exhaustive": n * (n - 1) // 2,
        "edges_kept": int((result.sync.weights > 0).sum()),
        "edge_status": {key: status.count(key) for key in EDGE_STATUS},
        "g2o_vertices": {str(k): result.names[k] for k in world},
        "variance_factor": round(factor, 4),
        # graph.g2o holds the information as measured (what data_tools.resync synchronizes again); times this, the
        # information to_gtsam hands gtsam (gtsam_api.calibration)
        "calibration": float(f"{calibration(result):.6g}"),
        "pose_covariances": covariance_report(result),
        "seconds": {k: round(v, 3) for k, v in result.timings.items()},
        "peak_memory_mb": round(peak_memory_mb(), 1),
        "parameters": asdict(config),
        "kitti_order": [result.names[k] for k in world],
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


# --- reading a folder back -------------------------------------------------------------------------------


def load_results(out: str | Path) -> RunResult:
    """A run's results folder ``out`` read back into a ``RunResult``: names, flags, skipped scans, voxel, seconds
    and the front end's report from report.json; poses from poses.txt (NaN for unregistered scans, which have
    none); every edge in its ``graph`` order from edges.csv (overlap score, inliers, weights, residual, origin,
    free-space conflict, overruled), its transform and information from graph.g2o (the kept ones: the information
    the result rests on) or graph_rejected.g2o; pose covariances where report.json holds them (NaN elsewhere).
    Not in a folder, so empty or None: the scans' grids (``features``: empty; merged.ply holds the merged cloud),
    the registrations' fit, the synchronization's history, ``centres``. ``InputError`` for a folder that is not a
    run's complete results."""
    from sghr_gtsam.features.local import ScanFeatures
    from sghr_gtsam.registration.pairwise import PairResult
    from sghr_gtsam.result import RunResult
    from sghr_gtsam.types import SyncResult

    out = Path(out)
    missing = [
        name
        for name in ("report.json", "poses.txt", "edges.csv", "graph.g2o", "graph_rejected.g2o")
        if not (out / name).is_file()
    ]
    if missing:
        raise InputError(f"{out} is not a run's complete results folder: no {', '.join(missing)}")
    try:
        report = json.loads((out / "report.json").read_text(encoding="utf-8"))
        names = list(report["scans"])
        index = {name: k for k, name in enumerate(names)}
        n = len(names)
        with open(out / "edges.csv", newline="", encoding="utf-8") as f:
            rows = list(csv.DictReader(f))
        i = np.array([int(r["i"]) for r in rows], dtype=np.int64)
        j = np.array([int(r["j"]) for r in rows], dtype=np.int64)
        status = [r["status"] for r in rows]
        number = {
            key: np.array([float(r[key]) for r in rows])
            for key in ("overlap_score", "initial_weight", "final_weight", "residual_deg")
        }
        conflict = np.array([float(r["free_space_conflict"] or "nan") for r in rows])
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(f"{out}: report.json or edges.csv is not a run's ({type(e).__name__}: {e})") from None
    if (i.size and (min(i.min(), j.min()) < 0 or max(i.max(), j.max()) >= n)) or set(status) - set(EDGE_STATUS):
        raise InputError(f"{out}/edges.csv: a scan index or status that report.json does not know")
    listed, poses_listed = read_poses(out / "poses.txt")
    poses = np.full((n, 4, 4), np.nan)
    for name, T in zip(listed, poses_listed):
        if name not in index:
            raise InputError(f"{out}/poses.txt: scan {name!r} is not in report.json")
        poses[index[name]] = T
    T = np.full((len(rows), 4, 4), np.nan)
    information = np.zeros((len(rows), 6, 6))
    world = np.zeros(n, dtype=bool)
    parts = report.get("parts") or [{"scans": [name for name in names if name not in set(report["unregistered"])]}]
    world[[index[name] for name in parts[0]["scans"] if name in index]] = True
    kept = np.array([s == "kept" for s in status], dtype=bool) & world[i] & world[j]  # write_graphs' split
    for file, chosen in (("graph.g2o", kept), ("graph_rejected.g2o", ~kept)):
        ids, _, g = read_g2o(out / file)
        ids = np.asarray(ids, dtype=np.int64)
        at = np.flatnonzero(chosen)
        if g.num_edges != len(at) or not (np.array_equal(ids[g.i], i[at]) and np.array_equal(ids[g.j], j[at])):
            raise InputError(f"{out}/{file}: its edges are not the {len(at)} edges.csv lists for it")
        T[at], information[at] = g.T, g.information
    graph = PoseGraph(n=n, i=i, j=j, T=T, weight=number["initial_weight"], information=information)
    scores = np.full((n, n), np.nan)
    scores[i, j] = scores[j, i] = number["overlap_score"]
    pairs = [
        PairResult(
            T=T[e],
            inliers=int(rows[e]["inliers"]),
            fitness=float("nan"),
            rmse=float("nan"),
            information=information[e],
            seconds=0.0,
        )
        for e in range(len(rows))
    ]
    covariances = np.full((n, 6, 6), np.nan)
    try:
        unregistered = list(report.get("unregistered", []))
        component = np.zeros(n, dtype=np.int64)
        component[[index[name] for name in unregistered]] = np.arange(1, len(unregistered) + 1)  # parts unknown
        for name, entry in (report.get("pose_covariances") or {}).items():
            C = np.array(entry["covariance"], dtype=float)  # JSON null: NaN
            if C.shape != (6, 6):
                raise ValueError(f"{name}: a covariance of shape {C.shape}")
            covariances[index[name]] = C
    except (ValueError, KeyError, TypeError, IndexError) as e:
        raise InputError(f"{out}/report.json: not a run's ({type(e).__name__}: {e})") from None
    sync = SyncResult(
        poses=np.where(np.isfinite(poses), poses, np.eye(4)),
        weights=number["final_weight"],
        residual_deg=number["residual_deg"],
        component=component,
    )
    empty = np.zeros((0, 3))
    voxel = float(report["voxel"]) if report.get("voxel") is not None else float("nan")
    features = [ScanFeatures(empty, empty, None, voxel, empty, np.zeros((0, 33), dtype=np.float32))] * n
    result = RunResult(
        names=names,
        poses=poses,
        voxel=voxel,
        scores=scores,
        graph=graph,
        pairs=pairs,
        sync=sync,
        unregistered=unregistered,
        skipped=dict(report.get("skipped", {})),
        features=features,
        timings=dict(report.get("seconds", {})),
        global_feature=report.get("global_feature", ""),
        edge_origin=[r["origin"] for r in rows],
        edge_conflict=conflict,
        edge_overruled=np.array([s == "overruled" for s in status], dtype=bool),
        densify=dict(report.get("front_end") or {}),
        covariances=covariances,
        cache=report.get("cache"),
    )
    if "parts" in report:
        try:
            result.verdict = Verdict.from_dict(report)
        except (ValueError, KeyError, TypeError) as e:
            raise InputError(f"{out}/report.json: its parts are not a run's ({type(e).__name__}: {e})") from None
    return result


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
        raise InputError(
            f"output folder {out} is the scan folder: its results would be read as scans by the next "
            f"run (use e.g. --out {out / 'results'})"
        )
    if target in scene.parents:
        raise InputError(
            f"output folder {out} holds the scan folder {scene_dir}: replacing it with the results "
            f"would delete the scans"
        )
    mount = mounted(out, CACHE)  # said now, not after the run's work
    if mount:
        raise InputError(mount)
    if out.is_dir():
        foreign = sorted(
            p.name
            for p in out.iterdir()
            if p.name not in RESULT_FILES + _LEGACY + (CACHE,) and not _OURS_HIDDEN.match(p.name)
        )
        if foreign:
            shown = ", ".join(foreign[:3]) + (", ..." if len(foreign) > 3 else "")
            raise InputError(
                f"output folder {out} holds files that are not a run's results ({shown}): the new "
                f"results replace the folder as a whole, so choose a new or empty one"
            )
