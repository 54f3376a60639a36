"""Per-scan local features: a voxel grid with normals and GICP covariances, and the keypoints and
descriptors that pairs are matched on: FPFH of the grid points, or keypoints and descriptors computed
elsewhere (``Keypoints``, e.g. YOHO). Computed once per scan and shared by every pair the scan is in, so
the pairwise stage only matches, solves and refines."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import open3d as o3d
import small_gicp
from scipy.spatial import cKDTree

from sghr_gtsam.cache import Kind
from sghr_gtsam.config import DESCRIPTORS
from sghr_gtsam.features.learned import learned_descriptors
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
# YOHO keypoints on 3DMatch fragments lie 0.33-0.35 voxels (median; all < 0.9) from the 4.1 cm grid;
# keypoints in another frame or unit lie metres away.
KEYPOINT_MAX_DISTANCE = 2.0
# Memory per point of the search structures (measured: 200k points): a GICP cloud with its covariances (and
# normals), its k-d tree and scipy's on the points (22 bytes); a scipy k-d tree on D-d descriptors copies them as
# float64 (8·D) and adds this.
GICP_BYTES = 252
TREE_BYTES = 35
# Voxels a scan may span along an axis: open3d's voxel grid indexes its cells by int32.
MAX_CELLS = int(np.iinfo(np.int32).max)


@dataclass(eq=False)
class ScanFeatures:
    """Features of one scan, in the scan's own frame.

    ``points`` (M, 3) float64 voxel-grid centroids; ``normals`` (M, 3) unit normals oriented towards
    the scan's origin; ``voxel`` the grid size. Matching: ``keypoints`` (K, 3) float64 and their
    ``descriptors`` (K, D) float32, which are ``points`` and ``fpfh`` (M, 33) unless they were given
    (then ``fpfh`` is None: not computed). Search structures, built from the arrays on first use in whichever
    process uses them (they are neither stored nor pickled: a task that only reads the points builds none):
    ``descriptor_tree`` (k-d tree on ``descriptors``), ``cloud`` (``points`` with GICP covariances,
    small_gicp), its k-d tree ``cloud_tree`` and scipy's ``point_tree`` (``registration.icp``).
    """

    points: np.ndarray
    normals: np.ndarray
    fpfh: np.ndarray | None
    voxel: float
    keypoints: np.ndarray
    descriptors: np.ndarray

    def __post_init__(self) -> None:
        self._tree: cKDTree | None = None
        self._gicp: tuple[small_gicp.PointCloud, small_gicp.KdTree, cKDTree] | None = None

    def __len__(self) -> int:
        return len(self.points)

    @property
    def descriptor_tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.descriptors)
        return self._tree

    @property
    def cloud(self) -> small_gicp.PointCloud:
        return self._built_gicp()[0]

    @property
    def cloud_tree(self) -> small_gicp.KdTree:
        return self._built_gicp()[1]

    @property
    def point_tree(self) -> cKDTree:
        return self._built_gicp()[2]

    def _built_gicp(self) -> tuple[small_gicp.PointCloud, small_gicp.KdTree, cKDTree]:
        if self._gicp is None:
            self._gicp = search_structures(self.points)
        return self._gicp

    @property
    def nbytes(self) -> int:
        """Memory it holds: its arrays and the search structures built so far (``TREE_BYTES``, ``GICP_BYTES``)."""
        arrays = sum(
            a.nbytes for a in (self.points, self.normals, self.fpfh, self.keypoints, self.descriptors) if a is not None
        )
        tree = 0 if self._tree is None else len(self.descriptors) * (8 * self.descriptors.shape[1] + TREE_BYTES)
        return arrays + tree + (0 if self._gicp is None else len(self.points) * GICP_BYTES)

    def __getstate__(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if k not in ("_tree", "_gicp")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self.__post_init__()


def _encode_features(f: ScanFeatures | str) -> dict[str, np.ndarray] | None:
    if isinstance(f, str):  # a scan without features: its reason is not stored
        return None
    out = {"points": f.points, "normals": f.normals, "voxel": np.float64(f.voxel)}
    if f.fpfh is None:
        out["keypoints"] = f.keypoints
    else:
        out["fpfh"] = f.fpfh
    if f.descriptors is not f.fpfh:  # given, or learned on the grid
        out["descriptors"] = f.descriptors
    return out


def _decode_features(a: dict[str, np.ndarray]) -> ScanFeatures:
    fpfh = a.get("fpfh")
    keypoints = a["points"] if fpfh is not None else a["keypoints"]
    features = ScanFeatures(a["points"], a["normals"], fpfh, float(a["voxel"]), keypoints, a.get("descriptors", fpfh))
    # Readable arrays of the wrong shape or with NaN (an entry edited or damaged inside) failed every later run.
    m, k = len(features.points), len(features.keypoints)
    shapes = [(features.points, (m, 3)), (features.normals, (m, 3)), (features.keypoints, (k, 3))]
    if any(x.shape != shape or not np.isfinite(x).all() for x, shape in shapes) or len(features.descriptors) != k:
        raise ValueError("features entry of inconsistent shapes or non-finite values")
    return features


FEATURES = Kind("features", _encode_features, _decode_features)
"""A scan's features in the cache and the store (``cache.Kind``)."""


