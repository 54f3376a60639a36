"""Full 3DMatch test scenes end to end: scans placed, the paper's registration recall and the whole-model check.

    python benchmarks/bench_3dmatch.py [--data ../shared/data] [--scenes home_at hotel_uc studyroom kitchen bunny]
        [--set key=value ...] [--workers N] [--json rows.json]

Each scene runs ``sghr_gtsam.pipeline.run`` in its own process (so peak memory is the scene's own) and is scored
by ``sghr_gtsam.evaluate.score_run``: fragments placed / unregistered / unverified; registration recall by the
paper's protocol (gt.log pairs with |i − j| > 1, a pair with an unplaced fragment counts as failed); and the
whole model: one rigid alignment of all placed scan positions to GT (as ``evo_ape --align``), then the scans
within 5° / 0.2 m (bunny: 0.2° / 0.5 mm, aligned by whole poses: its sensor positions ring the object and
leave a positions-only alignment's rotation loose), ATE rmse and rotation errors. ``doubted`` lists the placed scans
outside the tolerance (fragment numbers), ``flagged`` those the run itself called unverified, contested or
unregistered.
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
GT_3DMATCH = "3dmatch-test-gt/3DMatch"


@dataclass(frozen=True)
class Scene:
    folder: str
    gt_poses: str
    gt_dir: str | None  # folder with gt.log / gt.info
    max_deg: float = 5.0
    max_trans: float = 0.2
    align: str = "positions"  # object scans: "poses" (evaluate.align_poses)


SCENES = {
    "home_at": Scene("3dmatch-scenes/home_at", "3dmatch-scenes/home_at/gt_poses.txt",
                     f"{GT_3DMATCH}/sun3d-home_at-home_at_scan1_2013_jan_1"),
    "hotel_uc": Scene("3dmatch-scenes/hotel_uc", "3dmatch-scenes/hotel_uc/gt_poses.txt",
                      f"{GT_3DMATCH}/sun3d-hotel_uc-scan3"),
    "studyroom": Scene("3dmatch-scenes/studyroom", "3dmatch-scenes/studyroom/gt_poses.txt",
                       f"{GT_3DMATCH}/sun3d-mit_76_studyroom-76-1studyroom2"),
    "kitchen": Scene("kitchen", "kitchen/gt/gt_poses.txt", "kitchen/gt"),
    "bunny": Scene("bunny", "bunny/gt_poses.txt", None, 0.2, 0.0005, "poses"),
}
DEFAULT_SCENES = ["home_at", "hotel_uc", "studyroom"]


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
    kw = {"gt_names": gt_names, "gt_poses": gt_poses, "max_deg": scene.max_deg, "max_trans": scene.max_trans,
          "align": scene.align}
    if scene.gt_dir:
        kw["gt_log"] = read_gt_log(data / scene.gt_dir / "gt.log")
        kw["gt_info"] = read_gt_info(data / scene.gt_dir / "gt.info")
    return kw


def score_row(name: str, score, seconds: dict[str, float], wall: float, peak_mb: float | None,
              contested: list[str] = ()) -> dict:
    """One JSON-able row from a ``SceneScore``, the run's timings and its contested scans."""
    w = score.whole
    return {
        "scene": name, "scans": score.scans, "placed": len(score.placed), "unregistered": score.unregistered,
        "unverified": score.unverified, "contested": list(contested), "recall": score.recall.recall if score.recall else None,
        "within": score.within, "tolerance": [score.max_deg, score.max_trans], "ate_rmse": w.ate_rmse,
        "median_rot": float(np.median(w.rotation_deg)), "worst_rot": float(w.rotation_deg.max()),
        "worst_trans": float(w.translation.max()), "seconds": seconds, "wall": wall, "peak_mb": peak_mb,
        "doubted": score.doubted,
        "errors": {n: [float(r), float(t)] for n, r, t in zip(w.names, w.rotation_deg, w.translation)},
    }


def labels(names: list[str]) -> str:
    """Fragment numbers (or file stems) of scans, for a table cell."""
    return " ".join(fragment_label(n) for n in names) or "-"


