"""Per-scan local features: a voxel grid with normals and FPFH descriptors (for matching), and a
finer cloud with GICP covariances (for the pairwise refinement). Computed once per scan and shared by
every pair the scan is in, so the pairwise stage only matches and solves."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import small_gicp
from scipy.spatial import cKDTree

from sghr_gtsam.types import InputError

NUM_THREADS = len(os.sched_getaffinity(0))
# Normal-estimation and FPFH neighbourhoods are capped (open3d's hybrid search); 30 / 100 are the
# values the FPFH authors and open3d use, and they bound the cost per point.
NORMAL_MAX_NN = 30
FPFH_MAX_NN = 100
# The refinement cloud is this fraction of the matching voxel: GICP on it is what makes pairwise
# poses precise to a fraction of a voxel (on the bunny 2x finer halves the ICP error spread).
REFINE_FRACTION = 0.5
# GICP covariances from this many neighbours (small_gicp's default is 20).
COV_NEIGHBORS = 20


@dataclass(eq=False)
class ScanFeatures:
    """Features of one scan, in the scan's own frame.

    ``points`` (M, 3) float64 voxel-grid centroids; ``normals`` (M, 3) unit normals oriented towards
    the scan's origin; ``fpfh`` (M, 33) float32 FPFH descriptors of ``points``; ``voxel`` the grid size.
    ``refine_points`` (F, 3) the scan on a grid ``REFINE_FRACTION`` finer, used by GICP through
    ``refine_cloud`` (small_gicp cloud with covariances) and ``refine_tree``. ``fpfh_tree`` is a
    k-d tree on ``fpfh``.
    """

    points: np.ndarray
    normals: np.ndarray
    fpfh: np.ndarray
    voxel: float
    refine_points: np.ndarray
    fpfh_tree: cKDTree = field(repr=False)
    refine_cloud: small_gicp.PointCloud = field(repr=False)
    refine_tree: small_gicp.KdTree = field(repr=False)

    def __len__(self) -> int:
        return len(self.points)


def _grid(points: np.ndarray, voxel: float) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)


def compute_features(
    points: np.ndarray, voxel: float, normal_radius: float = 2.0, fpfh_radius: float = 5.0
) -> ScanFeatures:
    """Voxel grid, normals and FPFH of one scan; radii in voxels (as in ``Config``).

    Normals point towards the scan's origin, i.e. the sensor for scans in sensor coordinates (3DMatch
    fragments) and the object's inside for object-centred scans (Stanford): either way consistently
    across scans, which FPFH needs (its angles change sign with the normals).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must be (N, 3), got {points.shape}")
    if not voxel > 0:
        raise InputError(f"voxel must be positive, got {voxel}")
    points = points[np.isfinite(points).all(axis=1)]

    pcd = _grid(points, voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(normal_radius * voxel, NORMAL_MAX_NN))
    pcd.orient_normals_towards_camera_location(np.zeros(3))
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(fpfh_radius * voxel, FPFH_MAX_NN)
    )
    fpfh = np.ascontiguousarray(np.asarray(fpfh.data).T, dtype=np.float32)

    refine_points = np.asarray(_grid(points, REFINE_FRACTION * voxel).points)
    refine_cloud = small_gicp.PointCloud(refine_points)
    refine_tree = small_gicp.KdTree(refine_cloud, num_threads=NUM_THREADS)
    small_gicp.estimate_covariances(refine_cloud, refine_tree, COV_NEIGHBORS, NUM_THREADS)

    return ScanFeatures(
        points=np.asarray(pcd.points),
        normals=np.asarray(pcd.normals),
        fpfh=fpfh,
        voxel=float(voxel),
        refine_points=refine_points,
        fpfh_tree=cKDTree(fpfh),
        refine_cloud=refine_cloud,
        refine_tree=refine_tree,
    )


def default_voxel(scans: list[np.ndarray]) -> float:
    """Voxel size from the scene: 1/100 of the median scan's bounding-box diagonal."""
    if not scans:
        raise InputError("no scans to derive a voxel size from")
    diagonals = [np.linalg.norm(np.ptp(s[np.isfinite(s).all(axis=1)], axis=0)) for s in scans if len(s)]
    return float(np.median(diagonals)) / 100.0
