"""Are the pose covariances calibrated? NEES on simulated scenes with known range noise, and the coverage of the
real errors by the reported σ on the real scenes.

    python benchmarks/bench_covariance.py --scenes 60 --first-seed 1000
    python benchmarks/bench_covariance.py --real [bunny kitchen home_at hotel_uc studyroom] [--workers 1]
        [--data ../shared/data] [--out DIR] [--reuse]

Real: each scene run by ``pipeline.run`` (results and cache in ``--out``/scene, kept for the next call; ``--reuse``
takes the runs an earlier call pickled there, for a change of the covariances alone), then
``gtsam_api.pose_covariances``. Every registered scan but the world scan is scored against the scene's GT and,
for the 3DMatch scenes (the kitchen's fragments are 3DMatch's too), against that GT re-fitted to the scans
(``data_tools.refit_gt``, the better reference: the shipped GT is off by degrees): its rotation and translation
errors relative to the world scan, each against the σ of its covariance along the error's own direction. The
table: share of scans within 3σ in both, median σ / error, NEES, scans more than 5° off; also written as JSON
(command, commit, machine, per-scan rows and the poses, so that runs before and after a change compare).

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
import tempfile
from pathlib import Path

import gtsam
import numpy as np
from scipy.stats import chi2

from sghr_gtsam.config import Config
from sghr_gtsam.gtsam_api import pose_covariances
from sghr_gtsam.pipeline import Scan, register, run
from sghr_gtsam.se3 import inv_T

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # data_tools
from benchmarks._results import save  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402

GROSS_DEG = 5.0


def band(m: int) -> tuple[float, float]:
    return chi2.ppf(0.025, 6 * m) / m, chi2.ppf(0.975, 6 * m) / m


def simulated(scenes: int, first_seed: int, n_scans: int) -> None:
    from sghr_gtsam.synthetic import make_scene

    rows: dict[str, list[dict]] = {"room": [], "object": []}
    gross, count = {"room": 0, "object": 0}, {"room": 0, "object": 0}
    for s in range(first_seed, first_seed + scenes):
        kind = "room" if s % 2 == 0 else "object"
        count[kind] += 1
        scene = make_scene(kind=kind, n_scans=n_scans, seed=s)
        result = register(
            [Scan(n, P) for n, P in zip(scene.names, scene.scans)],
            Config(record=False, seed=s, voxel=scene.voxel, workers=1),
            log=lambda m: None,
        )
        anchor = int(np.flatnonzero(result.sync.component == 0)[0])
        scans = coverage_rows(result.poses, scene.poses, pose_covariances(result), result.registered, anchor)
        gross[kind] += sum(r["rot"] > GROSS_DEG for r in scans)
        rows[kind] += [r for r in scans if r["rot"] <= GROSS_DEG]
        print(
            f"seed {s} {kind}: {len(scans)} scans, NEES mean {np.mean([r['nees'] for r in scans]):.2f}",
            file=sys.stderr,
            flush=True,
        )
    print(
        f"| scenes | scans | gross (> {GROSS_DEG:g}°) | mean NEES | median NEES | 95 % band of the mean "
        f"| scans with NEES < χ²₆(0.95) | within {WITHIN:g}σ | median σ/error rot | median σ/error trans |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for label, kinds in (("rooms", ["room"]), ("objects", ["object"]), ("all", ["room", "object"])):
        kept = [r for k in kinds for r in rows[k]]
        x = np.array([r["nees"] for r in kept])
        lo, hi = band(len(x))
        t = summary(kept)
        print(
            f"| {label} ({sum(count[k] for k in kinds)}) | {len(x)} | {sum(gross[k] for k in kinds)} | "
            f"{x.mean():.2f} | {np.median(x):.2f} | [{lo:.2f}, {hi:.2f}] | {np.mean(x < chi2.ppf(0.95, 6)):.0%} | "
            f"{t['covered']:.0%} | {t['median_ratio_rot']:.2f} | {t['median_ratio_trans']:.2f} |"
        )


REAL = {  # scene: folder, GT poses, voxel of the GT re-fit (None: no re-fit, the GT is the best there is)
    "bunny": ("bunny", "bunny/gt_poses.txt", None),
    "kitchen": ("kitchen", "kitchen/gt/gt_poses.txt", 0.025),
    "home_at": ("3dmatch-scenes/home_at", "3dmatch-scenes/home_at/gt_poses.txt", 0.025),
    "hotel_uc": ("3dmatch-scenes/hotel_uc", "3dmatch-scenes/hotel_uc/gt_poses.txt", 0.025),
    "studyroom": ("3dmatch-scenes/studyroom", "3dmatch-scenes/studyroom/gt_poses.txt", 0.025),
}
WITHIN = 3.0
"""A scan is covered when its rotation error and its translation error are each within this many σ, the σ of its
covariance along the error's own direction."""


