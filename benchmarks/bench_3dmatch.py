"""Full 3DMatch test scenes end to end: scans placed, the paper's registration recall and the whole-model check.

    python benchmarks/bench_3dmatch.py [--data ../shared/data] [--scenes home_at hotel_uc studyroom kitchen bunny
        bunny_ring | unseen] [--set key=value ...] [--workers N] [--refit-gt] [--gt-overlap] [--json rows.json]

Each scene runs ``sghr_gtsam.pipeline.run`` in its own process (so peak memory is the scene's own) and is scored
by ``sghr_gtsam.evaluate.score_run``: fragments placed / unregistered; registration recall by the paper's
protocol on 3DMatch (gt.log) and 3DLoMatch (its gt.log: pairs of 10-30 % overlap) pairs with |i − j| > 1, a pair
with an unplaced fragment counting as failed; the run's parts (``verify``) by ``evaluate.score_parts``: a scan is
misplaced when outside the largest rigid piece of its own part (15° / 0.6 m against GT), and the doubted scans
(the run's doubts) are scored against the misplaced ones and against the scans outside the largest rigid piece of
the whole model (a scan alone in its part, or a part placed by a failed join, can be off there only); and the
whole model: one rigid alignment of all placed scan positions to GT (as ``evo_ape --align``), then the scans
within 5° / 0.2 m (bunny: 0.2° / 0.5 mm, aligned by whole poses: its sensor positions ring the object and
leave a positions-only alignment's rotation loose), ATE rmse and rotation errors. ``doubted`` lists the placed scans
outside the tolerance (fragment numbers), and ``unflagged wrong`` the scans of the trusted model (``Verdict.trusted``:
the
verified scans of the world part) that one rigid alignment of those scans alone leaves outside the tolerance
(``SceneScore.unflagged_wrong``: a wrong model that looks right). ``bunny_ring`` is the bunny's six
ring scans alone (45-90° apart). ``unseen`` is the other five 3DMatch test scenes (``kitchen60``, ``home_md``,
``hotel_umd1``, ``hotel_umd3``, ``mit_lab``), built by ``data_tools.other_3dmatch_scenes`` into a folder of their own.
``--refit-gt`` also scores the 3DMatch scenes against their GT re-fitted to the scans (``data_tools.refit_gt``):
the GT's own error, measured, beside the GT and never instead of it.
``--gt-overlap`` chooses each scan's top-k partners by the scene's GT overlap (``gt_overlap.log``) instead of the
global features: an upper reference for what a better overlap estimate could do, never a result.
``--set`` overrides a ``Config`` field (parsed by the field's type, ``none`` for None) for ablations;
``--workers`` is passed to ``Config.workers`` when the installed Config has that field. Seconds per stage
are the run's own timings; ``wall s`` is the whole child process, imports included.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
import types
import typing
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # data_tools
from benchmarks._results import save  # noqa: E402
from data_tools.other_3dmatch_scenes import GT_DIR as GT_3DMATCH  # noqa: E402
from data_tools.other_3dmatch_scenes import OTHER_SCENES  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402


@dataclass(frozen=True)
class Scene:
    folder: str
    gt_poses: str
    gt_dir: str | None  # folder with gt.log / gt.info
    max_deg: float = 5.0
    max_trans: float = 0.2
    align: str = "positions"  # object scans: "poses" (evaluate.align_poses)
    scans: tuple[str, ...] = ()  # a subset of the folder's scans (all when empty)


SCENES = {
    "home_at": Scene(
        "3dmatch-scenes/home_at",
        "3dmatch-scenes/home_at/gt_poses.txt",
        f"{GT_3DMATCH}/sun3d-home_at-home_at_scan1_2013_jan_1",
    ),
    "hotel_uc": Scene(
        "3dmatch-scenes/hotel_uc", "3dmatch-scenes/hotel_uc/gt_poses.txt", f"{GT_3DMATCH}/sun3d-hotel_uc-scan3"
    ),
    "studyroom": Scene(
        "3dmatch-scenes/studyroom",
        "3dmatch-scenes/studyroom/gt_poses.txt",
        f"{GT_3DMATCH}/sun3d-mit_76_studyroom-76-1studyroom2",
    ),
    "kitchen": Scene("kitchen", "kitchen/gt/gt_poses.txt", "kitchen/gt"),
    "bunny": Scene("bunny", "bunny/gt_poses.txt", None, 0.2, 0.0005, "poses"),
    "bunny_ring": Scene(
        "bunny",
        "bunny/gt_poses.txt",
        None,
        0.3,
        0.0006,
        "poses",
        tuple(f"bun{a:03d}.ply" for a in (0, 45, 90, 180, 270, 315)),
    ),
}
DEFAULT_SCENES = ["home_at", "hotel_uc", "studyroom"]
# The other five 3DMatch test scenes, never tuned to: not in the shared data, built into a data folder of their own
# by data_tools.other_3dmatch_scenes (then --data that folder); --scenes unseen runs them all.
for _name, _full in OTHER_SCENES.items():
    SCENES[_name] = Scene(f"3dmatch-scenes/{_name}", f"3dmatch-scenes/{_name}/gt_poses.txt", f"{GT_3DMATCH}/{_full}")
GROUPS = {"unseen": list(OTHER_SCENES)}


def parse_overrides(pairs: list[str], config_cls: type) -> dict:
    """``key=value`` strings to Config field values, each parsed by the field's declared type."""
    hints = typing.get_type_hints(config_cls)
    out = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or key not in hints:
            raise SystemExit(f"--set {pair!r}: expected key=value with key one of {', '.join(sorted(hints))}")
        allowed = typing.get_args(hints[key]) if isinstance(hints[key], types.UnionType) else (hints[key],)
        if text.lower() == "none" and type(None) in allowed:
            out[key] = None
            continue
        for kind in (bool, int, float, str):
            if kind not in allowed:
                continue
            if kind is bool:
                if text.lower() in ("true", "false", "1", "0"):
                    out[key] = text.lower() in ("true", "1")
                    break
                continue
            try:
                out[key] = kind(text)
                break
            except ValueError:
                continue
        else:
            raise SystemExit(f"--set {pair!r}: cannot read {text!r} as {hints[key]}")
    return out


