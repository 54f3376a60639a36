"""The resume cache (sghr_gtsam.cache): what it reuses, what misses it, damaged entries, and a run killed during
pairwise registration resumed to the same poses."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sghr_gtsam.cache import Cache, pair_key, refined_key, scan_key
from sghr_gtsam.config import Config
from sghr_gtsam.io.results import CACHE
from sghr_gtsam.pipeline import register
from sghr_gtsam.scene import load_scene
from sghr_gtsam.synthetic import make_scene, write_scene
from sghr_gtsam.types import InputError, Keypoints, Scan

ROOT = Path(__file__).resolve().parents[1]


def _counts(result) -> dict[str, tuple[int, int]]:
    return {kind: (c["cached"], c["computed"]) for kind, c in result.cache.items() if kind != "unreadable"}


def test_keys_change_with_every_parameter_and_the_content():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(200, 3))
    scan, config = Scan("a", P), Config()
    base = scan_key(scan, 0.05, config)
    assert base == scan_key(Scan("renamed", P.copy()), 0.05, config)  # content, not name or identity
    changed = [
        scan_key(Scan("a", P + 1e-12), 0.05, config),
        scan_key(scan, 0.051, config),
        scan_key(replace(scan, centre=np.array([0.0, 0.0, 1.0])), 0.05, config),
        scan_key(replace(scan, keypoints=Keypoints(P[:10], rng.random((10, 4)))), 0.05, config),
    ]
    changed += [
        scan_key(scan, 0.05, replace(config, **{name: value}))
        for name, value in (("normal_radius", 2.5), ("fpfh_radius", 4.0), ("descriptor", "learned"))
    ]
    assert len({base, *changed}) == len(changed) + 1
    pair = pair_key(base, changed[0], config)
    others = [pair_key(changed[0], base, config)] + [
        pair_key(base, changed[0], replace(config, **{name: value}))
        for name, value in (("matcher", "kiss"), ("icp_distance", 2.0), ("seed", 1))
    ]
    assert len({pair, *others}) == len(others) + 1
    guess = np.eye(4)
    moved = guess.copy()
    moved[0, 3] = 1e-15
    assert (
        len(
            {
                refined_key(base, changed[0], guess, 1.5, 15),
                refined_key(base, changed[0], moved, 1.5, 15),
                refined_key(base, changed[0], guess, 2.0, 15),
                refined_key(base, changed[0], guess, 1.5, 16),
            }
        )
        == 4
    )
    assert pair_key("", base, config) is None and refined_key(base, "", guess, 1.5, 15) is None  # unknown: not cached


@pytest.fixture(scope="module")
def room():
    scene = make_scene(kind="room", n_scans=4, seed=2)
    return [Scan(n, P) for n, P in zip(scene.names, scene.scans)]


def test_cache_reuses_what_matches_recomputes_what_changed_or_is_damaged(room, tmp_path):
    config = Config(record=False, workers=1)
    quiet = {"log": lambda m: None}
    first = register(room, config, cache=Cache(tmp_path), **quiet)
    pairs = first.cache["pairs"]["computed"]
    assert (
        _counts(first)
        == {
            "features": (0, 4),
            "pyramids": (0, 4),
            "pairs": (0, pairs),
            "refined": (0, first.cache["refined"]["computed"]),
        }
        and pairs >= 6
    )
    again = register(room, config, cache=Cache(tmp_path), **quiet)
    assert all(computed == 0 for _, computed in _counts(again).values()), again.cache
    np.testing.assert_array_equal(again.poses, first.poses)
    assert again.sync.weights.tolist() == first.sync.weights.tolist()

    # A truncated pair, a features file of garbage and an empty pyramid: recomputed, and written back whole.
    pair_file = sorted((tmp_path / "pairs").iterdir())[0]
    pair_file.write_bytes(pair_file.read_bytes()[:200])
    sorted((tmp_path / "features").iterdir())[1].write_bytes(b"not an npz")
    sorted((tmp_path / "pyramids").iterdir())[2].write_bytes(b"")
    repaired = register(room, config, cache=Cache(tmp_path), **quiet)
    assert repaired.cache["unreadable"] == 3
    assert [repaired.cache[kind]["computed"] for kind in ("features", "pyramids", "pairs")] == [1, 1, 1]
    np.testing.assert_array_equal(repaired.poses, first.poses)
    assert register(room, config, cache=Cache(tmp_path), **quiet).cache["unreadable"] == 0

    # Another ICP distance: the same features and grids, every registration anew; another voxel: nothing reused.
    icp = register(room, replace(config, icp_distance=2.0), cache=Cache(tmp_path), **quiet)
    assert _counts(icp)["features"] == (4, 0) and _counts(icp)["pyramids"] == (4, 0)
    assert icp.cache["pairs"]["cached"] == 0 and icp.cache["refined"]["cached"] == 0
    voxel = register(room, replace(config, voxel=first.voxel * 1.1), cache=Cache(tmp_path), **quiet)
    assert all(cached == 0 for cached, _ in _counts(voxel).values()), voxel.cache


def test_entries_swapped_between_keys_are_recomputed_not_used(room, tmp_path):
    """Two features entries (and two pairs) swapped: each is a readable result of another scan (or pair), and was
    used as it was: 2 of 4 scans placed, poses off by up to 1.07, exit 0. Each entry holds its own key now."""
    config = Config(record=False, workers=1)
    first = register(room, config, cache=Cache(tmp_path), log=lambda m: None)
    for kind in ("features", "pairs"):
        a, b = sorted((tmp_path / kind).iterdir())[:2]
        a.rename(tmp_path / "swap")
        b.rename(a)
        (tmp_path / "swap").rename(b)
    again = register(room, config, cache=Cache(tmp_path), log=lambda m: None)
    assert again.cache["unreadable"] == 4 and again.cache["features"]["computed"] == 2
    np.testing.assert_array_equal(again.poses, first.poses)


def test_entries_readable_but_damaged_inside_are_recomputed(room, tmp_path):
    """Arrays that read but cannot be a result (points cut to two columns, NaN points, a NaN transform) ended every
    later run with an unexpected IndexError, LinAlgError or "edge 1: T is not finite"."""
    config = Config(record=False, workers=1)
    first = register(room, config, cache=Cache(tmp_path), log=lambda m: None)

    def rewrite(path: Path, change) -> None:
        with np.load(path) as archive:
            arrays = dict(archive)
        change(arrays)
        with open(path, "wb") as f:
            np.savez(f, **arrays)

    features = sorted((tmp_path / "features").iterdir())
    rewrite(features[0], lambda a: a.update(points=a["points"][:, :2]))
    rewrite(features[1], lambda a: a["points"].__setitem__(0, np.nan))
    rewrite(sorted((tmp_path / "pyramids").iterdir())[0], lambda a: a["grid0"].__setitem__(0, np.nan))
    rewrite(sorted((tmp_path / "pairs").iterdir())[0], lambda a: a["T"].__setitem__((0, 3), np.nan))
    again = register(room, config, cache=Cache(tmp_path), log=lambda m: None)
    assert again.cache["unreadable"] == 4
    np.testing.assert_array_equal(again.poses, first.poses)


def test_a_scan_changed_while_the_run_uses_it_is_named(tmp_path):
    """A scan file replaced after the run first read it put the new points' features under the old points' key:
    every later run took them from the cache (a scan given another's pose, exit 0)."""
    scene = make_scene(kind="room", n_scans=3, seed=2)
    write_scene(scene, tmp_path / "scene")
    scans, _ = load_scene(tmp_path / "scene", Config(), log=lambda m: None)
    (tmp_path / "scene" / scene.names[2]).write_bytes((tmp_path / "scene" / scene.names[1]).read_bytes())
    with pytest.raises(InputError, match=f"scan {scene.names[2]} changed while the run was using it"):
        scans[2].read()
    scans[1].read()  # unchanged: read as before


def test_temporaries_of_a_killed_write_are_removed(tmp_path):
    (tmp_path / "pairs").mkdir()
    old, new = tmp_path / "pairs" / ".k.npz.a1.tmp.npz", tmp_path / "pairs" / ".j.npz.b2.tmp.npz"
    old.write_bytes(b"half")
    new.write_bytes(b"being written")
    os.utime(old, (time.time() - 3600,) * 2)
    Cache(tmp_path)
    assert not old.exists() and new.exists()  # a write in progress (another run's) is left alone


def _cli(scene: Path, out: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "sghr_gtsam",
        "run",
        str(scene),
        "--out",
        str(out),
        "--workers",
        "2",
        "--no-record",
        "--quiet",
    ]


def _entries(folder: Path) -> int:
    """Finished entries (a write in progress has a hidden temporary name)."""
    return len([p for p in folder.glob("*.npz") if not p.name.startswith(".")]) if folder.is_dir() else 0


ENV = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}


