"""How far a scene's ground truth is from what its own scans say: GT poses re-fitted to the data.

The 3DMatch ground truth comes from reconstructing each RGB-D sequence; it is not exact. A whole-model check
("every scan within 5° / 0.2 m after one rigid alignment") cannot read better than the GT's own error, and
where a registration fits the scans better than the GT does, a miss may be the GT's. This tool measures that,
independently of the pipeline: Open3D point-to-plane ICP on every pair the GT says overlaps (``MIN_OVERLAP``),
started from the GT relative pose, then the GT poses re-fitted to those ICP results by gtsam Levenberg-Marquardt
(each pair weighted by Open3D's information of its ICP, a Huber kernel against a bad one), started from the GT.
It never sees a run's output, so it cannot drift towards one: it moves the GT only as far as the scans pull it.

Use it beside the GT, never instead of it: docs/BENCHMARKS.md reports the whole-model check against both.

Command line: ``python -m data_tools.refit_gt SCENE_DIR GT_POSES OUT [--voxel V]`` writes the re-fitted poses
(``gt_poses.txt`` form) to OUT and prints how far each pair's ICP moved from the GT and each scan's pose moved.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import gtsam
import numpy as np
import open3d as o3d

from data_tools.gt_overlap import combine, directed_overlap_matrix
from sghr_gtsam.io.poses import read_poses, write_poses
from sghr_gtsam.io.scans import load_scan
from sghr_gtsam.se3 import inv_T, relative_errors

MIN_OVERLAP = 0.3
"""GT overlap (mean of both directions, points within 2 voxels) from which a pair is re-fitted: 3DMatch's own
threshold for a benchmark pair."""
MAX_MOVE = (10.0, 0.5)
"""An ICP that ends farther than this (degrees, metres) from the GT pose is taken as failed and left out."""
HUBER = 1.345
"""Huber threshold in standard deviations (the usual 95 %-efficiency value)."""

_reg = o3d.pipelines.registration


@dataclass
class Refit:
    """``poses``: the re-fitted GT (N, 4, 4), scan 0 held at its GT pose; ``pairs``: (P, 2) pairs re-fitted;
    ``icp_move``: (P, 2) how far each pair's ICP optimum lies from the GT relative pose (degrees, metres);
    ``failed``: pairs left out (ICP farther than ``MAX_MOVE``)."""

    poses: np.ndarray
    pairs: np.ndarray
    icp_move: np.ndarray
    failed: list[tuple[int, int]]


def _cloud(points: np.ndarray, voxel: float) -> o3d.geometry.PointCloud:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * voxel, max_nn=30))
    return cloud


def refit(scans: list[np.ndarray], gt: np.ndarray, voxel: float) -> Refit:
    """Re-fit GT poses ``gt`` (N, 4, 4) of ``scans`` to the scans themselves (module docstring)."""
    clouds = [_cloud(np.asarray(P, dtype=np.float64), voxel) for P in scans]
    grids = [np.asarray(c.points) for c in clouds]
    overlap = combine(directed_overlap_matrix(grids, gt, 2 * voxel, None, max_points=2000), "mean")
    i, j = np.nonzero(np.triu(overlap >= MIN_OVERLAP, 1))
    graph, pairs, moves, failed = gtsam.NonlinearFactorGraph(), [], [], []
    for a, b in zip(i.tolist(), j.tolist()):
        T_gt = inv_T(gt[a]) @ gt[b]
        icp = _reg.registration_icp(
            clouds[b],
            clouds[a],
            2 * voxel,
            T_gt,
            _reg.TransformationEstimationPointToPlane(),
            _reg.ICPConvergenceCriteria(max_iteration=60),
        )
        T = icp.transformation
        move = relative_errors(T, T_gt)
        if move[0] > MAX_MOVE[0] or move[1] > MAX_MOVE[1]:
            failed.append((a, b))
            continue
        # Open3D's information perturbs T on the left (in scan a's frame); gtsam's BetweenFactor on the right.
        info = _reg.get_information_matrix_from_point_clouds(clouds[b], clouds[a], 2 * voxel, T)
        adjoint = gtsam.Pose3(T).AdjointMap()
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(HUBER),
            gtsam.noiseModel.Gaussian.Information(adjoint.T @ info @ adjoint),
        )
        graph.add(gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(T), noise))
        pairs.append((a, b))
        moves.append(move)
    values = gtsam.Values()
    for k, T in enumerate(gt):
        values.insert(k, gtsam.Pose3(T))
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(gt[0]), gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values).optimize()
    poses = np.array([result.atPose3(k).matrix() if result.exists(k) else gt[k] for k in range(len(gt))])
    return Refit(poses, np.array(pairs, dtype=np.int64).reshape(-1, 2), np.array(moves).reshape(-1, 2), failed)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("gt_poses", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--voxel", type=float, default=0.025, help="grid for ICP and overlap, metres (3DMatch: 2.5 cm)")
    args = ap.parse_args(argv)
    names, gt = read_poses(args.gt_poses)
    r = refit([load_scan(args.scene / n) for n in names], gt, args.voxel)
    write_poses(
        args.out,
        names,
        r.poses,
        comment=f"{args.gt_poses} re-fitted to the scans by data_tools.refit_gt (not ground truth)",
    )
    rot, trans = r.icp_move.T
    print(
        f"{len(r.pairs)} pairs re-fitted, {len(r.failed)} left out; ICP optimum from GT: rotation median / 90 % / max "
        f"{np.median(rot):.2f} / {np.quantile(rot, 0.9):.2f} / {rot.max():.2f}°, translation "
        f"{np.median(trans):.3f} / {np.quantile(trans, 0.9):.3f} / {trans.max():.3f} m"
    )
    for name, T, G in zip(names, r.poses, gt):
        dr, dt = relative_errors(T, G)
        print(f"{name}: re-fitted {dr:.2f}° {dt:.3f} m from GT")
    return 0


if __name__ == "__main__":
    sys.exit(main())
