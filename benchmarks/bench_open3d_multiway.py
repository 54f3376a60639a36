"""Open3D multiway registration as in Open3D's ``reconstruction_system``, without and with its refinement stage.

    python benchmarks/bench_open3d_multiway.py [--data ../shared/data] [--scenes kitchen bunny home_at]
        [--processes 2] [--json rows.json]

Learned from Open3D's examples/python/reconstruction_system (register_fragments.py, refine_registration.py,
optimize_posegraph.py), with the same parameters, on the same voxel as our pipeline (``default_voxel``):

1. every pair: FPFH (normals at 2 v, features at 5 v) + RANSAC (mutual filter off, 1.4 v, 4-point samples,
   edge-length 0.9 and distance checkers, 10⁶ iterations, confidence 0.999); a pair is kept when the
   information's [5, 5] entry is ≥ 0.3 × the smaller cloud (the script's test); then point-to-plane ICP
   at v (50 iterations), as the script does for its odometry edges, gives the edge and its information;
2. pose graph optimization (Levenberg–Marquardt with line process: max correspondence 1.4 v, edge prune 0.25,
   loop-closure preference 5.0, reference node 0);
3. refinement (``refine``): multi-scale point-to-plane ICP (v, v/2, v/4; 50, 30, 14 iterations; distance 1.4 v)
   on every edge that survived, started from the optimized poses, then the same optimization again.

Adaptations, because these scans are unordered fragments without the RGB-D odometry the script relies on:
every edge is a loop closure (``uncertain``), and the initial poses come from a maximum spanning tree of the kept
edges (weight: the information's [5, 5], the inlier count) from scan 0; a scan outside scan 0's part has no pose
(unregistered). Open3D's refinement starts from each edge's stored transform; the reading compared here starts it
from the optimized poses, which is what is done here. Colored ICP (the script's default) needs colors the scans
do not have. Both variants are scored by ``sghr_gtsam.evaluate.score_run`` (same tolerances as bench_3dmatch).
Pairs run over ``--processes`` processes (Open3D single-threaded in each).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np
from bench_3dmatch import SCENES, labels, scene_gt

from data_tools.scene_gt import data_root

_CLOUDS: dict = {}  # per worker process: name -> (raw cloud, down-sampled cloud with normals, FPFH)


def _prepare(points: np.ndarray, voxel: float):
    import open3d as o3d

    raw = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    down = raw.voxel_down_sample(voxel)
    down.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * voxel, max_nn=30))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        down, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * voxel, max_nn=100)
    )
    return raw, down, fpfh


def _init_worker(points: list[np.ndarray], voxel: float) -> None:
    import open3d as o3d

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    _CLOUDS.update({k: _prepare(p, voxel) for k, p in enumerate(points)})
    _CLOUDS["voxel"] = voxel


def _global_pair(pair: tuple[int, int]):
    """(s, t, T_ts, information) of one pair (T maps scan s into scan t), or None when it fails the script's test."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    s, t = pair
    o3d.utility.random.seed(s * 100003 + t)  # per pair: results do not depend on which process ran it
    v = _CLOUDS["voxel"]
    (_, src, fs), (_, dst, ft) = _CLOUDS[s], _CLOUDS[t]
    dist = 1.4 * v
    result = reg.registration_ransac_based_on_feature_matching(
        src,
        dst,
        fs,
        ft,
        False,
        dist,
        reg.TransformationEstimationPointToPoint(False),
        4,
        [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(dist)],
        reg.RANSACConvergenceCriteria(1000000, 0.999),
    )
    if np.trace(result.transformation) == 4.0:
        return None
    info = reg.get_information_matrix_from_point_clouds(src, dst, dist, result.transformation)
    if info[5, 5] / min(len(src.points), len(dst.points)) < 0.3:
        return None
    T, info = _multiscale_icp(s, t, result.transformation, [v], [50])
    return s, t, T, info