def make_config(overrides: dict, workers: int | None):
    from sghr_gtsam.config import Config

    values = dict(overrides)
    if workers is not None and "workers" in {f.name for f in fields(Config)}:
        values["workers"] = workers
    return Config(**values).validate()


def fragment_label(name: str) -> str:
    from sghr_gtsam.evaluate import fragment_id

    stem = Path(name).stem
    return str(fragment_id(name)) if stem.startswith("cloud_bin_") else stem


def scene_gt(data: Path, scene: Scene) -> dict:
    """GT of a scene as ``score_run`` keyword arguments (gt names and poses, gt.log/gt.info when given)."""
    from sghr_gtsam.io.poses import read_gt_info, read_gt_log, read_poses

    gt_names, gt_poses = read_poses(data / scene.gt_poses)
    if scene.scans:
        keep = [gt_names.index(n) for n in scene.scans]
        gt_names, gt_poses = [gt_names[k] for k in keep], gt_poses[keep]
    kw = {
        "gt_names": gt_names,
        "gt_poses": gt_poses,
        "max_deg": scene.max_deg,
        "max_trans": scene.max_trans,
        "align": scene.align,
    }
    if scene.gt_dir:
        kw["gt_log"] = read_gt_log(data / scene.gt_dir / "gt.log")
        kw["gt_info"] = read_gt_info(data / scene.gt_dir / "gt.info")
    return kw


def lo_gt(data: Path, scene: Scene) -> tuple[dict, dict] | None:
    """The scene's 3DLoMatch pairs (gt.log, gt.info of the 3DLoMatch benchmark; the kitchen's gtLo files), or None."""
    from sghr_gtsam.io.poses import read_gt_info, read_gt_log

    if not scene.gt_dir:
        return None
    folder = data / scene.gt_dir
    for log, info in (
        (folder / "gtLo.log", folder / "gtLo.info"),
        (
            data / scene.gt_dir.replace("/3DMatch/", "/3DLoMatch/") / "gt.log",
            data / scene.gt_dir.replace("/3DMatch/", "/3DLoMatch/") / "gt.info",
        ),
    ):
        if log.is_file() and info.is_file():
            return read_gt_log(log), read_gt_info(info)
    return None


