"""Pairwise registration on the real scenes (kitchen: 9 3DMatch fragments, 36 pairs; bunny: 10 Stanford
scans, 45 pairs; the three shared full 3DMatch test scenes on their gt.log pairs), for each matcher: how
many pairs land within the error bounds of ground truth, the time a pair takes, and how well the inlier
count r_ij (and the inliers' coverage, ``PairResult.coverage``) separates right pairs from wrong ones.

    python benchmarks/bench_pairwise.py [--matchers sc2,kiss,ransac] [--scenes kitchen,bunny,home_at,...]
        [--pairs] [--negatives 40]

3DMatch scenes (home_at, hotel_uc, studyroom): every gt.log pair (the benchmark's pairs, GT overlap >= 30 %) is
registered and scored by the paper's protocol (``evaluate.registration_recall``: rmse <= 0.2 m under the pair's
gt.info); the recall is given over all gt.log pairs and over those with |i - j| > 1 (the paper's set). Rotation
and translation errors are ScanNet-style over all gt.log pairs. ``--negatives`` more pairs per scene, drawn
at random (seed 0) from those not in gt.log (little or no overlap, as the top-k graph also proposes), enter
only the separation tables: right there means within 5 deg / 0.2 m. Seconds per pair are CPU seconds of
``register_pair`` (process time: both k-d query threads counted), median and mean, on a shared machine.

On kitchen and bunny a pair is *right* within 5 deg / 0.2 m (kitchen) or 1 deg / 1 mm (bunny). Its ground-truth
overlap is
the larger of the two fractions of grid points with a point of the other scan within 3 voxels after
ground-truth alignment; pairs over 0.1 are the ones a registration can be asked to get. *Near* pairs
are wrong but within 5 deg / 5 voxels (a refinement short of the bounds); *far* pairs are the rest.
``frac`` is r_ij over the smaller scan's grid size, a scale-free form of r_ij. Times are wall clock.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from sghr_gtsam.evaluate import registration_recall
from sghr_gtsam.features.local import ScanFeatures, compute_features, default_voxel
from sghr_gtsam.io.poses import read_gt_info, read_gt_log, read_poses
from sghr_gtsam.io.scans import load_scan
from sghr_gtsam.registration.pairwise import MATCHERS, register_pair
from sghr_gtsam.se3 import inv_T, relative_errors, transform_points

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # data_tools
from data_tools.scene_gt import data_root  # noqa: E402

DATA = data_root()
# scene: (folder, ground-truth file, rotation bound deg, translation bound in scene units)
SCENES = {
    "kitchen": ("kitchen", "kitchen/gt/gt_poses.txt", 5.0, 0.2),
    "bunny": ("bunny", "bunny/gt_poses.txt", 1.0, 0.001),
}
# 3DMatch scenes: folder under 3dmatch-scenes/ and the scene's name in 3dmatch-test-gt/3DMatch/.
MATCH_SCENES = {
    "home_at": "sun3d-home_at-home_at_scan1_2013_jan_1",
    "hotel_uc": "sun3d-hotel_uc-scan3",
    "studyroom": "sun3d-mit_76_studyroom-76-1studyroom2",
}
PAPER_RMSE = 0.2  # m
FAR = (10.0, 0.5)  # deg, m: a wrong 3DMatch pair this far off is a gross error, not a near miss
R_BINS = [0, 5, 10, 15, 20, 30, 50, 100, 10**9]
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
    coverage: int
    seconds: float
    kind: str  # right / near / far


def gt_overlap(fi: ScanFeatures, fj: ScanFeatures, T_ij: np.ndarray, radius: float) -> float:
    q = transform_points(T_ij, fj.points)
    a = np.mean(cKDTree(fi.points).query(q, distance_upper_bound=radius)[0] < radius)
    b = np.mean(cKDTree(q).query(fi.points, distance_upper_bound=radius)[0] < radius)
    return float(max(a, b))


def load_scene(name: str) -> tuple[list[str], np.ndarray, list[np.ndarray], float]:
    """One of ``SCENES`` (kitchen, bunny): scan names, GT poses, scans and the default voxel."""
    folder, gt_file, _, _ = SCENES[name]
    names, poses = read_poses(DATA / gt_file)
    scans = [load_scan(DATA / folder / n) for n in names]
    return names, poses, scans, default_voxel(scans)


def run_scene(name: str, matchers: list[str], show_pairs: bool) -> None:
    _, _, rot_bound, trans_bound = SCENES[name]
    t0 = time.perf_counter()
    names, poses, scans, voxel = load_scene(name)
    t_load = time.perf_counter() - t0
    t0 = time.perf_counter()
    feats = [compute_features(s, voxel) for s in scans]
    t_feat = time.perf_counter() - t0
    pairs = list(itertools.combinations(range(len(scans)), 2))
    gt = {(i, j): inv_T(poses[i]) @ poses[j] for i, j in pairs}
    overlap = {p: gt_overlap(feats[p[0]], feats[p[1]], gt[p], OVERLAP_RADIUS * voxel) for p in pairs}
    n_ov = sum(o > MIN_OVERLAP for o in overlap.values())
    print(
        f"\n== {name}: {len(scans)} scans, voxel {voxel:.4g} (grid {np.mean([len(f) for f in feats]):.0f} points "
        f"a scan), load {t_load:.2f} s, features {t_feat / len(scans):.3f} s a scan; {len(pairs)} pairs, "
        f"{n_ov} with GT overlap > {MIN_OVERLAP}; right = within {rot_bound:g} deg / {trans_bound:g}"
    )

    for matcher in matchers:
        rows = []
        for i, j in pairs:
            res = register_pair(feats[i], feats[j], voxel, matcher=matcher)
            rot, trans = (float(x) for x in relative_errors(res.T, gt[(i, j)]))
            kind = (
                "right"
                if rot < rot_bound and trans < trans_bound
                else "near"
                if rot < NEAR[0] and trans < NEAR[1] * voxel
                else "far"
            )
            rows.append(
                Row(
                    i,
                    j,
                    overlap[(i, j)],
                    rot,
                    trans,
                    res.inliers,
                    res.inliers / min(len(feats[i]), len(feats[j])),
                    res.coverage,
                    res.seconds,
                    kind,
                )
            )
        if show_pairs:
            print(f"  {matcher}: pair, GT overlap, rotation error (deg), translation error, r_ij, frac, seconds")
            for r in sorted(rows, key=lambda r: -r.overlap):
                print(
                    f"    {names[r.i]:>14} {names[r.j]:>14}  {r.overlap:4.2f}  {r.rot_deg:7.2f}  {r.trans:8.4f}  "
                    f"{r.inliers:5d}  {r.frac:.4f}  {r.seconds:.2f}  {r.kind}"
                )
        summarize(matcher, rows, voxel)


def summarize(matcher: str, rows: list[Row], voxel: float) -> None:
    by = {k: [r for r in rows if r.kind == k] for k in ("right", "near", "far")}
    ov = [r for r in rows if r.overlap > MIN_OVERLAP]
    secs = np.array([r.seconds for r in rows])
    print(
        f"  {matcher:6s} right {sum(r.kind == 'right' for r in ov):2d}/{len(ov)} of the overlapping pairs "
        f"({len(by['right'])}/{len(rows)} of all; near {len(by['near'])}, far {len(by['far'])}); "
        f"{secs.mean():.3f} s a pair (max {secs.max():.2f})"
    )
    right = by["right"]
    if right:
        rot = np.array([r.rot_deg for r in right])
        tr = np.array([r.trans for r in right])
        print(
            f"         right pairs' error: rotation median {np.median(rot):.3f} max {rot.max():.3f} deg, "
            f"translation median {np.median(tr):.4g} max {tr.max():.4g} ({np.median(tr) / voxel:.2f} / "
            f"{tr.max() / voxel:.2f} voxels)"
        )

    def extreme(kinds: tuple[str, ...], f, attr: str):
        vals = [getattr(r, attr) for k in kinds for r in by[k]]
        return f(vals) if vals else float("nan")

    for attr, fmt in (("inliers", "{:.0f}"), ("frac", "{:.4f}"), ("coverage", "{:.0f}")):
        lo_right = extreme(("right",), min, attr)
        hi_wrong = extreme(("near", "far"), max, attr)
        hi_far = extreme(("far",), max, attr)
        lo_near = extreme(("right", "near"), min, attr)
        print(
            f"         {attr:7s}: right >= {fmt.format(lo_right)}, wrong <= {fmt.format(hi_wrong)}  |  "
            f"right or near >= {fmt.format(lo_near)}, far <= {fmt.format(hi_far)}"
        )


def paper_rmse(T_est: np.ndarray, T_gt: np.ndarray, info: np.ndarray) -> float:
    """The paper's rmse of one pair: ``registration_recall`` on a two-scan model (ids 0 and 2 so that the
    pair passes its |i - j| > 1 filter)."""
    return float(registration_recall([0, 2], np.stack([np.eye(4), T_est]), {(0, 2): T_gt}, {(0, 2): info}).rmse[0])


def load_3dmatch(root: Path, name: str, gt_name: str) -> tuple[np.ndarray, dict, dict, list[np.ndarray], float]:
    """A 3DMatch scene under ``root`` (the shared data's layout): GT poses, gt.log, gt.info, scans, default voxel."""
    folder = root / "3dmatch-scenes" / name
    gt_dir = root / "3dmatch-test-gt" / "3DMatch" / gt_name
    names, poses = read_poses(folder / "gt_poses.txt")
    scans = [load_scan(folder / n) for n in names]
    return poses, read_gt_log(gt_dir / "gt.log"), read_gt_info(gt_dir / "gt.info"), scans, default_voxel(scans)


def run_3dmatch(name: str, matchers: list[str], show_pairs: bool, negatives: int) -> None:
    poses, log, info, scans, voxel = load_3dmatch(DATA, name, MATCH_SCENES[name])
    t0 = time.perf_counter()
    feats = [compute_features(s, voxel) for s in scans]
    t_feat = time.perf_counter() - t0
    others = [p for p in itertools.combinations(range(len(scans)), 2) if p not in log]
    rng = np.random.default_rng(0)
    extra = [others[k] for k in sorted(rng.choice(len(others), min(negatives, len(others)), replace=False))]
    print(
        f"\n== {name}: {len(scans)} fragments, voxel {voxel:.4g} (grid {np.mean([len(f) for f in feats]):.0f} points "
        f"a scan), features {t_feat / len(scans):.3f} s a scan; {len(log)} gt.log pairs "
        f"({sum(abs(i - j) > 1 for i, j in log)} with |i-j| > 1), {len(extra)} negatives"
    )
    print(
        "| matcher | right / gt.log pairs | right / pairs \\|i-j\\|>1 | rot err median (deg) | trans err median (m) "
        "| < 5 deg & 0.2 m | CPU s a pair median (mean) |"
    )
    print("|---|---|---|---|---|---|---|")
    tables = {}
    for matcher in matchers:
        rows = []  # (i, j, in gt.log, right, far, rot, trans, r_ij, cpu, coverage)
        for i, j in sorted(log) + extra:
            t0 = time.process_time()
            res = register_pair(feats[i], feats[j], voxel, matcher=matcher)
            cpu = time.process_time() - t0
            T_gt = log.get((i, j), inv_T(poses[i]) @ poses[j])
            rot, trans = (float(x) for x in relative_errors(res.T, T_gt))
            right = paper_rmse(res.T, T_gt, info[(i, j)]) <= PAPER_RMSE if (i, j) in log else rot < 5 and trans < 0.2
            far = not right and (rot > FAR[0] or trans > FAR[1])
            rows.append((i, j, (i, j) in log, right, far, rot, trans, res.inliers, cpu, res.coverage))
        g = [r for r in rows if r[2]]
        far_gap = [r for r in g if abs(r[0] - r[1]) > 1]
        rot = np.array([r[5] for r in g])
        tr = np.array([r[6] for r in g])
        cpu = np.array([r[8] for r in g])
        n_right = sum(r[3] for r in g)
        n_gap = sum(r[3] for r in far_gap)
        print(
            f"| {matcher} | {n_right}/{len(g)} = {n_right / len(g):.3f} | {n_gap}/{len(far_gap)} = "
            f"{n_gap / len(far_gap):.3f} | {np.median(rot):.2f} | {np.median(tr):.3f} | "
            f"{np.mean((rot < 5) & (tr < 0.2)):.3f} | {np.median(cpu):.3f} ({cpu.mean():.3f}) |"
        )
        if show_pairs:
            for r in rows:
                print(
                    f"    {r[0]:3d} {r[1]:3d} gt.log {r[2]!s:5} right {r[3]!s:5} rot {r[5]:7.2f} trans {r[6]:6.3f} "
                    f"r_ij {r[7]:4d} coverage {r[9]:3d} cpu {r[8]:.3f}"
                )
        tables[matcher] = rows
    for matcher, rows in tables.items():
        for column, score in ((7, "r_ij"), (9, "coverage")):
            separation_table(
                f"{name}, {matcher}", score, [(r[column], "right" if r[3] else "far" if r[4] else "near") for r in rows]
            )


def separation_table(title: str, score: str, scored: list[tuple[int, str]]) -> None:
    """Histogram of a score over right, near and far pairs (``scored``: (score, kind) a pair)."""
    print(f"\n  {score} separation ({title}; gt.log pairs and negatives): pairs a bin")
    print(
        f"  | {score} | "
        + " | ".join(f"[{lo}, {hi})" if hi < 10**9 else f">= {lo}" for lo, hi in itertools.pairwise(R_BINS))
        + " |"
    )
    print("  |" + "---|" * len(R_BINS))
    for kind in ("right", "near", "far"):
        r = np.array([s for s, k in scored if k == kind], dtype=float)
        print(
            f"  | {kind} ({len(r)}) | "
            + " | ".join(str(int(np.sum((r >= lo) & (r < hi)))) for lo, hi in itertools.pairwise(R_BINS))
            + " |"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--matchers", default=",".join(MATCHERS))
    parser.add_argument("--scenes", default=",".join([*SCENES, *MATCH_SCENES]))
    parser.add_argument("--pairs", action="store_true", help="also list every pair")
    parser.add_argument("--negatives", type=int, default=40, help="3DMatch pairs outside gt.log a scene (r_ij table)")
    args = parser.parse_args()
    if not (DATA / "MANIFEST.md").is_file():
        sys.exit(f"real data not found at {DATA} (set SGHR_DATA)")
    for scene in args.scenes.split(","):
        if scene in MATCH_SCENES:
            run_3dmatch(scene, args.matchers.split(","), args.pairs, args.negatives)
        else:
            run_scene(scene, args.matchers.split(","), args.pairs)


if __name__ == "__main__":
    main()