def print_table(rows: list[dict]) -> None:
    stages = list(dict.fromkeys(k for r in rows for k in r.get("seconds", {})))
    print("| scene | scans | placed | unregistered | unverified | RR (paper) | within tol | ATE rmse m | median rot ° "
          "| worst rot ° | " + " | ".join(f"{s} s" for s in stages) + " | wall s | peak MB | doubted (whole model) "
          "| flagged by the run (unverified; contested; unregistered) |")
    print("|---" * (15 + len(stages)) + "|")
    for r in rows:
        if "error" in r:
            print(f"| {r['scene']} | failed: {r['error']} |")
            continue
        rr = "-" if r["recall"] is None else f"{r['recall']:.3f}"
        print(f"| {r['scene']} | {r['scans']} | {r['placed']}/{r['scans']} | {len(r['unregistered'])} "
              f"| {len(r['unverified'])} | {rr} | {r['within']}/{r['scans']} | {r['ate_rmse']:.4g} "
              f"| {r['median_rot']:.3g} | {r['worst_rot']:.3g} | "
              + " | ".join(f"{r['seconds'].get(s, 0.0):.1f}" for s in stages)
              + f" | {r['wall']:.0f} | {r['peak_mb']:.0f} | {labels(r['doubted'])} "
              f"| {labels(r['unverified'])}; {labels(r.get('contested', []))}; {labels(r['unregistered'])} |")


def child(scene_dir: str, overrides_json: str, workers: str) -> None:
    """Run the pipeline on one scene and print what scoring needs as one JSON line."""
    from sghr_gtsam.pipeline import run
    from sghr_gtsam.result import peak_memory_mb

    config = make_config(json.loads(overrides_json), int(workers) if workers != "none" else None)
    with tempfile.TemporaryDirectory() as out:
        res = run(scene_dir, out, config, log=lambda m: print(m, file=sys.stderr))
    print(json.dumps({"names": res.names, "poses": res.poses.tolist(), "unregistered": res.unregistered,
                      "unverified": res.unverified, "contested": res.contested, "timings": res.timings,
                      "peak_mb": peak_memory_mb()}))


def run_scene(data: Path, name: str, overrides: dict, workers: int | None) -> dict:
    from sghr_gtsam.evaluate import score_run

    scene = SCENES[name]
    started = time.perf_counter()
    proc = subprocess.run([sys.executable, __file__, "--child", str(data / scene.folder), json.dumps(overrides),
                           str(workers) if workers else "none"], capture_output=True, text=True, cwd=ROOT,
                          check=False)
    wall = time.perf_counter() - started
    if proc.returncode:
        return {"scene": name, "error": (proc.stderr.strip().splitlines() or ["?"])[-1]}
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    score = score_run(r["names"], np.array(r["poses"]), unregistered=r["unregistered"], unverified=r["unverified"],
                      **scene_gt(data, scene))
    return score_row(name, score, r["timings"], wall, r["peak_mb"], r.get("contested", []))


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(*sys.argv[2:5])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--scenes", nargs="+", default=DEFAULT_SCENES, choices=list(SCENES))
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="override a Config field (repeatable)")
    ap.add_argument("--workers", type=int, help="Config.workers, when the installed Config has it")
    ap.add_argument("--json", type=Path, help="also write the raw rows (with per-scan errors) here")
    args = ap.parse_args()
    from sghr_gtsam.config import Config
    from sghr_gtsam.types import InputError

    overrides = parse_overrides(args.overrides, Config)
    try:
        make_config(overrides, args.workers)  # a bad override fails here, before any scene runs
    except InputError as e:
        raise SystemExit(f"--set: {e}") from None
    rows = []
    for name in args.scenes:
        print(f"running {name} ...", file=sys.stderr, flush=True)
        rows.append(run_scene(args.data, name, overrides, args.workers))
    print_table(rows)
    if args.json:
        from sghr_gtsam.io.atomic import atomic_write

        with atomic_write(args.json) as f:
            json.dump({"overrides": overrides, "workers": args.workers, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
