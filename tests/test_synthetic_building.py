"""The generated building and hotel: a floor that grows with the number of scans while each scan overlaps a bounded
number of others (measured from the points under the GT poses), one connected overlap graph, determinism,
streaming, identical hotel rooms; and end to end, every scan registered to GT or flagged."""

import weakref

import numpy as np
import pytest
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from data_tools.gt_overlap import combine, directed_overlap_matrix
from sghr_gtsam import synthetic
from sghr_gtsam.config import Config
from sghr_gtsam.evaluate import score_result
from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.io.scans import load_scan, write_scan
from sghr_gtsam.pipeline import Scan, register
from sghr_gtsam.se3 import inv_T, transform_points
from sghr_gtsam.synthetic import make_scene, write_scene
from sghr_gtsam.synthetic.building import building_layout

OVERLAP = 0.1  # a pair overlaps when this fraction of their points (mean of both ways) lie within 2 voxels


def _overlaps(scene) -> np.ndarray:
    """Symmetric GT overlap of every pair from the scans' points under the GT poses (0 on the diagonal)."""
    M = combine(
        directed_overlap_matrix(list(scene.scans), scene.poses, 2 * scene.voxel, scene.voxel, max_points=400), "mean"
    )
    np.fill_diagonal(M, 0.0)
    return M


@pytest.fixture(scope="module")
def sizes():
    """Two buildings, one branch (30 scans) and two branches (100 scans), with their overlaps."""
    return {n: (scene, _overlaps(scene)) for n in (30, 100) for scene in [make_scene("building", n, seed=1)]}


def test_the_floor_grows_with_the_scans_while_the_overlaps_per_scan_stay_bounded(sizes):
    areas = {}
    for n, (scene, M) in sizes.items():
        assert len(scene.scans) == len(scene.names) == len(scene.poses) == n
        xy = np.concatenate([transform_points(T, P[::50]) for T, P in zip(scene.poses, scene.scans)])[:, :2]
        areas[n] = np.prod(np.ptp(xy, axis=0))
        partners = (M >= OVERLAP).sum(axis=1)
        assert partners.max() <= 16 and 3 <= np.median(partners) <= 12, (n, np.bincount(partners))
    assert areas[100] > 2.5 * areas[30], areas


def test_the_overlap_graph_is_connected(sizes):
    """Doorway views see room and corridor, views across the corridors overlap their neighbours, the spine joins
    the branches: one part."""
    for n, (_, M) in sizes.items():
        assert connected_components(M >= OVERLAP)[0] == 1, n


def test_scans_are_views_of_the_room_kind(sizes):
    scene, _ = sizes[30]
    for P in scene.scans:
        assert P.dtype == np.float64 and P.shape[1] == 3 and np.isfinite(P).all()
        assert 5_000 <= len(P) <= 15_000 and (P[:, 2] > 0).all()
    R = scene.poses[:, :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, 1, 2), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)


def test_same_seed_same_scans_in_any_order_other_seed_other_scene():
    a, b, c = (make_scene("building", 12, seed=s) for s in (3, 3, 4))
    late = b.scans[9]  # read first: each scan has its own seed
    np.testing.assert_array_equal(a.poses, b.poses)
    for P, Q in zip(a.scans, b.scans):
        np.testing.assert_array_equal(P, Q)
    np.testing.assert_array_equal(a.scans[9], late)
    assert not np.allclose(a.poses, c.poses)


def test_names_sort_in_scan_order_for_thousands():
    scene = make_scene("building", 1000, seed=0)
    assert scene.names[0] == "scan_000.ply" and scene.names[-1] == "scan_999.ply"
    assert sorted(scene.names) == scene.names


@pytest.mark.parametrize("kind", ["building", "room"])
def test_writing_a_building_holds_one_scan_at_a_time(tmp_path, monkeypatch, kind):
    """``write_scene`` streams a building: when a scan is written, no scan written before it is still alive. The
    room kind, a list, keeps them all (the check can fail)."""
    scene = make_scene(kind, 10, seed=2)
    written, alive = [], []

    def spy(path, points):
        alive.append(sum(ref() is not None for ref in written))
        written.append(weakref.ref(points))
        write_scan(path, points)

    monkeypatch.setattr(synthetic, "write_scan", spy)
    paths = write_scene(scene, tmp_path)
    assert alive == ([0] * 10 if kind == "building" else list(range(10)))
    names, poses = read_poses(tmp_path / "gt_poses.txt")
    assert names == [p.name for p in paths] == scene.names
    np.testing.assert_allclose(poses, scene.poses, atol=1e-9)
    np.testing.assert_allclose(load_scan(paths[7]), scene.scans[7], atol=1e-9)


