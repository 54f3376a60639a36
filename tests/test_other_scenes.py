"""data_tools.other_3dmatch_scenes: a scene in the source repository's form (points pickled by torch, per-fragment
info poses) comes out in the shared scenes' form, poses relative to fragment 0 and checked against gt.log."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from data_tools.other_3dmatch_scenes import GT_DIR, OTHER_SCENES, convert
from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.io.scans import load_scan
from sghr_gtsam.se3 import inv_T, make_T


def _write_source(root, scene: str, poses: list[np.ndarray], points: list[np.ndarray]) -> None:
    folder = root / "test" / scene
    folder.mkdir(parents=True)
    for i, (M, P) in enumerate(zip(poses, points)):
        torch.save(P, folder / f"cloud_bin_{i}.pth")  # a numpy array, as the repository's files hold
        rows = "\n".join("\t".join(f"{v:.12e}" for v in row) for row in M)
        (folder / f"cloud_bin_{i}.info.txt").write_text(f"{scene}\t seq-01\t {50 * i}\t {50 * i + 49}\n{rows}\n")


def _write_gt_log(data, scene: str, poses: list[np.ndarray], shift: float = 0.0) -> None:
    folder = data / GT_DIR / scene
    folder.mkdir(parents=True)
    blocks = []
    for i in range(len(poses)):
        for j in range(i + 1, len(poses)):
            T = inv_T(poses[i]) @ poses[j]
            T[0, 3] += shift
            blocks.append(f"{i}\t{j}\t{len(poses)}\n" + "\n".join(" ".join(f"{v:.9f}" for v in r) for r in T))
    (folder / "gt.log").write_text("\n".join(blocks) + "\n")


@pytest.fixture
def scene_files(tmp_path):
    rng = np.random.default_rng(0)
    scene = OTHER_SCENES["mit_lab"]
    poses = [make_T(Rotation.random(random_state=k).as_matrix(), rng.normal(size=3) * 3) for k in range(3)]
    points = [rng.normal(size=(50 + 10 * i, 3)) for i in range(3)]
    _write_source(tmp_path / "src", scene, poses, points)
    return tmp_path, scene, poses, points


def test_a_scene_converts_to_the_shared_layout(scene_files):
    root, scene, poses, points = scene_files
    _write_gt_log(root / "data", scene, poses)
    line = convert(root / "src" / "test", root / "data", root / "out", "mit_lab")
    assert line.startswith("mit_lab: 3 fragments")
    names, T = read_poses(root / "out" / "3dmatch-scenes" / "mit_lab" / "gt_poses.txt")
    assert names == [f"cloud_bin_{i}.ply" for i in range(3)]
    for i in range(3):
        np.testing.assert_allclose(T[i], inv_T(poses[0]) @ poses[i], atol=1e-9)
        np.testing.assert_allclose(
            load_scan(root / "out" / "3dmatch-scenes" / "mit_lab" / names[i]), points[i], atol=1e-6
        )


def test_poses_that_disagree_with_gt_log_are_refused(scene_files):
    root, scene, poses, _ = scene_files
    _write_gt_log(root / "data", scene, poses, shift=0.01)
    with pytest.raises(ValueError, match="disagree with gt.log"):
        convert(root / "src" / "test", root / "data", root / "out", "mit_lab")