def score_row(
    name: str, score, seconds: dict[str, float], wall: float, peak_mb: float | None, parts, lo_recall: float | None
) -> dict:
    """One JSON-able row from a ``SceneScore``, the run's timings, its ``evaluate.PartsScore`` and its 3DLoMatch
    recall."""
    w = score.whole
    return {
        "scene": name,
        "scans": score.scans,
        "placed": len(score.placed),
        "unregistered": score.unregistered,
        "parts": [len(p) for p in parts.parts],
        "pieces": [len(p) for p in parts.pieces],
        "misplaced": parts.misplaced,
        "doubts": parts.doubted,
        "caught": parts.caught,
        "unflagged_wrong": score.unflagged_wrong,
        "recall": score.recall.recall if score.recall else None,
        "lo_recall": lo_recall,
        "within": score.within,
        "tolerance": [score.max_deg, score.max_trans],
        "ate_rmse": w.ate_rmse,
        "median_rot": float(np.median(w.rotation_deg)),
        "worst_rot": float(w.rotation_deg.max()),
        "worst_trans": float(w.translation.max()),
        "seconds": seconds,
        "wall": wall,
        "peak_mb": peak_mb,
        "doubted": score.doubted,
        "errors": {n: [float(r), float(t)] for n, r, t in zip(w.names, w.rotation_deg, w.translation)},
    }


def labels(names: list[str]) -> str:
    """Fragment numbers (or file stems) of scans, for a table cell."""
    return " ".join(fragment_label(n) for n in names) or "-"


def tables(rows: list[dict]) -> list[tuple[str, list[str], list[list]]]:
    """The runs' table, then (with ``--refit-gt``) the same runs against the re-fitted GT: (kind, columns, rows)."""
    stages = list(dict.fromkeys(k for r in rows for k in r.get("seconds", {})))
    columns = [
        "scene",
        "scans",
        "placed",
        "RR (paper)",
        "3DLoMatch RR",
        "parts (scans)",
        "misplaced in its part",
        "doubted by the run",
        "of them misplaced",
        "of them off the whole model",
        "within tol",
        "ATE rmse m",
        "median rot °",
        "worst rot °",
        *(f"{s} s" for s in stages),
        "wall s",
        "peak MB",
        "outside tol (whole model)",
        "unflagged wrong",
    ]
    cells = []
    for r in rows:
        if "error" in r:
            cells.append([r["scene"], f"failed: {r['error']}", *[""] * (len(columns) - 2)])
            continue
        rr = "-" if r["recall"] is None else f"{r['recall']:.3f}"
        lo = "-" if r["lo_recall"] is None else f"{r['lo_recall']:.3f}"
        cells.append(
            [
                r["scene"],
                r["scans"],
                f"{r['placed']}/{r['scans']}",
                rr,
                lo,
                " + ".join(map(str, r["parts"])),
                labels(r["misplaced"]),
                labels(r["doubts"]),
                len(r["caught"]),
                len(r.get("doubted_off_whole", [])),
                f"{r['within']}/{r['scans']}",
                f"{r['ate_rmse']:.4g}",
                f"{r['median_rot']:.3g}",
                f"{r['worst_rot']:.3g}",
                *(f"{r['seconds'].get(s, 0.0):.1f}" for s in stages),
                f"{r['wall']:.0f}",
                f"{r['peak_mb']:.0f}",
                labels(r["doubted"]),
                labels(r["unflagged_wrong"]),
            ]
        )
    out = [("runs", columns, cells)]
    refit = [r for r in rows if "refit" in r]
    if refit:
        columns = [
            "scene",
            "pairs re-fitted",
            "ICP optimum from GT: rot median / 90 % °",
            "trans median / 90 % m",
            "re-fitted GT vs GT: within tol, ATE m",
            "within tol",
            "ATE rmse m",
            "doubted",
            "unflagged wrong",
            "placed together (5° / 0.2 m): scans, fragments, turn against the largest",
        ]
        cells = []
        for r in refit:
            f = r["refit"]
            cells.append(
                [
                    r["scene"],
                    f["pairs"],
                    f"{f['rot'][0]:.2f} / {f['rot'][1]:.2f}",
                    f"{f['trans'][0]:.3f} / {f['trans'][1]:.3f}",
                    f"{f['gt_within']}/{r['scans']}, {f['gt_ate']:.3f}",
                    f"{f['within']}/{r['scans']}",
                    f"{f['ate_rmse']:.4g}",
                    labels(f["doubted"]),
                    labels(f["unflagged_wrong"]),
                    "; ".join(f.get("groups", [])),
                ]
            )
        out.append(("refit", columns, cells))
    return out


