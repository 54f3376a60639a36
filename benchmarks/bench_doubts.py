"""Doubts on generated scenes: do a run's doubts catch its misplaced scans, and how many right ones do they mark?

    python benchmarks/bench_doubts.py [--kinds room fragments building hotel] [--seeds 0 1 2] [--workers 2]
        [--set KEY=VALUE]

Each scene is ``synthetic.make_scene(kind, scans, seed)`` (rooms of 10 scans; RGB-D fragments of a room, fused from a
walking camera's frames, of 12; buildings of 12, 20 and 30; hotels, whose rooms are all alike, of 16 and 30), registered
by ``pipeline.register`` with the default ``Config`` (``record=False``); the scene column reads kind, scans / seed. Its
parts (``verify``) are scored against GT by ``evaluate.score_parts`` as ``bench_3dmatch.py`` scores the real scenes: a
scan is *misplaced* when outside the largest rigid piece of its own part (15° / 0.6 m), and *off the whole model* when
outside the largest rigid piece of all placed scans (where a scan alone in its part, or a part placed by a failed join,
can be off). Per scene: parts, misplaced, off the whole model, doubted, and how the doubts split; a row per kind sums
its scenes, and the notes give per kind the doubts' precision (doubted scans that are off, either way, of the doubted)
and recall (scans off doubted, of them), and the share of scans doubted in scenes where none is off.

``--set`` overrides a ``Config`` field in every run (such a run is printed, not saved): a change well below any
registration's noise (``icp_distance=1.5015``, as in ``bench_stability.py``) shows how far these scenes' answers move
by chance.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_3dmatch import parse_overrides  # noqa: E402

from benchmarks._results import save  # noqa: E402
from sghr_gtsam.config import Config  # noqa: E402
from sghr_gtsam.evaluate import score_parts  # noqa: E402
from sghr_gtsam.pipeline import Scan, register  # noqa: E402
from sghr_gtsam.result import RunResult  # noqa: E402
from sghr_gtsam.synthetic import make_scene  # noqa: E402

SCANS = {"room": (10,), "object": (10,), "fragments": (12,), "building": (12, 20, 30), "hotel": (16, 30)}
KINDS = ("room", "fragments", "building", "hotel")
"""The kinds a run takes unless ``--kinds`` names others."""
COLUMNS = [
    "scene (scans / seed)",
    "scans",
    "placed",
    "parts",
    "misplaced in its part",
    "off the whole model",
    "doubted",
    "doubted and off",
    "off, not doubted",
]


def scene_row(kind: str, scans: int, seed: int, workers: int, overrides: dict | None = None) -> dict:
    """One generated scene run and scored (module doc)."""
    scene = make_scene(kind, scans, seed)
    result = register(
        [Scan(n, np.asarray(P)) for n, P in zip(scene.names, scene.scans)],
        Config(**{**(overrides or {}), "record": False, "workers": workers}),
        log=lambda m: None,
    )
    return scored_row(f"{kind} {scans}/{seed}", result, scene.poses)


def scored_row(label: str, result: RunResult, truth: np.ndarray) -> dict:
    """A run's parts and doubts scored against the ground truth ``truth`` ((N, 4, 4), in ``result.names``' order)."""
    names, poses = result.names, result.poses
    placed = [names[k] for k in result.registered]
    parts = [p.scans for p in result.verdict.parts]
    doubted = sorted(result.verdict.doubts, key=names.index)
    by_part = score_parts(names, poses, truth, parts, doubted)
    whole = score_parts(names, poses, truth, [placed], doubted)
    off = set(whole.misplaced) | set(by_part.misplaced)
    return {
        "scene": label,
        "scans": len(names),
        "placed": len(placed),
        "parts": " + ".join(str(len(p)) for p in parts),
        "misplaced": by_part.misplaced,
        "off": sorted(off, key=names.index),
        "doubted": doubted,
        "caught": [n for n in doubted if n in off],
        "missed": [n for n in sorted(off, key=names.index) if n not in set(doubted)],
    }


def _plural(kind: str) -> str:
    return kind if kind.endswith("s") else kind + "s"


def _total(kind: str, rows: list[dict]) -> list:
    """The table's row summing ``rows``."""
    return [
        f"all {_plural(kind)}",
        sum(r["scans"] for r in rows),
        sum(r["placed"] for r in rows),
        "",
        sum(len(r["misplaced"]) for r in rows),
        sum(len(r["off"]) for r in rows),
        sum(len(r["doubted"]) for r in rows),
        sum(len(r["caught"]) for r in rows),
        sum(len(r["missed"]) for r in rows),
    ]


def _summary(kind: str, rows: list[dict]) -> str:
    """The doubts' precision and recall over ``rows``, and the share doubted where no scan is off."""
    doubted = sum(len(r["doubted"]) for r in rows)
    caught = sum(len(r["caught"]) for r in rows)
    off = sum(len(r["off"]) for r in rows)
    clean = [r for r in rows if not r["off"]]
    precision = f"{caught / doubted:.2f}" if doubted else "-"
    recall = f"{caught / off:.2f}" if off else "-"
    return (
        f"{_plural(kind).capitalize()}: precision {precision} ({caught} of {doubted} doubts on scans off), "
        f"recall {recall} ({caught} of {off} scans off doubted); in the {len(clean)} with no scan off, "
        f"{sum(len(r['doubted']) for r in clean)} of {sum(r['scans'] for r in clean)} scans doubted."
    )


def _labels(names: list[str]) -> str:
    return " ".join(n.removeprefix("scan_").removesuffix(".ply") for n in names) or "-"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kinds", nargs="+", default=list(KINDS), choices=list(SCANS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-save", action="store_true")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a Config field")
    args = ap.parse_args(argv)
    overrides = parse_overrides(args.set, Config)
    rows = []
    for kind in args.kinds:
        for scans in SCANS[kind]:
            for seed in args.seeds:
                r = scene_row(kind, scans, seed, args.workers, overrides)
                rows.append(r)
                print(f"{r['scene']}: parts {r['parts']}, off {_labels(r['off'])}, doubted {_labels(r['doubted'])}")
    table = [
        [
            r["scene"],
            r["scans"],
            r["placed"],
            r["parts"],
            _labels(r["misplaced"]),
            _labels(r["off"]),
            _labels(r["doubted"]),
            len(r["caught"]),
            _labels(r["missed"]),
        ]
        for r in rows
    ]
    summaries = []
    for kind in args.kinds:
        of_kind = [r for r in rows if r["scene"].split()[0] == kind]
        table.append(_total(kind, of_kind))
        summaries.append(_summary(kind, of_kind))
    summary = " ".join(summaries)
    print("| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS))
    for row in table:
        print("| " + " | ".join(str(x) for x in row) + " |")
    print(summary)
    if not args.no_save and not overrides:
        save(
            "doubts_generated",
            table,
            COLUMNS,
            notes=summary,
            section="Other",
            title="Doubts on generated scenes: the misplaced scans they catch, the right ones they mark",
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