def _room_points(scene, layout, room: int) -> np.ndarray:
    """World points of the views from a room's ellipse (its scans but the last two, the doorway views)."""
    views = np.flatnonzero(layout.cell_of_scan == room)[:-2]
    return np.concatenate([transform_points(scene.poses[k], scene.scans[k]) for k in views])


@pytest.mark.parametrize("kind", ["hotel", "building"])
def test_hotel_rooms_are_one_room(kind):
    """A room's points moved into another room's frame land on that room's points in the hotel only."""
    scene = make_scene(kind, 24, seed=4)
    layout = building_layout(24, seed=4, identical_rooms=kind == "hotel")
    a, b = [k for k, cell in enumerate(layout.cells) if cell.kind == "room"][:2]
    moved = transform_points(layout.cells[a].frame @ inv_T(layout.cells[b].frame), _room_points(scene, layout, b))
    near = (cKDTree(_room_points(scene, layout, a)).query(moved)[0] < 0.02).mean()
    assert near > 0.6 if kind == "hotel" else near < 0.15, near


def test_too_few_scans_for_a_building():
    with pytest.raises(ValueError, match="at least 9 scans"):
        make_scene("building", 8)


def _register(scene):
    return register(
        [Scan(n, P) for n, P in zip(scene.names, scene.scans)], Config(record=False, seed=0), log=lambda m: None
    )


def test_a_small_building_registers_to_ground_truth():
    """16 scans (two rooms, a corridor): every scan placed without a flag lands within 5° / 0.2 m of GT, and that
    is nearly every scan."""
    scene = make_scene("building", 16, seed=2)
    score = score_result(_register(scene), scene.names, scene.poses)
    assert score.unflagged_wrong == []
    assert len(score.placed) - len(score.flagged) >= 14, score.flagged


@pytest.mark.xfail(
    strict=True,
    reason=(
        "identical rooms: registrations and free space cannot tell the twin rooms apart; verification splits off the "
        "groups that dropped registrations place elsewhere (look-alikes), but the world part still stacks scans of "
        "both rooms (2 of its 5 turned 180°), each loop of it closing"
    ),
)
def test_a_small_hotel_places_no_scan_wrongly_without_a_flag():
    """The repeated-room scene (16 scans, two identical rooms facing each other across the corridor): the graph
    stacks the rooms, and free space cannot tell the two placements apart. No scan should be placed wrongly in
    the trusted model: the stacked room doubted or a part of its own."""
    scene = make_scene("hotel", 16, seed=0)
    result = _register(scene)
    assert score_result(result, scene.names, scene.poses).unflagged_wrong == []


@pytest.mark.xfail(
    strict=True,
    reason=(
        "look-alikes (the repeated-room test is the 16-scan hotel above), measured: the hotel "
        "of 24 scans (seed 1; three identical rooms) stacks its rooms, and no "
        "group of scans has more than two dropped registrations agreeing on another placement: the top-10 graph holds "
        "look-alike registrations between the rooms and hardly any right one between rooms and corridors. 21 scans "
        "are placed wrongly without a flag (docs/BENCHMARKS.md at 18b90a6, look-alikes; 20 before the free-space blame)"
    ),
)
def test_a_larger_hotel_places_no_scan_wrongly_without_a_flag():
    scene = make_scene("hotel", 24, seed=1)
    assert score_result(_register(scene), scene.names, scene.poses).unflagged_wrong == []


def test_a_scan_that_one_registration_places_elsewhere_and_outweighs_its_own_is_doubted():
    """A 12-scan building (seed 0): three light registrations (16-25 inliers) agree on scan_01 turned 180° in its
    corridor and close loops with the scans they join, and synchronization keeps them; the one right registration
    (106 inliers), dropped, outweighs them. With two dropped registrations asked for, the scan stood verified 179°
    off; now it is doubted and every scan placed without a flag lands within 5° / 0.2 m of GT."""
    scene = make_scene("building", 12, seed=0)
    result = _register(scene)
    assert score_result(result, scene.names, scene.poses).unflagged_wrong == []
    assert result.verdict.doubts == {"scan_01.ply": "competing placement"}, result.verdict.doubts
