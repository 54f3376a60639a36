"""The run's store (sghr_gtsam.store): what it reads back is what was computed, to the bit; its memory stays within its
bound; what crosses to a worker is small; a missing or damaged entry is computed again where the scans are and named
where they are not; a run without a cache leaves no temporary folder, failed or not; and a run's poses equal those of
the same run holding every scan's features and grids in memory."""

from __future__ import annotations

import gc
import importlib.util
import pickle
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from sghr_gtsam import pipeline, store
from sghr_gtsam.cache import Cache, entry_path, pyramid_key, scan_key
from sghr_gtsam.config import Config
from sghr_gtsam.executor import parallel_map
from sghr_gtsam.features.local import FEATURES, scan_features
from sghr_gtsam.pipeline import register, run
from sghr_gtsam.registration.refine import PYRAMIDS, scan_pyramid
from sghr_gtsam.scene import load_scene
from sghr_gtsam.store import Attribute, Store, Stored, pair_order
from sghr_gtsam.synthetic import make_scene, write_scene
from sghr_gtsam.types import InputError, Scan

QUIET = {"log": lambda m: None}


@pytest.fixture(scope="module")
def room():
    scene = make_scene(kind="room", n_scans=5, seed=3)
    return [Scan(n, P) for n, P in zip(scene.names, scene.scans)]


@pytest.fixture(autouse=True)
def _fresh_lru(monkeypatch):
    """Each test starts with an empty memory of this process's items (the module's lives as long as the process)."""
    monkeypatch.setattr(store, "_LRU", store._Lru(store.LRU_BYTES))


def _stored(room, cache, voxel=0.08):
    """The room's features and pyramids written through a ``Store`` and read back as ``Stored`` sequences."""
    config = Config(voxel=voxel)
    box = Store(cache)
    settings = (voxel, config.normal_radius, config.fpfh_radius, config.descriptor)
    keys = [scan_key(s, voxel, config) for s in room]
    grid_keys = [pyramid_key(k) for k in keys]
    box.map(FEATURES, scan_features, settings, room, keys, 1, None, None, keep=lambda f: None)
    box.map(PYRAMIDS, scan_pyramid, voxel, room, grid_keys, 1, None, None, keep=lambda p: None)
    return (
        box,
        box.sequence(FEATURES, keys, lambda k: scan_features(settings, room[k])),
        box.sequence(PYRAMIDS, grid_keys, lambda k: scan_pyramid(voxel, room[k])),
    )


@dataclass
class _Item:
    nbytes: int


def test_lru_keeps_within_its_bound_and_drops_the_least_recently_used():
    lru = store._Lru(100)
    loads = []

    def load(key, size):
        return lambda: loads.append(key) or _Item(size)

    for key in "abc":
        lru.get(key, load(key, 30))
    lru.get("a", load("a", 30))  # a is now the most recent: b is the oldest
    lru.get("d", load("d", 30))  # 120 bytes: b goes
    assert list(lru._items) == ["c", "a", "d"] and loads == ["a", "b", "c", "d"]
    lru.get("b", load("b", 30))
    assert loads[-1] == "b" and list(lru._items) == ["a", "d", "b"]
    lru._items["d"].nbytes = 80  # a task built its search structures: the bound counts them at the next read
    lru.get("a", load("a", 30))  # a use, no read: nothing is summed or dropped
    assert list(lru._items) == ["d", "b", "a"] and loads[-1] == "b"
    lru.get("e", load("e", 10))  # 150 bytes: d, the oldest, goes
    assert list(lru._items) == ["b", "a", "e"]
    lru.get("huge", load("huge", 500))  # larger than the bound: kept alone, the newest
    assert list(lru._items) == ["huge"]