def print_table(rows: list[dict]) -> None:
    for kind, columns, cells in tables(rows):
        if kind == "refit":
            print("\nThe same runs against the GT re-fitted to the scans (data_tools.refit_gt):\n")
        print("| " + " | ".join(columns) + " |")
        print("|---" * len(columns) + "|")
        for row in cells:
            print("| " + " | ".join(str(c) for c in row) + " |")


def child(scene_dir: str, overrides_json: str, workers: str, overlap_log: str) -> None:
    """Run the pipeline on one scene and print what scoring needs as one JSON line. With ``overlap_log`` (not
    "none") the top-k graph comes from those GT overlaps (``register(scores=...)``) and no output is written."""
    from sghr_gtsam.pipeline import load_scene, register, run
    from sghr_gtsam.result import peak_memory_mb

    config = make_config(json.loads(overrides_json), int(workers) if workers != "none" else None)
    log = lambda m: print(m, file=sys.stderr)  # noqa: E731
    if overlap_log == "none":
        with tempfile.TemporaryDirectory() as out:
            res = run(scene_dir, out, config, log=log)
    else:
        from data_tools.scene_gt import log_overlaps
        from sghr_gtsam.evaluate import fragment_id

        scans, skipped = load_scene(scene_dir, config, log)
        scores = log_overlaps(Path(overlap_log), [fragment_id(s.name) for s in scans])
        res = register(scans, config, log=log, skipped=skipped, scores=scores)
    verdict = res.verdict
    print(
        json.dumps(
            {
                "names": res.names,
                "poses": res.poses.tolist(),
                "unregistered": res.unregistered,
                "trusted": verdict.trusted(),
                "parts": [p.scans for p in verdict.parts],
                "doubts": list(verdict.doubts),
                "timings": res.timings,
                "peak_mb": peak_memory_mb(),
            }
        )
    )


def run_scene(
    data: Path, name: str, overrides: dict, workers: int | None, refit_gt: bool = False, gt_overlap: bool = False
) -> dict:
    from sghr_gtsam.evaluate import fragment_id, registration_recall_counting_unplaced, score_parts, score_run

    scene = SCENES[name]
    with tempfile.TemporaryDirectory() as subset:
        folder = data / scene.folder
        if scene.scans:  # the subset as a folder of links
            for n in scene.scans:
                (Path(subset) / n).symlink_to(folder / n)
            folder = Path(subset)
        started = time.perf_counter()
        overlap_log = str(data / scene.gt_dir / "gt_overlap.log") if gt_overlap and scene.gt_dir else "none"
        proc = subprocess.run(
            [
                sys.executable,
                __file__,
                "--child",
                str(folder),
                json.dumps(overrides),
                str(workers) if workers else "none",
                overlap_log,
            ],
            capture_output=True,
            text=True,
            cwd=ROOT,
            check=False,
        )
        wall = time.perf_counter() - started
    if proc.returncode:
        return {"scene": name, "error": (proc.stderr.strip().splitlines() or ["?"])[-1]}
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    names, poses = r["names"], np.array(r["poses"])
    gt = scene_gt(data, scene)
    flagged = set(names) - set(r["trusted"])
    score = score_run(names, poses, unregistered=r["unregistered"], flagged=flagged, **gt)
    gt_by_name = dict(zip(gt["gt_names"], gt["gt_poses"]))
    truth = np.stack([gt_by_name[n] for n in names])
    parts = score_parts(names, poses, truth, r["parts"], r["doubts"])
    unregistered = set(r["unregistered"])
    placed = [k for k, n in enumerate(names) if n not in unregistered]
    whole = score_parts(names, poses, truth, [[names[k] for k in placed]], r["doubts"])  # the whole model as one part
    lo_recall = None
    lo = lo_gt(data, scene)
    if lo is not None:
        lo_recall = registration_recall_counting_unplaced(
            [fragment_id(names[k]) for k in placed],
            poses[placed],
            *lo,
            scene_ids=[fragment_id(n) for n in gt["gt_names"]],
        ).recall
    row = score_row(name, score, r["timings"], wall, r["peak_mb"], parts, lo_recall)
    row["doubted_off_whole"] = whole.caught
    row["poses"] = dict(zip(names, r["poses"]))  # for scoring against another reference later
    if refit_gt and scene.gt_dir:
        row["refit"] = refit_row(data, scene, names, poses, r, gt)
    return row


