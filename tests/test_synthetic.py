"""The generated scenes: fast, rigid ground truth, scans in their own frames that overlap their
neighbours, and registrable by FPFH + RANSAC + ICP at the scene's voxel size."""

import time

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import cKDTree

from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.io.scans import list_scans, load_scan
from sghr_gtsam.se3 import inv_T, relative_errors, rotation_angle, transform_points
from sghr_gtsam.synthetic import KINDS, make_scene, write_scene


@pytest.fixture(scope="module", params=KINDS)
def scene(request):
    return make_scene(kind=request.param, n_scans=6, seed=0)


def _overlap(A: np.ndarray, B: np.ndarray, radius: float) -> float:
    """Fraction of the points of A within ``radius`` of B."""
    return float((cKDTree(B).query(A)[0] < radius).mean())


@pytest.mark.parametrize("kind", KINDS)
def test_six_scans_in_well_under_two_seconds(kind):
    t0 = time.perf_counter()
    s = make_scene(kind=kind, n_scans=6, seed=3)
    assert time.perf_counter() - t0 < 2.0
    assert len(s.scans) == len(s.names) == len(s.poses) == 6
    for P in s.scans:
        assert P.dtype == np.float64 and P.shape[1] == 3 and np.isfinite(P).all()
        assert 3_000 <= len(P) <= (40_000 if kind == "fragments" else 15_000)  # fused from many frames


def test_ground_truth_poses_are_rigid(scene):
    R = scene.poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-12)
    np.testing.assert_array_equal(scene.poses[:, 3], np.tile([0.0, 0.0, 0.0, 1.0], (6, 1)))


def test_scans_are_in_their_own_sensor_frames(scene):
    """Every point lies in front of its sensor (z > 0) and the poses are far from the identity and
    from each other, so that registering needs real rotations and translations."""
    for P in scene.scans:
        assert (P[:, 2] > 0).all()
    assert np.degrees(rotation_angle(scene.poses[0][:3, :3])) > 20
    rel = inv_T(scene.poses[:-1]) @ scene.poses[1:]
    assert (np.degrees(rotation_angle(rel[:, :3, :3])) > 10).all()
    assert (np.linalg.norm(rel[:, :3, 3], axis=1) > 0.3).all()


def test_consecutive_scans_overlap_under_ground_truth_and_not_under_identity(scene):
    world = [transform_points(T, P) for T, P in zip(scene.poses, scene.scans)]
    for i in range(len(world) - 1):
        aligned = _overlap(world[i], world[i + 1], 2 * scene.voxel)
        unaligned = _overlap(scene.scans[i], scene.scans[i + 1], 2 * scene.voxel)
        assert aligned > 0.3, (i, aligned)
        assert aligned > unaligned + 0.1, (i, aligned, unaligned)


def test_each_scan_sees_only_part_of_the_scene(scene):
    world = [transform_points(T, P) for T, P in zip(scene.poses, scene.scans)]
    everything = np.concatenate(world)[::4]
    for W in world:
        assert _overlap(everything, W, 2 * scene.voxel) < 0.8


def test_same_seed_same_scene_other_seed_other_scene():
    a, b, c = (make_scene("room", 3, seed=s) for s in (5, 5, 6))
    assert a.names == b.names == ["scan_00.ply", "scan_01.ply", "scan_02.ply"]
    np.testing.assert_array_equal(a.poses, b.poses)
    for P, Q in zip(a.scans, b.scans):
        np.testing.assert_array_equal(P, Q)
    assert not np.allclose(a.poses, c.poses)


@pytest.mark.parametrize("kind", KINDS)
def test_neighbouring_scans_register_with_fpfh_ransac_icp(kind):
    """What the demo relies on. Normals are oriented towards each scan's origin (its sensor)."""
    s = make_scene(kind=kind, n_scans=6, seed=0)
    v = s.voxel
    reg = o3d.pipelines.registration

    def features(P):
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P)).voxel_down_sample(v)
        cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2 * v, max_nn=30))
        cloud.orient_normals_towards_camera_location(np.zeros(3))
        fpfh = reg.compute_fpfh_feature(cloud, o3d.geometry.KDTreeSearchParamHybrid(radius=5 * v, max_nn=100))
        return cloud, fpfh

    o3d.utility.random.seed(0)
    for i in (0, 3):
        (target, f_target), (source, f_source) = features(s.scans[i]), features(s.scans[i + 1])
        coarse = reg.registration_ransac_based_on_feature_matching(
            source,
            target,
            f_source,
            f_target,
            True,
            1.5 * v,
            reg.TransformationEstimationPointToPoint(False),
            3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9), reg.CorrespondenceCheckerBasedOnDistance(1.5 * v)],
            reg.RANSACConvergenceCriteria(100_000, 0.999),
        )
        fine = reg.registration_icp(
            source, target, 1.5 * v, coarse.transformation, reg.TransformationEstimationPointToPlane()
        )
        T_gt = inv_T(s.poses[i]) @ s.poses[i + 1]
        rot, _ = relative_errors(fine.transformation, T_gt)
        # Misplacement of the scan's own points: the translation of T_ij alone would scale the
        # rotation error by the 2 m from the object to its sensor.
        P = s.scans[i + 1]
        shift = np.linalg.norm(transform_points(fine.transformation, P) - transform_points(T_gt, P), axis=1)
        assert rot < 1.5 and np.sqrt(np.mean(shift**2)) < 0.5 * v, (i, rot, shift)


def test_write_scene_with_mixed_formats_reads_back(tmp_path):
    s = make_scene("object", n_scans=5, seed=1)
    paths = write_scene(s, tmp_path / "scene", formats=("ply", "npy", "xyz", "pcd", "npz"))
    assert [p.name for p in paths] == ["scan_00.ply", "scan_01.npy", "scan_02.xyz", "scan_03.pcd", "scan_04.npz"]
    assert list_scans(tmp_path / "scene") == paths  # gt_poses.txt is not a scan
    for path, P in zip(paths, s.scans):
        np.testing.assert_allclose(load_scan(path), P, atol=1e-6 if path.suffix == ".pcd" else 0)
    names, poses = read_poses(tmp_path / "scene" / "gt_poses.txt")
    assert names == [p.name for p in paths]
    np.testing.assert_array_equal(poses, s.poses)


def test_default_write_uses_the_scene_names(tmp_path):
    s = make_scene("room", n_scans=2, seed=0)
    assert [p.name for p in write_scene(s, tmp_path)] == s.names


def test_bad_arguments():
    with pytest.raises(ValueError, match="unknown scene kind"):
        make_scene("garden")
    with pytest.raises(ValueError, match="at least 2"):
        make_scene(n_scans=1)


@pytest.mark.parametrize("noise", [float("nan"), float("inf"), -0.01])
def test_a_noise_no_sensor_has_is_refused(noise):
    """A NaN noise gave scans of NaN points without a word."""
    with pytest.raises(ValueError, match="noise must be a finite number"):
        make_scene(kind="room", n_scans=2, noise=noise)