def test_items_read_back_are_the_computed_ones_to_the_bit(room, tmp_path):
    voxel, config = 0.08, Config(voxel=0.08)
    settings = (voxel, config.normal_radius, config.fpfh_radius, config.descriptor)
    _, features, pyramids = _stored(room, Cache(tmp_path))
    for k, scan in enumerate(room):
        computed, read = scan_features(settings, scan), features[k]
        for name in ("points", "normals", "fpfh", "keypoints", "descriptors"):
            a, b = getattr(computed, name), getattr(read, name)
            assert a.dtype == b.dtype and np.array_equal(a, b), name
        assert read.voxel == computed.voxel
        # the lazily built search structures answer as the computed ones
        q = computed.descriptors[:50]
        assert np.array_equal(read.descriptor_tree.query(q, k=2)[1], computed.descriptor_tree.query(q, k=2)[1])
        grid = scan_pyramid(voxel, scan)
        assert read is features[k] and pyramids[k].voxels == grid.voxels
        assert all(np.array_equal(a, b) for a, b in zip(pyramids[k].grids, grid.grids))
    assert np.array_equal(Attribute(features, "points")[2], features[2].points)


def test_a_sequence_pickles_as_its_folder_and_keys(room, tmp_path):
    _, features, _ = _stored(room, Cache(tmp_path))
    sent = pickle.dumps(features)
    arrays = pickle.dumps([features[k] for k in range(len(room))])
    assert len(sent) < 100 * len(room) + 300 < len(arrays) / 100, (len(sent), len(arrays))
    worker = pickle.loads(sent)  # what a worker gets: no store, no scans, the same items
    assert worker._store is None and worker.keys == features.keys
    store._LRU._items.clear()
    assert np.array_equal(worker[1].fpfh, features[1].fpfh)


def test_missing_or_damaged_entries_are_computed_again_where_the_scans_are(room, tmp_path):
    box, features, pyramids = _stored(room, Cache(tmp_path))
    expected = [features[k].fpfh.copy() for k in range(3)]
    store._LRU._items.clear()
    entry_path(tmp_path, "features", features.keys[0]).unlink()
    entry_path(tmp_path, "features", features.keys[1]).write_bytes(b"not an npz")
    damaged = entry_path(tmp_path, "pyramids", pyramids.keys[2])
    damaged.write_bytes(damaged.read_bytes()[:100])
    worker = pickle.loads(pickle.dumps(features))
    with pytest.raises(
        InputError, match=f"^{re.escape(str(entry_path(tmp_path, 'features', features.keys[1])))} is missing or damaged"
    ):
        worker[1]
    for k in range(3):
        assert np.array_equal(features[k].fpfh, expected[k])
    assert len(pyramids[2].grids) >= 1
    assert box.disk.unreadable == 2 and box.disk.counts["features"]["computed"] == 5 + 2
    store._LRU._items.clear()
    assert np.array_equal(worker[1].fpfh, expected[1])  # written back whole


def test_a_worker_that_does_not_see_the_folder_says_so(room, tmp_path):
    _, features, _ = _stored(room, Cache(tmp_path / "out" / "cache"))
    elsewhere = Stored(str(tmp_path / "other" / "cache"), FEATURES, features.keys)
    with pytest.raises(
        InputError,
        match="does not exist on .*: on a Ray cluster of several machines the output "
        "folder must be on a filesystem every node mounts at the same path$",
    ):
        elsewhere[0]


def _points(features: Stored, k: int) -> np.ndarray:
    return features[k].points


@pytest.mark.skipif(importlib.util.find_spec("ray") is None, reason="the optional extra ray is not installed")
def test_a_ray_worker_that_does_not_see_the_store_ends_the_run_with_one_line(tmp_path):
    import ray

    elsewhere = Stored(str(tmp_path / "not-on-this-node"), FEATURES, ("0" * 64,))
    try:
        with pytest.raises(InputError, match="does not exist on .*: on a Ray cluster of several machines"):
            parallel_map(_points, elsewhere, [0], 1, ray="local")
    finally:
        ray.shutdown()


