"""What each rule of the trust machinery buys: the default run against the same run with one rule switched off.

    python benchmarks/bench_ablation.py [--part graphs scenes] [--seeds 0 1 2] [--rules ...]
        [--real home_at ...] [--data ../shared/data] [--workers 2]

A rule is switched off in this process only, by replacing the function that applies it with one that changes nothing
(``POLISH_RULES``, ``VERIFY_RULES``); the package itself has no switch for it. Two parts:

- ``graphs``: the steps of synchronization's loop polish (``sync._loop_placement``, ``sync._readmit``) on the pose
  graphs of ``bench_robustness.py`` (8 3DMatch scenes' ground truth, top-10 partners, a share ρ of the edges replaced
  by random or structured outliers; seeds ``--seeds``), scored by the recall over all node pairs (5° / 0.2 m).
- ``scenes``: the free-space and dispute rules that decide parts and doubts (``registration.overrule``,
  ``registration.visibility``, ``verify``), the front end's weak-group stage, and the polish steps ``--rules`` names,
  each through whole runs on the generated scenes of ``bench_doubts.py`` (rooms, fragments, buildings, hotels; seeds
  ``--seeds``) and on the real scenes ``--real``, scored as there: scans in parts of two or more, misplaced in their
  part, off the whole model, doubted, doubted and off (either way), off and not doubted.

A rule that buys nothing on any of these is a candidate for removal; one that buys something says here what a change
to it can break.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from multiprocessing import Pool
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_doubts import KINDS as SCENE_KINDS  # noqa: E402
from bench_doubts import SCANS, scene_row, scored_row  # noqa: E402
from bench_robustness import all_pairs_recall  # noqa: E402

import sghr_gtsam.pipeline as pipeline  # noqa: E402
import sghr_gtsam.sync as sync  # noqa: E402
import sghr_gtsam.verify as verify  # noqa: E402
from benchmarks._results import save  # noqa: E402
from data_tools.outlier_graphs import KINDS, SCENES, ground_truth, make_graph  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402
from sghr_gtsam.config import Config  # noqa: E402
from sghr_gtsam.io.poses import read_poses  # noqa: E402
from sghr_gtsam.scene import load_scene  # noqa: E402

RATIOS = (0.3, 0.5, 0.7)


def _unchanged(graph: object, poses: np.ndarray, *_: object) -> np.ndarray:
    return poses


class _Challengers:
    """``sync._overturns`` with its first (the grown start) or second (the second opinion) call in each loop polish
    answered "no": the polish calls it once for each, in that order."""

    def __init__(self, refused: int) -> None:
        self.refused, self.calls = refused, 0
        self.overturns, self.placement = sync._overturns, sync._loop_placement

    def install(self) -> None:
        def placement(*args, **kwargs):
            self.calls = 0
            result = self.placement(*args, **kwargs)
            if self.calls != 2:  # a row would switch off another challenger than it names
                raise RuntimeError(f"the loop polish asked _overturns {self.calls} times, not 2: update _Challengers")
            return result

        def overturns(*args):
            self.calls += 1
            return False if self.calls == self.refused else self.overturns(*args)

        sync._loop_placement, sync._overturns = placement, overturns


def _set(module: object, name: str, value: object) -> Callable[[], None]:
    getattr(module, name)  # a renamed rule fails on import (tests/test_imports.py), not as a row that changes nothing
    return lambda: setattr(module, name, value)


POLISH_RULES: dict[str, tuple[str, Callable[[], None]]] = {
    "grown start": ("the scans grown from the most consistent core, as a second start", _Challengers(1).install),
    "group moves": ("blocks hung on one edge moved where their edges agree", _set(sync, "replace_groups", _unchanged)),
    "scan consensus": (
        "single scans moved where most of their edges agree",
        _set(sync, "consensus_placement", _unchanged),
    ),
    "cut moves": (
        "groups held by several wrong edges moved across a minimum cut",
        _set(sync, "cut_moves", _unchanged),
    ),
    "second opinion": ("re-placed with the votes each weight class earned", _Challengers(2).install),
    "re-admission": (
        "edges re-judged at the least-squares optimum",
        _set(sync, "_readmit", lambda graph, poses, kept, solve: (poses, kept, np.zeros(len(kept), dtype=bool))),
    ),
}

VERIFY_RULES: dict[str, tuple[str, Callable[[], None] | dict]] = {
    "free space": ("every free-space test (Config.free_space off)", {"free_space": False}),
    "overrule": (
        "registrations holding a group where the free space rules it out dropped before synchronizing",
        _set(pipeline, "overruled_edges", lambda views, graph, result: np.zeros(graph.num_edges, dtype=bool)),
    ),
    "look-alike disputes": (
        "joins disputed where dropped registrations agree on a placement the free space cannot rule out",
        _set(pipeline, "look_alikes", lambda views, graph, sync_result: []),
    ),
    "outweighed disputes": (
        "joins disputed where dropped registrations that agree on another placement outweigh the kept ones",
        _set(verify, "_disputed", lambda graph, kept, placed, poses: []),
    ),
    "free-space cut": (
        "joins cut where more pairs of scans across them conflict than they have registrations",
        _set(
            verify,
            "_seen_through",
            lambda graph, passed, placed, conflicts: (
                np.zeros(graph.num_edges, dtype=bool),
                verify.rigid_parts(graph.n, graph.i, graph.j, passed, placed, graph.weight),
            ),
        ),
    ),
    "scan blame": (
        "a scan in free-space conflicts that no cut separates doubted",
        _set(verify, "contradicted_scans", lambda clash, parts, held: np.zeros(len(parts), dtype=bool)),
    ),
    "guessed edges": (
        "registrations started from the poses they check not counted as independent for weak scans",
        _set(pipeline, "GUESSED", ()),
    ),
    "weak groups": ("weak groups registered whole (Config.groups off)", {"groups": False}),
}
SCENE_RULES = {**VERIFY_RULES, **POLISH_RULES}


def _polish_task(task: tuple[str, int, str, float]) -> float:
    scene, seed, kind, ratio = task
    graph, _, _ = make_graph(scene, ratio, kind, seed)
    return all_pairs_recall(sync.synchronize(graph).poses, ground_truth(scene, seed).poses)


def polish_table(seeds: list[int], jobs: int) -> list[list]:
    """Per rule switched off: the all-pairs recall per kind and ratio, averaged over the scenes and seeds."""
    rows = []
    for rule in ["default", *POLISH_RULES]:
        tasks = [(s, seed, k, r) for k in KINDS for r in RATIOS for s in SCENES for seed in seeds]
        with Pool(jobs, initializer=None if rule == "default" else POLISH_RULES[rule][1]) as pool:
            recall = np.array(pool.map(_polish_task, tasks)).reshape(len(KINDS), len(RATIOS), -1).mean(axis=2)
        what = "every rule on" if rule == "default" else POLISH_RULES[rule][0]
        rows.append([rule if rule == "default" else f"− {rule}", what, *(f"{x:.3f}" for x in recall.ravel())])
        print(" | ".join(map(str, rows[-1])), flush=True)
    return rows


def _real_row(data: Path, name: str, workers: int, overrides: dict) -> dict:
    """A shared real scene run and scored as ``bench_doubts.scene_row`` scores a generated one."""
    folder = data / "3dmatch-scenes" / name if (data / "3dmatch-scenes" / name).exists() else data / name
    config = Config(**{**overrides, "record": False, "workers": workers})
    scans, _ = load_scene(folder, config, lambda m: None)
    result = pipeline.register(scans, config)
    truth = dict(zip(*read_poses(folder / "gt_poses.txt")))
    return scored_row(name, result, np.stack([truth[n] for n in result.names]))


def _counts(rows: list[dict]) -> list[int]:
    """Scans, scans in parts of two or more, misplaced in their part, off the whole model, doubted, doubted and off,
    off and not doubted, summed over ``rows`` (``bench_doubts.scene_row``'s)."""
    off = [set(r["off"]) for r in rows]
    doubted = [set(r["doubted"]) for r in rows]
    return [
        sum(r["scans"] for r in rows),
        sum(int(x) for r in rows for x in r["parts"].split(" + ") if int(x) > 1),
        sum(len(r["misplaced"]) for r in rows),
        sum(len(o) for o in off),
        sum(len(d) for d in doubted),
        sum(len(d & o) for d, o in zip(doubted, off)),
        sum(len(o - d) for d, o in zip(doubted, off)),
    ]


def scenes_table(rules: list[str], seeds: list[int], real: list[str], data: Path | None, workers: int) -> list[list]:
    """Per rule switched off (``VERIFY_RULES`` or ``POLISH_RULES``): the counts of ``_counts`` over the generated
    scenes, then over the real ones."""
    rows = []
    for rule in ["default", *rules]:
        what, switch = SCENE_RULES.get(rule, ("every rule on", {}))
        overrides = switch if isinstance(switch, dict) else {}
        saved = {m: dict(vars(m)) for m in (pipeline, verify, sync)}
        if callable(switch):
            switch()
        try:
            generated = []
            for kind in SCENE_KINDS:
                for scans in SCANS[kind]:
                    for seed in seeds:
                        generated.append(scene_row(kind, scans, seed, workers, overrides))
            measured = [_real_row(data, name, workers, overrides) for name in real] if data else []
        finally:
            for m, names in saved.items():
                vars(m).update(names)
        label = rule if rule == "default" else f"− {rule}"
        rows.append([label, what, "generated", *_counts(generated)])
        print(" | ".join(map(str, rows[-1])), flush=True)
        if measured:
            rows.append([label, what, " ".join(real), *_counts(measured)])
            print(" | ".join(map(str, rows[-1])), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", nargs="+", default=["graphs", "scenes"], choices=["graphs", "scenes"])
    ap.add_argument(
        "--rules", nargs="+", default=list(VERIFY_RULES), choices=list(SCENE_RULES), help="those switched off in scenes"
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--real", nargs="*", default=[], help="shared real scenes with gt_poses.txt, e.g. home_at")
    ap.add_argument("--data", type=Path, default=None, help="the shared data (default: $SGHR_DATA or ../shared/data)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-save", action="store_true")
    args = ap.parse_args(argv)
    data = None
    if args.real:
        data = args.data or data_root()
        if not (data / "3dmatch-scenes").exists():
            print(f"no shared data at {data}: the real scenes are left out")
            data = None
    seeds = " ".join(map(str, args.seeds))
    if "graphs" in args.part:
        columns = ["switched off", "what it does", *(f"{k} ρ={r}" for k in KINDS for r in RATIOS)]
        rows = polish_table(args.seeds, args.workers)
        if not args.no_save:
            save(
                "ablation_polish",
                rows,
                columns,
                section="Synchronization",
                title=f"The loop polish without each of its steps: all-pairs recall (8 scenes × seeds {seeds})",
            )
    if "scenes" in args.part:
        columns = [
            "switched off",
            "what it does",
            "scenes",
            "scans",
            "in parts of 2+",
            "misplaced in its part",
            "off the whole model",
            "doubted",
            "doubted and off",
            "off, not doubted",
        ]
        rows = scenes_table(args.rules, args.seeds, args.real, data, args.workers)
        if not args.no_save:
            save(
                "ablation_verify",
                rows,
                columns,
                title=f"Parts and doubts without each rule (bench_doubts' generated scenes, seeds {seeds}; "
                + (f"{' '.join(args.real)})" if data else "no real scene)"),
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