def _multiscale_icp(s: int, t: int, T0: np.ndarray, voxels: list[float], iters: list[int]):
    import open3d as o3d

    reg = o3d.pipelines.registration
    dist = 1.4 * _CLOUDS["voxel"]
    T = T0
    for v, n in zip(voxels, iters):
        src, dst = _CLOUDS[s][0].voxel_down_sample(v), _CLOUDS[t][0].voxel_down_sample(v)
        for c in (src, dst):
            c.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        T = reg.registration_icp(
            src, dst, dist, T, reg.TransformationEstimationPointToPlane(), reg.ICPConvergenceCriteria(max_iteration=n)
        ).transformation
    return T, reg.get_information_matrix_from_point_clouds(src, dst, 1.4 * voxels[-1], T)


def _refine_pair(job: tuple[int, int, np.ndarray]):
    s, t, T0 = job
    v = _CLOUDS["voxel"]
    T, info = _multiscale_icp(s, t, T0, [v, v / 2, v / 4], [50, 30, 14])
    return s, t, T, info


def _spanning_tree_poses(n: int, edges: list) -> tuple[np.ndarray, list[int]]:
    """Initial poses (p_world = pose @ p_scan) from a maximum spanning tree of the edges (weight info[5, 5])
    grown from scan 0 (Prim), and the scans it reaches."""
    poses = np.tile(np.eye(4), (n, 1, 1))
    reached = {0}
    while True:
        best = None
        for s, t, T, info in edges:
            if (s in reached) != (t in reached) and (best is None or info[5, 5] > best[3][5, 5]):
                best = (s, t, T, info)
        if best is None:
            return poses, sorted(reached)
        s, t, T, _ = best  # T maps s into t: pose_s = pose_t @ T
        if s in reached:
            poses[t] = poses[s] @ np.linalg.inv(T)
            reached.add(t)
        else:
            poses[s] = poses[t] @ T
            reached.add(s)