def coverage_rows(
    poses: np.ndarray, gt: np.ndarray, covariances: np.ndarray, registered: list[int], anchor: int
) -> list[dict]:
    """Per registered scan but ``anchor``, errors relative to ``anchor`` (``ξ = Log(T̂⁻¹ T_gt)``, gtsam order)
    against the σ of ``covariances`` along them: rotation (degrees) and translation, their ratios σ / error, NEES."""
    est = inv_T(poses[anchor])[None] @ poses
    true = inv_T(gt[anchor])[None] @ gt
    rows = []
    for k in registered:
        if k == anchor:
            continue
        xi = gtsam.Pose3.Logmap(gtsam.Pose3(est[k]).between(gtsam.Pose3(true[k])))
        C = covariances[k]
        row = {"scan": int(k), "nees": float(xi @ np.linalg.solve(C, xi))}
        for part, block, unit in (("rot", slice(0, 3), np.degrees(1.0)), ("trans", slice(3, 6), 1.0)):
            e = float(np.linalg.norm(xi[block]))
            u = xi[block] / e if e > 0 else np.eye(3)[0]
            row[part] = e * unit
            row[f"sigma_{part}"] = float(np.sqrt(max(u @ C[block, block] @ u, 0.0))) * unit
        row["covered"] = bool(row["rot"] <= WITHIN * row["sigma_rot"] and row["trans"] <= WITHIN * row["sigma_trans"])
        rows.append(row)
    return rows


def summary(rows: list[dict]) -> dict:
    """Share of scans covered, median σ / error (rotation, translation), mean and median NEES, gross errors."""
    if not rows:
        return {"scans": 0}
    ratio = {p: np.median([r[f"sigma_{p}"] / max(r[p], 1e-12) for r in rows]) for p in ("rot", "trans")}
    nees = np.array([r["nees"] for r in rows])
    return {
        "scans": len(rows),
        "covered": float(np.mean([r["covered"] for r in rows])),
        "median_ratio_rot": float(ratio["rot"]),
        "median_ratio_trans": float(ratio["trans"]),
        "mean_nees": float(nees.mean()),
        "median_nees": float(np.median(nees)),
        "gross": int(sum(r["rot"] > GROSS_DEG for r in rows)),
    }


def _refit(folder: Path, names: list[str], gt: np.ndarray, voxel: float, out: Path) -> np.ndarray:
    """The GT re-fitted to the scans (``data_tools.refit_gt``), kept in ``out`` (it depends on the data alone)."""
    from data_tools.refit_gt import refit
    from sghr_gtsam.io.poses import read_poses, write_poses
    from sghr_gtsam.io.scans import load_scan

    path = out / "refit_gt.txt"
    if not path.exists():
        write_poses(
            path,
            names,
            refit([load_scan(folder / n) for n in names], gt, voxel).poses,
            comment="re-fitted GT (data_tools.refit_gt)",
        )
    refit_names, poses = read_poses(path)
    return poses[[refit_names.index(n) for n in names]]