def refit_row(data: Path, scene: Scene, names: list[str], poses: np.ndarray, r: dict, gt: dict) -> dict:
    """The run scored against its scene's GT re-fitted to the scans (``data_tools.refit_gt``)."""
    from data_tools.refit_gt import refit
    from sghr_gtsam.evaluate import score_run, whole_model_errors
    from sghr_gtsam.io.scans import load_scan

    fit = refit([load_scan(data / scene.folder / n) for n in gt["gt_names"]], gt["gt_poses"], 0.025)
    against = {**gt, "gt_poses": fit.poses, "gt_log": None, "gt_info": None}
    score = score_run(names, poses, unregistered=r["unregistered"], flagged=set(names) - set(r["trusted"]), **against)
    moved = whole_model_errors(gt["gt_names"], fit.poses, gt["gt_poses"], gt["align"])
    rot, trans = fit.icp_move.T
    return {
        "pairs": len(fit.pairs),
        "rot": [float(np.median(rot)), float(np.quantile(rot, 0.9))],
        "trans": [float(np.median(trans)), float(np.quantile(trans, 0.9))],
        "gt_within": int(moved.within(gt["max_deg"], gt["max_trans"]).sum()),
        "gt_ate": moved.ate_rmse,
        "within": score.within,
        "ate_rmse": score.whole.ate_rmse,
        "doubted": score.doubted,
        "unflagged_wrong": score.unflagged_wrong,
        "groups": _groups(names, poses, r["unregistered"], gt, fit.poses),
    }


def _groups(names: list[str], poses: np.ndarray, unregistered: list[str], gt: dict, truth: np.ndarray) -> list[str]:
    """``placement_groups`` of the placed scans against ``truth`` (poses of ``gt["gt_names"]``)."""
    from data_tools.scene_gt import placement_groups
    from sghr_gtsam.evaluate import fragment_id

    index = {n: k for k, n in enumerate(gt["gt_names"])}
    skip = set(unregistered)
    placed = [k for k, n in enumerate(names) if n not in skip]
    return placement_groups(
        poses[placed], truth[[index[names[k]] for k in placed]], [fragment_id(names[k]) for k in placed]
    )


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(*sys.argv[2:6])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=data_root())
    ap.add_argument("--scenes", nargs="+", default=DEFAULT_SCENES, choices=[*SCENES, *GROUPS])
    ap.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a Config field (repeatable)",
    )
    ap.add_argument("--workers", type=int, help="Config.workers, when the installed Config has it")
    ap.add_argument("--json", type=Path, help="also write the raw rows (with per-scan errors) here")
    ap.add_argument(
        "--refit-gt",
        action="store_true",
        help="also score the 3DMatch scenes against their GT re-fitted to the scans (data_tools.refit_gt)",
    )
    ap.add_argument(
        "--gt-overlap",
        action="store_true",
        help="the top-k graph from the scenes' GT overlaps (gt_overlap.log; 3DMatch scenes and kitchen): "
        "an upper reference for the overlap estimate, not a result",
    )
    args = ap.parse_args()
    from sghr_gtsam.config import Config
    from sghr_gtsam.types import InputError

    overrides = parse_overrides(args.overrides, Config)
    try:
        make_config(overrides, args.workers)  # a bad override fails here, before any scene runs
    except InputError as e:
        raise SystemExit(f"--set: {e}") from None
    rows = []
    for name in [n for group in args.scenes for n in GROUPS.get(group, [group])]:
        if not (args.data / SCENES[name].folder).is_dir():
            rows.append(
                {
                    "scene": name,
                    "error": f"{args.data / SCENES[name].folder} not found"
                    + (" (python -m data_tools.other_3dmatch_scenes)" if name in OTHER_SCENES else ""),
                }
            )
            continue
        print(f"running {name} ...", file=sys.stderr, flush=True)
        rows.append(run_scene(args.data, name, overrides, args.workers, args.refit_gt, args.gt_overlap))
    print_table(rows)
    if not overrides and not args.gt_overlap:  # the defaults' results: the benchmarks page's tables
        which = "unseen" if args.scenes == ["unseen"] else "shared"  # the titles name the scenes
        for kind, columns, cells in tables(rows):
            title = (
                f"{', '.join(args.scenes)}: the runs"
                if kind == "runs"
                else f"{', '.join(args.scenes)}: the same runs against the GT re-fitted to the scans"
            )
            save(f"3dmatch_{which}_{kind}", cells, columns, section="3DMatch end to end", title=title)
    if args.json:
        from sghr_gtsam.io.atomic import atomic_write

        with atomic_write(args.json) as f:
            json.dump({"overrides": overrides, "workers": args.workers, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
