"""Are the pose covariances calibrated? NEES on simulated scenes with known range noise, and the reported σ
next to the real error on the real scenes.

    python benchmarks/bench_covariance.py --scenes 60 --first-seed 1000
    python benchmarks/bench_covariance.py --real kitchen bunny [--data ../shared/data]

Simulated: ``synthetic.make_scene`` (rooms and objects alternating, 6 scans, 3 mm range noise), the whole
pipeline (default ``Config``), then ``gtsam_api.pose_covariances``. For every registered scan but the world
scan, ``ξ = Log(T̂⁻¹ T_gt)`` (both relative to the world scan) and ``NEES = ξᵀ Σ⁻¹ ξ``, which is χ²₆ when Σ is
right. The mean NEES over M scans of a calibrated estimator lies in ``[χ²_{6M}(0.025), χ²_{6M}(0.975)] / M``
(the band treats the scans as independent; scans of one scene share edges, so the band is optimistic).
Gross misregistrations (> 5°) are counted apart: no Gaussian covariance describes them.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gtsam
import numpy as np
from scipy.stats import chi2

from sghr_gtsam.config import Config
from sghr_gtsam.gtsam_api import pose_covariances, sigmas
from sghr_gtsam.pipeline import Scan, register, run
from sghr_gtsam.se3 import inv_T

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # data_tools
from data_tools.scene_gt import data_root  # noqa: E402

GROSS_DEG = 5.0


def scan_nees(poses: np.ndarray, gt: np.ndarray, covariances: np.ndarray, registered: list[int],
              anchor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per registered scan other than ``anchor``: NEES, rotation error (deg) and translation error."""
    est = inv_T(poses[anchor])[None] @ poses
    true = inv_T(gt[anchor])[None] @ gt
    nees, rot, trans = [], [], []
    for k in registered:
        if k == anchor:
            continue
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(est[k]).between(gtsam.Pose3(true[k])))
        nees.append(float(xi @ np.linalg.solve(covariances[k], xi)))
        rot.append(np.degrees(np.linalg.norm(xi[:3])))
        trans.append(float(np.linalg.norm(true[k][:3, 3] - est[k][:3, 3])))
    return np.array(nees), np.array(rot), np.array(trans)


def band(m: int) -> tuple[float, float]:
    return chi2.ppf(0.025, 6 * m) / m, chi2.ppf(0.975, 6 * m) / m


def simulated(scenes: int, first_seed: int, n_scans: int) -> None:
    from sghr_gtsam.synthetic import make_scene

    rows: dict[str, list[np.ndarray]] = {"room": [], "object": []}
    gross = {"room": 0, "object": 0}
    for s in range(first_seed, first_seed + scenes):
        kind = "room" if s % 2 == 0 else "object"
        scene = make_scene(kind=kind, n_scans=n_scans, seed=s)
        result = register([Scan(n, P) for n, P in zip(scene.names, scene.scans)],
                          Config(record=False, seed=s, voxel=scene.voxel, workers=1), log=lambda m: None)
        C = pose_covariances(result)
        anchor = int(np.flatnonzero(result.sync.component == 0)[0])
        nees, rot, _ = scan_nees(result.poses, scene.poses, C, result.registered, anchor)
        gross[kind] += int(np.count_nonzero(rot > GROSS_DEG))
        rows[kind].append(nees[rot <= GROSS_DEG])
        print(f"seed {s} {kind}: {len(nees)} scans, NEES mean {np.mean(nees):.2f}", file=sys.stderr, flush=True)
    print(f"| scenes | scans | gross (> {GROSS_DEG:g}°) | mean NEES | median NEES | 95 % band of the mean "
          f"| scans with NEES < χ²₆(0.95) |")
    print("|---|---|---|---|---|---|---|")
    for label, kinds in (("rooms", ["room"]), ("objects", ["object"]), ("all", ["room", "object"])):
        x = np.concatenate([a for k in kinds for a in rows[k]]) if any(rows[k] for k in kinds) else np.zeros(0)
        lo, hi = band(len(x))
        count = sum(len(rows[k]) for k in kinds)
        print(f"| {label} ({count}) | {len(x)} | {sum(gross[k] for k in kinds)} | {x.mean():.2f} | "
              f"{np.median(x):.2f} | [{lo:.2f}, {hi:.2f}] | {np.mean(x < chi2.ppf(0.95, 6)):.0%} |")


def real(names: list[str], data: Path) -> None:
    import tempfile

    from sghr_gtsam.io.poses import read_poses

    print("| scene | scan | σ rot [°] | rot error [°] | σ trans [mm] | trans error [mm] | NEES |")
    print("|---|---|---|---|---|---|---|")
    for scene in names:
        folder = data / scene
        gt_file = folder / "gt_poses.txt" if (folder / "gt_poses.txt").exists() else folder / "gt" / "gt_poses.txt"
        with tempfile.TemporaryDirectory() as out:
            result = run(folder, out, Config(record=False), log=lambda m: None)
        gt_names, gt = read_poses(gt_file)
        gt = gt[[gt_names.index(n) for n in result.names]]
        C = result.covariances if result.covariances is not None else pose_covariances(result)
        anchor = int(np.flatnonzero(result.sync.component == 0)[0])
        nees, rot, trans = scan_nees(result.poses, gt, C, result.registered, anchor)
        s_rot, s_trans = sigmas(C)
        print(f"{scene}: underdetermined {result.underdetermined}", file=sys.stderr, flush=True)
        others = [k for k in result.registered if k != anchor]
        for row, k in enumerate(others):
            print(f"| {scene} | {result.names[k]} | {s_rot[k]:.4f} | {rot[row]:.4f} | {1e3 * s_trans[k]:.3f} | "
                  f"{1e3 * trans[row]:.3f} | {nees[row]:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=60)
    parser.add_argument("--first-seed", type=int, default=1000)
    parser.add_argument("--scans", type=int, default=6)
    parser.add_argument("--real", nargs="*", default=None, help="real scenes instead: kitchen bunny")
    parser.add_argument("--data", type=Path, default=data_root())
    args = parser.parse_args()
    if args.real is not None:
        real(args.real or ["kitchen", "bunny"], args.data)
    else:
        simulated(args.scenes, args.first_seed, args.scans)


if __name__ == "__main__":
    main()