def test_run_killed_during_pairwise_registration_resumes_to_the_same_poses(tmp_path):
    """SIGKILL once some pair registrations are in OUT/cache; the next run reads those back, registers only the
    missing pairs and ends with the poses of a run never stopped (byte for byte)."""
    scene = tmp_path / "scene"
    write_scene(make_scene(kind="room", n_scans=8, seed=1), scene)
    subprocess.run(_cli(scene, tmp_path / "ref"), env=ENV, check=True, capture_output=True)
    reference = json.loads((tmp_path / "ref" / "report.json").read_text())["cache"]
    total = reference["pairs"]["computed"]

    out = tmp_path / "out"
    pairs = out / CACHE / "pairs"
    proc = subprocess.Popen(
        _cli(scene, out), env=ENV, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    try:
        while proc.poll() is None and _entries(pairs) < 3:
            time.sleep(0.01)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # the run and its workers, as a job scheduler would
        proc.wait()
    done = _entries(pairs)
    assert proc.returncode == -signal.SIGKILL and 3 <= done < total, (proc.returncode, done, total)
    assert not (out / "report.json").exists()

    resumed = subprocess.run(_cli(scene, out), env=ENV, capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    report = json.loads((out / "report.json").read_text())["cache"]
    assert report["features"] == {"cached": 8, "computed": 0}
    assert report["pairs"] == {"cached": done, "computed": total - done}
    assert report["refined"] == {"cached": 0, "computed": reference["refined"]["computed"]}
    assert (out / "poses.txt").read_text() == (tmp_path / "ref" / "poses.txt").read_text()