def _optimize(poses: np.ndarray, edges: list, voxel: float, nodes: list[int]):
    """Open3D's global optimization with line process over ``nodes`` (Open3D refuses a graph that is not
    connected, so only scan 0's part); returns all poses (others unchanged) and the surviving edges."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    local = {k: m for m, k in enumerate(nodes)}
    graph = reg.PoseGraph()
    for k in nodes:
        graph.nodes.append(reg.PoseGraphNode(poses[k]))
    for s, t, T, info in edges:
        if s in local and t in local:
            graph.edges.append(reg.PoseGraphEdge(local[s], local[t], T, info, uncertain=True))
    option = reg.GlobalOptimizationOption(
        max_correspondence_distance=1.4 * voxel,
        edge_prune_threshold=0.25,
        preference_loop_closure=5.0,
        reference_node=0,
    )
    reg.global_optimization(
        graph, reg.GlobalOptimizationLevenbergMarquardt(), reg.GlobalOptimizationConvergenceCriteria(), option
    )
    out = poses.copy()
    out[nodes] = np.stack([np.asarray(node.pose) for node in graph.nodes])
    kept = [
        (nodes[e.source_node_id], nodes[e.target_node_id], np.asarray(e.transformation), np.asarray(e.information))
        for e in graph.edges
    ]
    return out, kept


def run_scene(data: Path, name: str, processes: int) -> list[dict]:
    from sghr_gtsam.evaluate import score_run
    from sghr_gtsam.features.local import default_voxel
    from sghr_gtsam.io.scans import finite_points, list_scans, load_scan

    scene = SCENES[name]
    started = time.perf_counter()
    paths = list_scans(data / scene.folder)
    names = [p.name for p in paths]
    points = [finite_points(load_scan(p))[0] for p in paths]
    voxel = default_voxel(points)
    n = len(names)
    gt = scene_gt(data, scene)
    pairs = [(s, t) for s in range(n) for t in range(s + 1, n)]
    ctx = multiprocessing.get_context("spawn")
    rows = []
    with ctx.Pool(processes, initializer=_init_worker, initargs=(points, voxel)) as pool:
        edges = []
        for done, e in enumerate(pool.imap(_global_pair, pairs, chunksize=4), 1):
            if e is not None:
                edges.append(e)
            if done % max(1, len(pairs) // 10) == 0:
                print(
                    f"  {name}: {done}/{len(pairs)} pairs, {time.perf_counter() - started:.0f} s",
                    file=sys.stderr,
                    flush=True,
                )
        t_pairs = time.perf_counter() - started
        init, reached = _spanning_tree_poses(n, edges)
        poses, kept = _optimize(init, edges, voxel, reached)
        t_first = time.perf_counter() - started
        unregistered = [names[k] for k in range(n) if k not in set(reached)]
        rows.append(
            _row(
                name,
                "multiway",
                score_run(names, poses, unregistered=unregistered, **gt),
                len(pairs),
                len(edges),
                len(kept),
                {"pairs": t_pairs, "total": t_first},
            )
        )
        jobs = [(s, t, np.linalg.inv(poses[t]) @ poses[s]) for s, t, _, _ in kept]
        refined = pool.map(_refine_pair, jobs, chunksize=2)
    poses2, kept2 = _optimize(poses, refined, voxel, reached)
    rows.append(
        _row(
            name,
            "multiway + refinement",
            score_run(names, poses2, unregistered=unregistered, **gt),
            len(pairs),
            len(refined),
            len(kept2),
            {"pairs": t_pairs, "total": time.perf_counter() - started},
        )
    )
    return rows


def _row(scene: str, variant: str, score, pairs: int, edges: int, kept: int, seconds: dict) -> dict:
    w = score.whole
    return {
        "scene": scene,
        "variant": variant,
        "scans": score.scans,
        "placed": len(score.placed),
        "pairs": pairs,
        "edges": edges,
        "kept": kept,
        "within": score.within,
        "tolerance": [score.max_deg, score.max_trans],
        "recall": score.recall.recall if score.recall else None,
        "ate_rmse": w.ate_rmse,
        "worst_rot": float(w.rotation_deg.max()),
        "worst_trans": float(w.translation.max()),
        "doubted": score.doubted,
        "unregistered": score.unregistered,
        "seconds": seconds,
    }


def print_header() -> None:
    print(
        "| scene | variant | scans | placed | pairs registered / tried | edges kept | within tol | RR (paper) "
        "| ATE rmse m | worst rot ° | worst trans m | pairwise s | total s | doubted (whole model) |"
    )
    print("|---" * 14 + "|", flush=True)


def print_rows(rows: list[dict]) -> None:
    for r in rows:
        rr = "-" if r["recall"] is None else f"{r['recall']:.3f}"
        print(
            f"| {r['scene']} | {r['variant']} | {r['scans']} | {r['placed']}/{r['scans']} "
            f"| {r['edges']}/{r['pairs']} | {r['kept']} | {r['within']}/{r['scans']} | {rr} | {r['ate_rmse']:.4g} "
            f"| {r['worst_rot']:.3g} | {r['worst_trans']:.3g} | {r['seconds']['pairs']:.0f} "
            f"| {r['seconds']['total']:.0f} | {labels(r['doubted'])} |",
            flush=True,
        )


def main() -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")  # before open3d loads: one thread per process
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=data_root())
    ap.add_argument("--scenes", nargs="+", default=["kitchen", "bunny", "home_at"], choices=list(SCENES))
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--json", type=Path, help="also write the raw rows here")
    args = ap.parse_args()
    from sghr_gtsam.io.atomic import atomic_write

    rows = []
    print_header()
    for name in args.scenes:  # rows are printed (and saved) as each scene ends: the large one takes long
        print(f"running {name} ...", file=sys.stderr, flush=True)
        scene_rows = run_scene(args.data, name, args.processes)
        print_rows(scene_rows)
        rows.extend(scene_rows)
        if args.json:
            with atomic_write(args.json) as f:
                json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