def real(names: list[str], data: Path, out_root: Path, workers: int | None, reuse: bool) -> dict:
    """Each scene run (results and cache kept in ``out_root``/scene; ``reuse``: the run pickled there by an earlier
    call, so that a change of the covariances alone is measured in seconds), its ``pose_covariances`` against the
    errors to its GT and, for the 3DMatch scenes, to their GT re-fitted to the scans."""
    import dataclasses
    import pickle

    from sghr_gtsam.gtsam_api import variance_factor
    from sghr_gtsam.io.poses import read_poses

    scenes = {}
    for scene in names:
        folder, gt_file, refit_voxel = REAL[scene]
        out = out_root / scene
        saved = out_root / f"{scene}.pickle"
        if reuse and saved.exists():
            result = pickle.loads(saved.read_bytes())
        else:
            print(f"running {scene} ...", file=sys.stderr, flush=True)
            result = run(data / folder, out, Config(record=False, workers=workers), log=lambda m: None)
            result = dataclasses.replace(result, features=[])  # read from the run's store, which is gone
            saved.write_bytes(pickle.dumps(result))
        gt_names, gt = read_poses(data / gt_file)
        gt = gt[[gt_names.index(n) for n in result.names]]
        references = {"gt": gt}
        if refit_voxel is not None:
            references["refit"] = _refit(data / folder, result.names, gt, refit_voxel, out_root / f"{scene}-refit")
        C = pose_covariances(result)
        anchor = int(np.flatnonzero(result.sync.component == 0)[0])
        chosen = result.sync.weights > 0
        degree = np.bincount(np.r_[result.graph.i[chosen], result.graph.j[chosen]]).max()
        scenes[scene] = {
            "variance_factor": variance_factor(result),
            "most_edges_at_a_scan": int(degree),
            "loose": result.verdict.loose,
            "poses": result.poses.tolist(),
            "names": result.names,
        }
        for ref, truth in references.items():
            rows = coverage_rows(result.poses, truth, C, result.registered, anchor)
            for r in rows:
                r["scan"] = result.names[r["scan"]]
            scenes[scene][ref] = {"summary": summary(rows), "scans": rows}
    print("| " + " | ".join(COLUMNS) + " |")
    print("|---" * len(COLUMNS) + "|")
    for row in table(scenes):
        print("| " + " | ".join(map(str, row)) + " |")
    return scenes


COLUMNS = [
    "scene",
    "against",
    "scans",
    f"within {WITHIN:g}σ",
    "median σ/error rot",
    "median σ/error trans",
    "mean NEES",
    "median NEES",
    f"gross (> {GROSS_DEG:g}°)",
    "variance factor",
    "most edges at a scan",
]


def table(scenes: dict) -> list[list]:
    """The real scenes' coverage table, a row per scene and reference (GT as shipped, GT re-fitted to the scans)."""
    rows = []
    for scene, r in scenes.items():
        for ref in ("gt", "refit"):
            if ref in r:
                s = r[ref]["summary"]
                rows.append(
                    [
                        scene,
                        ref,
                        s["scans"],
                        f"{s['covered']:.0%}",
                        round(s["median_ratio_rot"], 2),
                        round(s["median_ratio_trans"], 2),
                        round(s["mean_nees"], 1),
                        round(s["median_nees"], 1),
                        s["gross"],
                        round(r["variance_factor"], 1),
                        r["most_edges_at_a_scan"],
                    ]
                )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", type=int, default=60)
    parser.add_argument("--first-seed", type=int, default=1000)
    parser.add_argument("--scans", type=int, default=6)
    parser.add_argument(
        "--real", nargs="*", default=None, choices=list(REAL), help="real scenes instead (none named: all of them)"
    )
    parser.add_argument("--data", type=Path, default=data_root())
    parser.add_argument(
        "--out",
        type=Path,
        default=Path(tempfile.gettempdir()) / "bench_covariance",
        help="the real runs' results and caches, kept for the next call",
    )
    parser.add_argument("--workers", type=int, help="Config.workers of the real runs")
    parser.add_argument("--reuse", action="store_true", help="the real runs of an earlier call, not run again")
    args = parser.parse_args()
    if args.real is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        scenes = real(args.real or list(REAL), args.data, args.out, args.workers, args.reuse)
        save(
            "covariance",
            table(scenes),
            COLUMNS,
            section="Covariances",
            title="Pose covariances against the real scans' errors",
            notes=f"A scan is covered when its rotation and translation errors relative to the world scan are each "
            f"within {WITHIN:g}σ along their own direction; `refit`: the GT re-fitted to the scans "
            f"(data_tools.refit_gt), `gt`: as shipped.",
        )
    else:
        simulated(args.scenes, args.first_seed, args.scans)


if __name__ == "__main__":
    main()