def test_a_temporary_store_goes_with_its_last_user(room, tmp_path):
    box, features, _ = _stored(room, None, voxel=0.08)
    folder = box.folder
    assert folder.is_dir() and folder.name.startswith(".store-")
    first = features[0].points.copy()
    box.close()
    assert not folder.exists() and not box.open
    store._LRU._items.clear()
    assert np.array_equal(features[0].points, first)  # computed again, not written back
    assert not folder.exists()
    scratch = Store(None, scratch=tmp_path)
    kept = scratch.folder
    assert kept.parent == tmp_path
    del scratch
    gc.collect()
    assert not kept.exists()


def test_pairs_run_scan_by_scan():
    ij = np.array([[3, 1], [0, 2], [1, 2], [0, 1], [2, 4]])
    assert pair_order(ij).tolist() == [3, 1, 2, 0, 4]


class _InMemory(Store):
    """The way before the store: every scan's features and grids computed in this process and held in lists."""

    def map(self, kind, fn, shared, tasks, keys, workers, on_result, ray, keep):
        return [keep(fn(shared, task)) for task in tasks]

    def sequence(self, kind, keys, compute):
        return _Held([compute(k) for k in range(len(keys))], tuple(keys))


class _Held(list):
    def __init__(self, items, keys):
        super().__init__(items)
        self.keys = keys


@pytest.fixture(scope="module")
def demo_room(tmp_path_factory):
    folder = tmp_path_factory.mktemp("store") / "scene"
    write_scene(make_scene(kind="room", n_scans=8, seed=0), folder)  # the demo's room
    return folder


@pytest.fixture(scope="module")
def in_memory(demo_room):
    scans, skipped = load_scene(demo_room, Config(), **QUIET)
    return register(scans, Config(record=False, workers=1), skipped=skipped, store=_InMemory(None), **QUIET)


@pytest.mark.parametrize(
    "workers, cache, lru",
    [(2, True, store.LRU_BYTES), (1, False, 0)],
    ids=["pool-2-cached", "in-process-no-cache-lru-0"],
)
def test_poses_equal_a_run_holding_everything_in_memory(
    demo_room, in_memory, tmp_path, monkeypatch, workers, cache, lru
):
    """Through the store, with every item read again at each use (a memory of 0 bytes) or not, the run gives the
    poses of one that holds every scan's features and grids, to the last bit."""
    monkeypatch.setattr(store, "_LRU", store._Lru(lru))
    result = run(demo_room, tmp_path / "out", Config(record=False, workers=workers, cache=cache), **QUIET)
    np.testing.assert_array_equal(result.poses, in_memory.poses)
    assert result.densify == in_memory.densify and result.densify["refine_tried"] > 0
    assert [p.inliers for p in result.pairs] == [p.inliers for p in in_memory.pairs]
    assert np.array_equal(result.features[3].points, in_memory.features[3].points)  # after the run, too
    assert not list(tmp_path.glob("**/.store-*"))


def test_a_failed_run_without_a_cache_leaves_no_temporary_folder(demo_room, tmp_path, monkeypatch):
    def fail(*args, **kwargs):
        raise RuntimeError("stopped in synchronization")

    monkeypatch.setattr(pipeline, "synchronize", fail)
    out = tmp_path / "runs" / "out"
    with pytest.raises(RuntimeError, match="stopped in synchronization"):
        run(demo_room, out, Config(record=False, workers=2, cache=False), **QUIET)
    assert not out.exists() and not any(p.name.startswith(".") for p in out.parent.iterdir())

    made = []
    monkeypatch.setattr(pipeline, "Store", lambda cache: made.append(Store(cache)) or made[-1])
    scans = [Scan(p.name, p) for p in sorted(Path(demo_room).glob("*.ply"))]
    with pytest.raises(RuntimeError, match="stopped in synchronization"):
        register(scans, Config(record=False, workers=1), **QUIET)
    assert len(made) == 1 and not made[0].folder.exists()