def query_threads() -> int:
    """Threads for scipy's k-d queries: the cores this process may run on now (an executor's worker is pinned to
    one; a count read at import would be the fork server's, and two threads on one core only take turns)."""
    return len(os.sched_getaffinity(0))


def search_structures(
    grid: np.ndarray, with_normals: bool = False
) -> tuple[small_gicp.PointCloud, small_gicp.KdTree, cKDTree]:
    """What GICP and the nearest-point searches of a grid (m, 3) need: small_gicp's cloud with the covariances of each
    point's ``COV_NEIGHBORS`` (and the normals of the same neighbourhoods ``with_normals``), small_gicp's k-d tree and
    scipy's (``registration.icp``)."""
    cloud = small_gicp.PointCloud(grid)
    cloud_tree = small_gicp.KdTree(cloud, num_threads=GICP_THREADS)
    estimate = small_gicp.estimate_normals_covariances if with_normals else small_gicp.estimate_covariances
    estimate(cloud, cloud_tree, COV_NEIGHBORS, GICP_THREADS)
    return cloud, cloud_tree, cKDTree(grid)


def compute_features(
    points: np.ndarray,
    voxel: float,
    normal_radius: float = 2.0,
    fpfh_radius: float = 5.0,
    given: Keypoints | None = None,
    sensor: np.ndarray | None = None,
    descriptor: str = "fpfh",
) -> ScanFeatures:
    """Voxel grid, normals and FPFH of one scan (its GICP covariances on first use); radii in voxels (as in
    ``Config``). Pairs are matched on the FPFH, or with ``descriptor`` 'learned' on ``features.learned``'s
    descriptors of the same grid points (the FPFH is kept for the global feature).
    With ``given`` keypoints and descriptors no FPFH is computed and pairs are matched on those;
    ``InputError`` when the keypoints do not lie on the scan (another frame or unit).

    Normals point towards ``sensor`` (default: the origin; the pipeline passes the input frame's origin of a scan
    it centred), the scan's origin: the sensor for scans in sensor coordinates (3DMatch),
    the object's inside for object-centred scans (Stanford). Either way they are consistent across
    scans, which FPFH needs (its angles change sign with the normals): unoriented normals lose 4 of
    the 20 right 3DMatch pairs and 5 of the 24 right pairs of an object's range scans.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must be (N, 3), got shape {points.shape}")
    if not voxel > 0:
        raise InputError(f"voxel must be positive, got {voxel}")
    if descriptor not in DESCRIPTORS:
        raise InputError(f"unknown descriptor {descriptor!r} ({', '.join(DESCRIPTORS)})")
    points = points[np.isfinite(points).all(axis=1)]
    if not len(points):
        raise InputError("no finite points")
    cells = float(np.ptp(points, axis=0).max()) / voxel
    if cells >= MAX_CELLS:
        raise InputError(f"its points span {cells:.3g} voxels of {voxel:.3g} (at most 2^31): a stray point far away?")

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(normal_radius * voxel, NORMAL_MAX_NN))
    pcd.orient_normals_towards_camera_location(np.zeros(3) if sensor is None else np.asarray(sensor, dtype=float))
    grid = np.asarray(pcd.points)

    if given is None:
        return _described(pcd, voxel, fpfh_radius, descriptor)
    features = ScanFeatures(grid, np.asarray(pcd.normals), None, float(voxel), given.points, given.descriptors)
    _, sq_dist = features.cloud_tree.batch_nearest_neighbor_search(given.points, GICP_THREADS)
    off = float(np.sqrt(np.median(sq_dist))) / voxel
    if off > KEYPOINT_MAX_DISTANCE:
        raise InputError(
            f"keypoints lie {off:.3g} voxels from the scan's points (median; at most "
            f"{KEYPOINT_MAX_DISTANCE:g}): are they in the scan's own frame and units?"
        )
    return features


def _described(pcd: o3d.geometry.PointCloud, voxel: float, fpfh_radius: float, descriptor: str) -> ScanFeatures:
    """The ``ScanFeatures`` of a voxel grid with oriented normals: FPFH, and the ``descriptor`` matched on."""
    fpfh = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(fpfh_radius * voxel, FPFH_MAX_NN)
    )
    fpfh = np.ascontiguousarray(np.asarray(fpfh.data).T, dtype=np.float32)
    grid, normals = np.asarray(pcd.points), np.asarray(pcd.normals)
    matched = fpfh if descriptor == "fpfh" else learned_descriptors(grid, normals, voxel, workers=query_threads())
    return ScanFeatures(grid, normals, fpfh, float(voxel), grid, matched)


def grid_features(
    grid: np.ndarray, normals: np.ndarray, voxel: float, fpfh_radius: float = 5.0, descriptor: str = "fpfh"
) -> ScanFeatures:
    """Features, as ``compute_features`` gives them, of points already on a voxel grid (``grid`` (m, 3), one a
    cell) with their unit oriented ``normals``."""
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(grid, dtype=np.float64)))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, dtype=np.float64))
    return _described(pcd, voxel, fpfh_radius, descriptor)


def scan_features(shared: tuple[float, float, float, str], scan: Scan) -> ScanFeatures | str:
    """An executor task: ``compute_features`` of ``scan`` (``shared``: voxel, normal and FPFH radii, descriptor),
    read where the task runs, so that its full-resolution points live only there, with normals towards the origin of
    its input frame (``-scan.centre``). The reason, as a string, when it has none (a stray point far away: too many
    voxels; given keypoints off the scan)."""
    voxel, normal_radius, fpfh_radius, descriptor = shared
    points, given = scan.read()
    try:
        return compute_features(
            points, voxel, normal_radius, fpfh_radius, given, sensor=-scan.centre, descriptor=descriptor
        )
    except InputError as e:
        return str(e)


def default_voxel(scans: list[np.ndarray]) -> float:
    """Voxel size from the scene: ``voxel_from_spans`` of the scans' finite points."""
    finite = [s[np.isfinite(s).all(axis=1)] for s in map(np.asarray, scans)]
    return voxel_from_spans([np.linalg.norm(np.ptp(s, axis=0)) for s in finite if len(s)])


def voxel_from_spans(spans: list[float]) -> float:
    """Voxel size from the scans' bounding-box diagonals ``spans``: 1/100 of the median one.

    4.2 cm on 3DMatch fragments and 2.5 mm on an object's range scans, where both do best:
    with kiss-matcher and FPFH at 5 voxels nine 3DMatch fragments get 19 / 20 / 19 of its 29 overlapping pairs
    right at 3 / 4.2 / 5 cm (3 cm costs 2.5x the time), the object 24 / 24 / 22 / 19 at 2 / 2.5 / 3 /
    4 mm (coarser grids miss its 1 mm bound).
    """
    if not len(spans):
        raise InputError("no finite points to derive a voxel size from")
    return float(np.median(spans)) / 100.0
