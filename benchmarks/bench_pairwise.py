"""Pairwise registration on the real scenes (kitchen: 9 3DMatch fragments, 36 pairs; bunny: 10 Stanford
scans, 45 pairs), for each matcher: how many pairs land within the error bounds of ground truth, the
time a pair takes, and how well the inlier count r_ij separates right pairs from wrong ones.

    python benchmarks/bench_pairwise.py [--matchers kiss,ransac] [--pairs]

A pair is *right* within 5 deg / 0.2 m (kitchen) or 1 deg / 1 mm (bunny). Its ground-truth overlap is
the larger of the two fractions of grid points with a point of the other scan within 3 voxels after
ground-truth alignment; pairs over 0.1 are the ones a registration can be asked to get. *Near* pairs
are wrong but within 5 deg / 5 voxels (a refinement short of the bounds); *far* pairs are the rest.
``frac`` is r_ij over the smaller scan's grid size, a scale-free form of r_ij. Times are wall clock.
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from sghr_gtsam.features.local import ScanFeatures, compute_features, default_voxel
from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.io.scans import load_scan
from sghr_gtsam.registration.pairwise import MATCHERS, register_pair
from sghr_gtsam.se3 import inv_T, relative_errors, transform_points

DATA = Path(os.environ.get("SGHR_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
# scene: (folder, ground-truth file, rotation bound deg, translation bound in scene units)
SCENES = {
    "kitchen": ("kitchen", "kitchen/gt/gt_poses.txt", 5.0, 0.2),
    "bunny": ("bunny", "bunny/gt_poses.txt", 1.0, 0.001),
}
OVERLAP_RADIUS = 3.0  # voxels
MIN_OVERLAP = 0.1
NEAR = (5.0, 5.0)  # deg, voxels


@dataclass
class Row:
    i: int
    j: int
    overlap: float
    rot_deg: float
    trans: float
    inliers: int
    frac: float
    seconds: float
    kind: str  # right / near / far


def gt_overlap(fi: ScanFeatures, fj: ScanFeatures, T_ij: np.ndarray, radius: float) -> float:
    q = transform_points(T_ij, fj.points)
    a = np.mean(cKDTree(fi.points).query(q, distance_upper_bound=radius)[0] < radius)
    b = np.mean(cKDTree(q).query(fi.points, distance_upper_bound=radius)[0] < radius)
    return float(max(a, b))


def run_scene(name: str, matchers: list[str], show_pairs: bool) -> None:
    folder, gt_file, rot_bound, trans_bound = SCENES[name]
    t0 = time.perf_counter()
    names, poses = read_poses(DATA / gt_file)
    scans = [load_scan(DATA / folder / n) for n in names]
    t_load = time.perf_counter() - t0
    voxel = default_voxel(scans)
    t0 = time.perf_counter()
    feats = [compute_features(s, voxel) for s in scans]
    t_feat = time.perf_counter() - t0
    pairs = list(itertools.combinations(range(len(scans)), 2))
    gt = {(i, j): inv_T(poses[i]) @ poses[j] for i, j in pairs}
    overlap = {p: gt_overlap(feats[p[0]], feats[p[1]], gt[p], OVERLAP_RADIUS * voxel) for p in pairs}
    n_ov = sum(o > MIN_OVERLAP for o in overlap.values())
    print(f"\n== {name}: {len(scans)} scans, voxel {voxel:.4g} (grid {np.mean([len(f) for f in feats]):.0f} points "
          f"a scan), load {t_load:.2f} s, features {t_feat / len(scans):.3f} s a scan; {len(pairs)} pairs, "
          f"{n_ov} with GT overlap > {MIN_OVERLAP}; right = within {rot_bound:g} deg / {trans_bound:g}")

    for matcher in matchers:
        rows = []
        for i, j in pairs:
            res = register_pair(feats[i], feats[j], voxel, matcher=matcher)
            rot, trans = (float(x) for x in relative_errors(res.T, gt[(i, j)]))
            kind = ("right" if rot < rot_bound and trans < trans_bound
                    else "near" if rot < NEAR[0] and trans < NEAR[1] * voxel else "far")
            rows.append(Row(i, j, overlap[(i, j)], rot, trans, res.inliers,
                            res.inliers / min(len(feats[i]), len(feats[j])), res.seconds, kind))
        if show_pairs:
            print(f"  {matcher}: pair, GT overlap, rotation error (deg), translation error, r_ij, frac, seconds")
            for r in sorted(rows, key=lambda r: -r.overlap):
                print(f"    {names[r.i]:>14} {names[r.j]:>14}  {r.overlap:4.2f}  {r.rot_deg:7.2f}  {r.trans:8.4f}  "
                      f"{r.inliers:5d}  {r.frac:.4f}  {r.seconds:.2f}  {r.kind}")
        summarize(matcher, rows, voxel)


def summarize(matcher: str, rows: list[Row], voxel: float) -> None:
    by = {k: [r for r in rows if r.kind == k] for k in ("right", "near", "far")}
    ov = [r for r in rows if r.overlap > MIN_OVERLAP]
    secs = np.array([r.seconds for r in rows])
    print(f"  {matcher:6s} right {sum(r.kind == 'right' for r in ov):2d}/{len(ov)} of the overlapping pairs "
          f"({len(by['right'])}/{len(rows)} of all; near {len(by['near'])}, far {len(by['far'])}); "
          f"{secs.mean():.3f} s a pair (max {secs.max():.2f})")
    right = by["right"]
    if right:
        rot = np.array([r.rot_deg for r in right])
        tr = np.array([r.trans for r in right])
        print(f"         right pairs' error: rotation median {np.median(rot):.3f} max {rot.max():.3f} deg, "
              f"translation median {np.median(tr):.4g} max {tr.max():.4g} ({np.median(tr) / voxel:.2f} / "
              f"{tr.max() / voxel:.2f} voxels)")

    def extreme(kinds: tuple[str, ...], f, attr: str):
        vals = [getattr(r, attr) for k in kinds for r in by[k]]
        return f(vals) if vals else float("nan")

    for attr, fmt in (("inliers", "{:.0f}"), ("frac", "{:.4f}")):
        lo_right = extreme(("right",), min, attr)
        hi_wrong = extreme(("near", "far"), max, attr)
        hi_far = extreme(("far",), max, attr)
        lo_near = extreme(("right", "near"), min, attr)
        print(f"         {attr:7s}: right >= {fmt.format(lo_right)}, wrong <= {fmt.format(hi_wrong)}  |  "
              f"right or near >= {fmt.format(lo_near)}, far <= {fmt.format(hi_far)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--matchers", default=",".join(MATCHERS))
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--pairs", action="store_true", help="also list every pair")
    args = parser.parse_args()
    if not (DATA / "MANIFEST.md").is_file():
        sys.exit(f"real data not found at {DATA} (set SGHR_DATA)")
    for scene in args.scenes.split(","):
        run_scene(scene, args.matchers.split(","), args.pairs)


if __name__ == "__main__":
    main()
