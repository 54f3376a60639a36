"""Per-scan local features: a voxel grid with normals and GICP covariances, and the keypoints and
descriptors that pairs are matched on: FPFH of the grid points, or keypoints and descriptors computed
elsewhere (``Keypoints``, e.g. YOHO). Computed once per scan and shared by every pair the scan is in, so
the pairwise stage only matches, solves and refines."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
import small_gicp
from scipy.spatial import cKDTree

from sghr_gtsam.types import InputError, Keypoints, Scan

# small_gicp parallelises with OpenMP, whose threads spin while waiting: on a shared 2-core machine
# one thread ran GICP 2.5x faster (wall) than two. scipy's k-d queries use plain threads.
GICP_THREADS = 1
# Neighbour caps of open3d's hybrid searches (the values open3d's own FPFH pipeline uses); they
# bound the cost per point. With 100 the FPFH neighbourhood still fills a 5-voxel radius on a surface.
NORMAL_MAX_NN = 30
FPFH_MAX_NN = 100
# Neighbours for the GICP covariances (small_gicp's default).
COV_NEIGHBORS = 20
# Given keypoints must lie on the scan: median distance to its grid at most this (voxels). The authors'
# YOHO keypoints on the kitchen lie 0.33-0.35 voxels (median; all < 0.9) from the 4.1 cm grid;
# keypoints in another frame or unit lie metres away.
KEYPOINT_MAX_DISTANCE = 2.0


@dataclass(eq=False)
class ScanFeatures:
    """Features of one scan, in the scan's own frame.

    ``points`` (M, 3) float64 voxel-grid centroids; ``normals`` (M, 3) unit normals oriented towards
    the scan's origin; ``voxel`` the grid size. Matching: ``keypoints`` (K, 3) float64 and their
    ``descriptors`` (K, D) float32, which are ``points`` and ``fpfh`` (M, 33) unless they were given
    (then ``fpfh`` is None: not computed). Search structures built once for all pairs:
    ``descriptor_tree`` (k-d tree on ``descriptors``), ``cloud`` (``points`` with GICP covariances,
    small_gicp) and its k-d tree ``cloud_tree``. ``key``: what made them, as the resume cache names them
    (``cache.scan_key``: the scan's content and centre, the voxel and radii); empty when not known.
    """

    points: np.ndarray
    normals: np.ndarray
    fpfh: np.ndarray | None
    voxel: float
    keypoints: np.ndarray
    descriptors: np.ndarray
    descriptor_tree: cKDTree = field(repr=False)
    cloud: small_gicp.PointCloud = field(repr=False)
    cloud_tree: small_gicp.KdTree = field(repr=False)
    key: str = ""

    @classmethod
    def from_arrays(cls, points: np.ndarray, normals: np.ndarray, fpfh: np.ndarray | None, voxel: float,
                    keypoints: np.ndarray, descriptors: np.ndarray) -> "ScanFeatures":
        """Features from their arrays, the search structures built as ``compute_features`` builds them (the resume
        cache stores the arrays only)."""
        return cls(points, normals, fpfh, float(voxel), keypoints, descriptors, cKDTree(descriptors),
                   *_gicp_cloud(points))

    def __len__(self) -> int:
        return len(self.points)

    # Pickling (to worker processes, sghr_gtsam.executor): small_gicp's cloud and tree cannot be pickled,
    # so they are rebuilt from the grid on arrival, exactly as compute_features built them.
    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("cloud", "cloud_tree")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.cloud, self.cloud_tree = _gicp_cloud(self.points)


def query_threads() -> int:
    """Threads for scipy's k-d queries: the cores this process may run on now (an executor's worker is pinned to
    one; a count read at import would be the fork server's, and two threads on one core only take turns)."""
    return len(os.sched_getaffinity(0))


def _gicp_cloud(grid: np.ndarray) -> tuple[small_gicp.PointCloud, small_gicp.KdTree]:
    cloud = small_gicp.PointCloud(grid)
    cloud_tree = small_gicp.KdTree(cloud, num_threads=GICP_THREADS)
    small_gicp.estimate_covariances(cloud, cloud_tree, COV_NEIGHBORS, GICP_THREADS)
    return cloud, cloud_tree


def compute_features(
    points: np.ndarray,
    voxel: float,
    normal_radius: float = 2.0,
    fpfh_radius: float = 5.0,
    given: Keypoints | None = None,
    sensor: np.ndarray | None = None,
) -> ScanFeatures:
    """Voxel grid, normals, GICP covariances and FPFH of one scan; radii in voxels (as in ``Config``).
    With ``given`` keypoints and descriptors no FPFH is computed and pairs are matched on those;
    ``InputError`` when the keypoints do not lie on the scan (another frame or unit).

    Normals point towards ``sensor`` (default: the origin; the pipeline passes the input frame's origin of a scan
    it centred), the scan's origin: the sensor for scans in sensor coordinates (3DMatch),
    the object's inside for object-centred scans (Stanford). Either way they are consistent across
    scans, which FPFH needs (its angles change sign with the normals): unoriented normals lose 4 of
    the 20 right kitchen pairs and 5 of the 24 right bunny pairs.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must be (N, 3), got shape {points.shape}")
    if not voxel > 0:
        raise InputError(f"voxel must be positive, got {voxel}")
    points = points[np.isfinite(points).all(axis=1)]
    if not len(points):
        raise InputError("no finite points")
    cells = float(np.ptp(points, axis=0).max()) / voxel
    if cells >= np.iinfo(np.int32).max:  # open3d's voxel grid indexes cells by int32
        raise InputError(f"its points span {cells:.3g} voxels of {voxel:.3g} (at most 2^31): a stray point far away?")

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(normal_radius * voxel, NORMAL_MAX_NN))
    pcd.orient_normals_towards_camera_location(np.zeros(3) if sensor is None else np.asarray(sensor, dtype=float))
    grid = np.asarray(pcd.points)
    cloud, cloud_tree = _gicp_cloud(grid)

    if given is None:
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(
            pcd, o3d.geometry.KDTreeSearchParamHybrid(fpfh_radius * voxel, FPFH_MAX_NN)
        )
        fpfh = np.ascontiguousarray(np.asarray(fpfh.data).T, dtype=np.float32)
        keypoints, descriptors = grid, fpfh
    else:
        fpfh, keypoints, descriptors = None, given.points, given.descriptors
        _, sq_dist = cloud_tree.batch_nearest_neighbor_search(keypoints, GICP_THREADS)
        off = float(np.sqrt(np.median(sq_dist))) / voxel
        if off > KEYPOINT_MAX_DISTANCE:
            raise InputError(f"keypoints lie {off:.3g} voxels from the scan's points (median; at most "
                             f"{KEYPOINT_MAX_DISTANCE:g}): are they in the scan's own frame and units?")
    return ScanFeatures(
        points=grid,
        normals=np.asarray(pcd.normals),
        fpfh=fpfh,
        voxel=float(voxel),
        keypoints=keypoints,
        descriptors=descriptors,
        descriptor_tree=cKDTree(descriptors),
        cloud=cloud,
        cloud_tree=cloud_tree,
    )


def scan_features(shared: tuple[float, float, float], scan: Scan) -> ScanFeatures | str:
    """An executor task: ``compute_features`` of ``scan`` (``shared``: voxel, normal and FPFH radii), read where
    the task runs, so that its full-resolution points live only there, with normals towards the origin of its input
    frame (``-scan.centre``). The reason, as a string, when it has none (a stray point far away: too many voxels;
    given keypoints off the scan)."""
    voxel, normal_radius, fpfh_radius = shared
    points, given = scan.read()
    try:
        return compute_features(points, voxel, normal_radius, fpfh_radius, given, sensor=-scan.centre)
    except InputError as e:
        return str(e)


def default_voxel(scans: list[np.ndarray]) -> float:
    """Voxel size from the scene: ``voxel_from_spans`` of the scans' finite points."""
    finite = [s[np.isfinite(s).all(axis=1)] for s in map(np.asarray, scans)]
    return voxel_from_spans([np.linalg.norm(np.ptp(s, axis=0)) for s in finite if len(s)])


def voxel_from_spans(spans: list[float]) -> float:
    """Voxel size from the scans' bounding-box diagonals ``spans``: 1/100 of the median one.

    4.2 cm on the 3DMatch kitchen and 2.5 mm on the Stanford bunny, where both scenes do best:
    with kiss-matcher and FPFH at 5 voxels the kitchen gets 19 / 20 / 19 of its 29 overlapping pairs
    right at 3 / 4.2 / 5 cm (3 cm costs 2.5x the time), the bunny 24 / 24 / 22 / 19 at 2 / 2.5 / 3 /
    4 mm (coarser grids miss its 1 mm bound).
    """
    if not len(spans):
        raise InputError("no finite points to derive a voxel size from")
    return float(np.median(spans)) / 100.0
