"""The five 3DMatch test scenes that are not in the shared data, in the shared scenes' layout, for a check on scenes
nobody here tuned to (``benchmarks/bench_3dmatch.py --scenes unseen``).

    python -m data_tools.other_3dmatch_scenes SOURCE [--data ../shared/data] [--out DIR]

SOURCE is the ``test/`` folder of a local clone of viratzzs/icp-3dmatch (the repository the shared scenes came
from, MANIFEST.md): per scene ``cloud_bin_<i>.pth`` (the fragment's points, an (N, 3) numpy array, metres, already
on the benchmark's ~2.5 cm grid) and ``cloud_bin_<i>.info.txt`` (a header, then the 4x4 fragment-to-scene pose
M_i). Nothing is downloaded. Written to ``OUT/3dmatch-scenes/<name>/``: the fragments as binary PLY and
``gt_poses.txt`` with ``T_i = P(inv(M_0) @ M_i)`` (P: the SVD projection to SO(3)), exactly as the shared scenes'
file is made; each scene's poses are checked against its ``gt.log`` in ``--data`` (3dmatch-test-gt). ``OUT`` also
gets a link to that GT folder, so that ``bench_3dmatch.py --data OUT`` finds everything. The points are read with
``torch.load(weights_only=True)``, numpy arrays allowed and nothing else.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

OTHER_SCENES = {
    "kitchen60": "7-scenes-redkitchen",
    "home_md": "sun3d-home_md-home_md_scan9_2012_sep_30",
    "hotel_umd1": "sun3d-hotel_umd-maryland_hotel1",
    "hotel_umd3": "sun3d-hotel_umd-maryland_hotel3",
    "mit_lab": "sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika",
}
"""Short name (the benchmark's) → the scene's 3DMatch name."""
GT_DIR = "3dmatch-test-gt/3DMatch"
MAX_GT_DEG = 1e-3
MAX_GT_M = 1e-3  # 7-scenes-redkitchen: 0.8 mm (the shared scenes: < 1e-4 m)


def _points(path: Path) -> np.ndarray:
    import torch

    # the repository's files were pickled by numpy 1, whose names (numpy.core) numpy 2 keeps only as aliases
    reconstruct, float64 = np._core.multiarray._reconstruct, type(np.dtype(np.float64))
    allowed = [
        reconstruct,
        (reconstruct, "numpy.core.multiarray._reconstruct"),
        np.ndarray,
        np.dtype,
        float64,
        (float64, "numpy.dtype[float64]"),
    ]
    with torch.serialization.safe_globals(allowed):
        P = np.asarray(torch.load(path, weights_only=True), dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or not np.isfinite(P).all():
        raise ValueError(f"{path}: not a finite (N, 3) array, shape {P.shape}")
    return P


def _info_pose(path: Path) -> np.ndarray:
    rows = [line.split() for line in path.read_text().splitlines()[1:5]]
    M = np.array(rows, dtype=np.float64)
    if M.shape != (4, 4):
        raise ValueError(f"{path}: no 4x4 pose after the header")
    return M


def _gt_log_deviation(poses: list[np.ndarray], gt_log: Path) -> tuple[float, float]:
    """Largest rotation (degrees) and translation (m) between ``inv(T_i) @ T_j`` and the gt.log's ``T_ij``."""
    from sghr_gtsam.io.poses import read_gt_log
    from sghr_gtsam.se3 import inv_T, relative_errors

    pairs = read_gt_log(gt_log)
    ours = np.stack([inv_T(poses[i]) @ poses[j] for i, j in pairs])
    rot, trans = relative_errors(ours, np.stack(list(pairs.values())))
    return float(rot.max()), float(trans.max())


def convert(source: Path, data: Path, out: Path, name: str) -> str:
    """One scene from ``source`` into ``out``; returns a line saying what was written."""
    import open3d as o3d

    from sghr_gtsam.se3 import inv_T, project_to_so3

    scene = OTHER_SCENES[name]
    folder = source / scene
    count = len(list(folder.glob("cloud_bin_*.pth")))
    if count == 0:
        raise FileNotFoundError(f"no cloud_bin_*.pth in {folder}")
    target = out / "3dmatch-scenes" / name
    target.mkdir(parents=True, exist_ok=True)
    M = [_info_pose(folder / f"cloud_bin_{i}.info.txt") for i in range(count)]
    poses = []
    for i in range(count):
        T = inv_T(M[0]) @ M[i]
        T[:3, :3] = project_to_so3(T[:3, :3])
        poses.append(T)
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(_points(folder / f"cloud_bin_{i}.pth")))
        o3d.io.write_point_cloud(str(target / f"cloud_bin_{i}.ply"), cloud)
    deg, m = _gt_log_deviation(poses, data / GT_DIR / scene / "gt.log")
    if deg > MAX_GT_DEG or m > MAX_GT_M:
        raise ValueError(f"{name}: poses disagree with gt.log by {deg:.2g}° / {m:.2g} m")
    with open(target / "gt_poses.txt", "w") as f:
        f.write(
            f"# DERIVED for 3DMatch test scene {scene}, {count} fragments, by data_tools.other_3dmatch_scenes:\n"
            f"# T_i = P(inv(M_0) @ M_i) from viratzzs/icp-3dmatch test/{scene}/cloud_bin_<i>.info.txt, P the\n"
            f"# SVD projection to SO(3); within {deg:.1g}° / {m:.1g} m of the scene's gt.log. p_world = T @ p_scan.\n"
        )
        for i, T in enumerate(poses):
            f.write(f"cloud_bin_{i}.ply\n" + "\n".join(" ".join(f"{v:.10f}" for v in row) for row in T) + "\n")
    return f"{name}: {count} fragments, gt.log within {deg:.1g}° / {m:.1g} m"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("source", type=Path, help="the test/ folder of a clone of viratzzs/icp-3dmatch")
    ap.add_argument(
        "--data",
        type=Path,
        default=Path(__file__).resolve().parents[2] / "shared" / "data",
        help="the shared data (for 3dmatch-test-gt)",
    )
    ap.add_argument(
        "--out",
        type=Path,
        help="where to write (default: --data is read-only, so ./other-scenes)",
        default=Path("other-scenes"),
    )
    args = ap.parse_args()
    gt = args.data / "3dmatch-test-gt"
    if not gt.is_dir():
        sys.exit(f"{gt} not found: --data must hold the 3DMatch test GT")
    args.out.mkdir(parents=True, exist_ok=True)
    link = args.out / "3dmatch-test-gt"
    if not link.exists():
        link.symlink_to(gt.resolve())
    for name in OTHER_SCENES:
        try:
            print(convert(args.source, args.data, args.out, name))
        except (OSError, ValueError) as e:
            sys.exit(f"{name}: {e}")


if __name__ == "__main__":
    main()
