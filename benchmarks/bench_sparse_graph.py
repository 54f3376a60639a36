"""Sparse top-k pose graph against the exhaustive graph (all pairs), end to end on the real scenes.

    python benchmarks/bench_sparse_graph.py [--data ../shared/data] [--scenes kitchen bunny]
                                            [--ks 2 3 4] [--random-seeds 5]
    python benchmarks/bench_sparse_graph.py --sim-rooms 0 1 2 [--sim-scans 50] --ks 5 10 --random-seeds 1
    python benchmarks/bench_sparse_graph.py --sim-rooms 0 --steps [on off exhaustive] [--ks 10] [--set KEY=VALUE]

Is the learned top-k graph at least as accurate as the exhaustive one with at most 40 % of its
pairs? Every row is a full ``pipeline.register`` run (features, global scores and top-k graph, pairwise
registration on the graph's edges, history-reweighted IRLS, gtsam polish) on the scans read once by
``scene.load_scene``, default ``Config`` except ``k``, ``global_feature`` and ``record=False``.
Rows per scene:

- **exhaustive**: k = N − 1 (every pair), with the default VLAD-codebook scores and with the learned head's
  (the scores still weigh the edges, ``w⁰ = s · r``);
- **learned head** / **VLAD codebook**: ``Config(global_feature="learned" | "vlad", k=k)``;
- **random scores**: uniform symmetric random scores (seeds 0 … S−1), the mean of the runs;
- **GT overlap** (upper reference): the GT overlaps as scores (kitchen: ``gt/gt_overlap.log``; bunny:
  ``data_tools.gt_overlap`` under the GT poses, the kitchen calibration scaled to the voxel, as
  ``bench_overlap.py``).

The random and GT rows pass their scores to ``pipeline.register(..., scores=...)``; everything else is the
pipeline's own code.

Scoring, against ``gt_poses.txt``: errors of each *registered* scan relative to the registered scan from which
the most registered scans are within tolerance (the pipeline's anchor, unless it sits in a misplaced group); within
tolerance = 5° / 0.2 m (kitchen) or 1° / 1 mm (bunny), as
``bench_pipeline.py``; kitchen registration recall (``evaluate.registration_recall``, 0.2 m) counted over
*all* gt.log pairs among the 9 fragments, a pair with an unregistered scan counting as missed. Times are
``RunResult.timings`` (features + global graph + pairwise + sync; scans already loaded), wall clock; CPU s is
the process CPU time of the run (all threads), less sensitive to other jobs on the machine. "flagged (of
the misplaced)": registered scans the run doubts (any reason of ``RunResult.flags``), and how many of the
registered scans outside tolerance are among them. Random rows: the mean over seeds of every column (errors are
over each run's registered scans only), ranges in brackets.

``--sim-rooms R``: the real scenes have 9 and 10 scans, so "≤ 40 % of the pairs" means k = 2–3 there; the
paper's claim is about 3DMatch scenes of ~54 scans and k = 10. These rows run that setting on R simulated
rooms of ``--sim-scans`` scans (``data_tools.simulate``, a dataset seed no head was trained or selected on),
scored as the kitchen (``sim_scene``), with one exhaustive row (the learned-weights one would register the same pairs).

``--steps`` (with ``--sim-rooms``): three rows a room instead, default ``Config`` (VLAD codebook)
with ``workers=2``: top-k (the first of ``--ks``) with the front end's steps 2-4 (refine, loops, retry, groups: the
default), the same graph with them off, and the exhaustive graph with them off. Besides recall, it counts the
pairs that got *global* registration (FPFH matching + estimator: the top-k graph with its bridges, every
pair the retries tried, and each weak group registered whole) and, separately, the pairs loop closure tried and
closed by ICP from the synchronized poses, which are not global registrations. ``--set KEY=VALUE`` overrides a
``Config`` field in all three rows (e.g. ``descriptor=learned``).
"""

from __future__ import annotations

import argparse
import itertools
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_3dmatch, when imported from elsewhere

from bench_3dmatch import parse_overrides  # noqa: E402

from data_tools.gt_overlap import overlap_matrix, relative_params  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402
from data_tools.simulate import make_training_scene  # noqa: E402
from sghr_gtsam import pipeline  # noqa: E402
from sghr_gtsam.config import Config  # noqa: E402
from sghr_gtsam.evaluate import fragment_id, registration_recall, scan_errors  # noqa: E402
from sghr_gtsam.features.local import default_voxel  # noqa: E402
from sghr_gtsam.graph import bridge_components, top_k_edges  # noqa: E402
from sghr_gtsam.io.poses import read_gt_info, read_gt_log, read_gt_overlap, read_poses  # noqa: E402
from sghr_gtsam.scene import load_scene  # noqa: E402
from sghr_gtsam.se3 import inv_T  # noqa: E402
from sghr_gtsam.types import InputError  # noqa: E402

DATA = data_root()
# scene: (scan folder, GT folder, max rotation deg, max translation, unit name, unit scale for printing)
SCENES = {
    "kitchen": ("kitchen", "kitchen/gt", 5.0, 0.2, "m", 1.0),
    "bunny": ("bunny", "bunny", 1.0, 0.001, "mm", 1000.0),
}
SIM_SEED = 2
"""Dataset seed of the simulated rooms: the shipped head trained on seed 0, bench_overlap --sim uses seed 1."""


def gt_overlap(name: str, data: Path, names: list[str], scans: list[np.ndarray]) -> np.ndarray:
    """GT overlap matrix in the order of ``names`` (diagonal 1)."""
    n = len(names)
    if name == "kitchen":
        log = read_gt_overlap(data / "kitchen" / "gt" / "gt_overlap.log")
        ids = [fragment_id(s) for s in names]
        G = np.eye(n)
        for a, b in itertools.combinations(range(n), 2):
            G[a, b] = G[b, a] = log[tuple(sorted((ids[a], ids[b])))]
        return G
    gt_names, gt_poses = read_poses(data / SCENES[name][1] / "gt_poses.txt")
    poses = gt_poses[[gt_names.index(s) for s in names]]
    radius, grid = relative_params(default_voxel(scans))
    G = overlap_matrix(scans, poses, radius, grid, mode="mean")
    np.fill_diagonal(G, 1.0)
    return G


def random_scores(n: int, seed: int) -> np.ndarray:
    S = np.random.default_rng(seed).uniform(size=(n, n))
    return np.triu(S, 1) + np.triu(S, 1).T + np.eye(n)


def run_row(scans, config: Config, scores: np.ndarray | None) -> pipeline.RunResult:
    """One ``register`` run; ``scores`` given: they replace the global-feature scores for this run."""
    return pipeline.register(scans, config, log=lambda m: None, scores=scores)


def score_run(res: pipeline.RunResult, gt: np.ndarray, max_deg: float, max_t: float, scene: Scene) -> dict:
    reg = res.registered
    # Errors relative to the reference scan that has the most registered scans within tolerance: measured
    # from the pipeline's anchor alone, an anchor inside a misplaced group would make every right scan wrong.
    best = max(
        ((scan_errors(res.names, res.poses, gt, reference=r), r) for r in reg),
        key=lambda e: int(np.sum(e[0].within(max_deg, max_t)[reg])),
    )[0]
    rot, trans = best.rotation_deg[reg], best.translation[reg]
    doubted = set().union(*res.flags.values())
    row = {
        "pairs": res.graph.num_edges,
        "n": len(res.names),
        "registered": len(reg),
        "within": int(np.sum((rot <= max_deg) & (trans <= max_t))),
        "rot_mean": float(rot.mean()),
        "rot_max": float(rot.max()),
        "t_mean": float(trans.mean()),
        "t_max": float(trans.max()),
        "total": sum(res.timings.get(s, 0.0) for s in ("features", "global_graph", "pairwise", "sync")),
        "pairwise": res.timings.get("pairwise", 0.0),
        "unregistered": res.unregistered,
        "misplaced": len(reg) - int(np.sum((rot <= max_deg) & (trans <= max_t))),
        "flagged": sum(res.names[k] in doubted for k in reg),
        "caught": sum(res.names[k] in doubted for k, r, t in zip(reg, rot, trans) if r > max_deg or t > max_t),
    }
    if scene.recall is not None:
        row["recalled"], row["recall_total"] = scene.recall(res), scene.recall_total
    return row


def fmt_row(scene_unit: float, label: str, k: str, rows: list[dict], n_all: int, has_recall: bool) -> str:
    def mean(key: str) -> float:
        return float(np.mean([r[key] for r in rows]))

    def span(key: str, f: str = "d") -> str:
        vals = [r[key] for r in rows]
        lo, hi = min(vals), max(vals)
        return f"{lo:{f}}" if lo == hi else f"{np.mean(vals):.1f} ({lo:{f}}–{hi:{f}})"

    pairs = span("pairs")
    cells = [label, k, f"{pairs} ({100 * mean('pairs') / n_all:.0f} %)", f"{span('registered')} / {span('within')}"]
    if has_recall:
        cells.append(f"{span('recalled')}/{rows[0]['recall_total']} = {mean('recalled') / rows[0]['recall_total']:.3f}")
    cells += [
        f"{mean('rot_mean'):.3f} / {mean('rot_max'):.3f}",
        f"{scene_unit * mean('t_mean'):.3f} / {scene_unit * mean('t_max'):.3f}",
        f"{mean('total'):.2f}",
        f"{mean('cpu'):.2f}",
        f"{mean('pairwise'):.2f}",
        f"{span('flagged')} ({span('caught')} of {span('misplaced')})",
    ]
    unreg = sorted({u for r in rows for u in r["unregistered"]})
    cells.append(", ".join(u.rsplit(".", 1)[0] for u in unreg) or "-")
    return "| " + " | ".join(cells) + " |"


@dataclass
class Scene:
    """A scene to benchmark: its scans, GT poses and overlaps, tolerance, units and recall rule."""

    name: str
    scans: list[pipeline.Scan]
    gt: np.ndarray  # (N, 4, 4) in the order of scans
    overlap: np.ndarray  # (N, N) GT overlap, diagonal 1
    max_deg: float
    max_t: float
    unit: str
    scale: float
    recall: Callable[[pipeline.RunResult], int] | None = None  # gt pairs recalled by a run
    recall_total: int = 0


def real_scene(name: str, data: Path) -> Scene:
    folder, gt_dir, max_deg, max_t, unit, scale = SCENES[name]
    scans, _ = load_scene(data / folder, Config(), log=lambda m: None)
    names = [s.name for s in scans]
    gt_names, gt_poses = read_poses(data / gt_dir / "gt_poses.txt")
    scene = Scene(
        name,
        scans,
        gt_poses[[gt_names.index(s) for s in names]],
        gt_overlap(name, data, names, [s.read()[0] for s in scans]),
        max_deg,
        max_t,
        unit,
        scale,
    )
    if (data / gt_dir / "gt.log").exists():
        gt_log, gt_info = read_gt_log(data / gt_dir / "gt.log"), read_gt_info(data / gt_dir / "gt.info")
        ids = set(fragment_id(s) for s in names)
        scene.recall_total = sum(1 for a, b in gt_log if abs(a - b) > 1 and a in ids and b in ids)
        scene.recall = lambda res: int(
            registration_recall(
                [fragment_id(res.names[k]) for k in res.registered], res.poses[res.registered], gt_log, gt_info
            ).recalled.sum()
        )
    return scene


def sim_scene(index: int, n_scans: int) -> Scene:
    """A simulated room (``data_tools.simulate``, dataset seed ``SIM_SEED``: never trained on) of ``n_scans``
    scans, scored as the kitchen: 5° / 0.2 m, and a 3DMatch-style recall over the pairs with GT overlap > 0.3
    and |i − j| > 1 (gt.log's selection), recalled when the RMS displacement of the second scan's points
    under the estimated against the GT relative pose is ≤ 0.2 m (what gt.info's quadratic form approximates)."""
    room = make_training_scene("room", n_scans, [SIM_SEED, index])
    scans = [pipeline.Scan(f"scan_{k:03d}", P) for k, P in enumerate(room.scans)]
    scene = Scene(f"simulated room {index}", scans, room.poses, room.overlap, 5.0, 0.2, "m", 1.0)
    pairs = [(a, b) for a, b in itertools.combinations(range(n_scans), 2) if b - a > 1 and room.overlap[a, b] > 0.3]
    sample = [
        P[np.random.default_rng(k).choice(len(P), min(len(P), 2000), replace=False)] for k, P in enumerate(room.scans)
    ]

    def recall(res: pipeline.RunResult) -> int:
        placed = set(res.registered)
        hits = 0
        for a, b in pairs:
            if a in placed and b in placed:
                d = (inv_T(res.poses[a]) @ res.poses[b]) - (inv_T(room.poses[a]) @ room.poses[b])
                hits += np.sqrt(np.mean(np.sum((sample[b] @ d[:3, :3].T + d[:3, 3]) ** 2, axis=1))) <= 0.2
        return hits

    scene.recall, scene.recall_total = recall, len(pairs)
    return scene


def bench_scene(scene: Scene, ks: list[int], seeds: int, exhaustive_learned: bool = True) -> None:
    name, scans, gt, G = scene.name, scene.scans, scene.gt, scene.overlap
    max_deg, max_t, unit, scale = scene.max_deg, scene.max_t, scene.unit, scene.scale
    n = len(scans)
    n_all = n * (n - 1) // 2
    has_recall = scene.recall is not None

    # (label, k, global_feature, scores maker or None); the scores maker takes a seed
    plan: list[tuple[str, int, str, object]] = [("exhaustive, VLAD weights (default)", n - 1, "vlad", None)]
    if exhaustive_learned:
        plan.append(("exhaustive, learned weights", n - 1, "learned", None))
    for k in ks:
        plan += [
            ("learned head", k, "learned", None),
            ("VLAD codebook", k, "vlad", None),
            (f"random scores (mean of {seeds} seeds)", k, "vlad", "random"),
            ("GT overlap (upper reference)", k, "vlad", "gt"),
        ]

    try:  # warm-up (imports, torch); two scans that do not overlap are fine for that
        pipeline.register(scans[:2], Config(record=False, global_feature="learned"), log=lambda m: None)
    except InputError:
        pass
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    lines = []
    for label, k, feature, maker in plan:
        config = Config(k=k, global_feature=feature, record=False)
        if maker == "random":
            variants = [(random_scores(n, s), f"random scores, seed {s}") for s in range(seeds)]
        elif maker == "gt":
            variants = [(G, "GT overlap")]
        else:
            variants = [(None, feature)]
        rows = []
        for scores, kind in variants:
            cpu0 = time.process_time()
            try:
                res = run_row(scans, config, scores)
            except InputError as e:
                print(f"  {label} k={k} ({kind}) failed: {e}", file=sys.stderr)
                continue
            rows.append(score_run(res, gt, max_deg, max_t, scene))
            rows[-1]["cpu"] = time.process_time() - cpu0
            r = rows[-1]
            print(
                f"  {name} {label} k={k} [{kind}]: {r['pairs']} pairs, {r['registered']} reg, "
                f"{r['within']} within, rot max {r['rot_max']:.3f}, t max {r['t_max']:.4g}, "
                f"{r['total']:.1f} s",
                file=sys.stderr,
                flush=True,
            )
        k_label = f"{k} (= N−1)" if k >= n - 1 else str(k)
        lines.append(
            fmt_row(scale, label, k_label, rows, n_all, has_recall)
            if rows
            else f"| {label} | {k_label} | every run failed |"
        )
    load1 = os.getloadavg()
    print(
        f"\n#### {name}: {n} scans, {n_all} pairs in the exhaustive graph; tolerance {max_deg:g}° / "
        f"{scale * max_t:g} {unit}; load average {load0[0]:.1f} at start, {load1[0]:.1f} at end "
        f"({os.cpu_count()} cores); {time.perf_counter() - t0:.0f} s for the table\n"
    )
    head = ["graph (scores)", "k", "pairs (% of all)", "registered / within tol."]
    if has_recall:
        head.append("registration recall")
    head += [
        "rot. err. mean / worst (°)",
        f"trans. err. mean / worst ({unit})",
        "time s",
        "CPU s",
        "pairwise s",
        "flagged (of the misplaced)",
        "unregistered (random: union over seeds)",
    ]
    print("| " + " | ".join(head) + " |")
    print("|---|---|" + "---:|" * (len(head) - 3) + "---|")
    for line in lines:
        print(line)


STEPS_PLAN = {
    "on": ("top-k + steps 2-4 (default)", False, True),
    "off": ("top-k, steps 2-4 off", False, False),
    "exhaustive": ("exhaustive, steps 2-4 off", True, False),
}
"""row name: (label, exhaustive, steps 2-4 on) of the ``--steps`` rows."""


def global_pairs(res: pipeline.RunResult, k: int, connect: bool = True) -> int:
    """Pairs the run registered globally: its top-k graph (recomputed from ``res.scores`` exactly as
    ``pipeline.register`` builds it, bridges included), the pairs the retries tried, and one for each weak group
    registered whole (a merged group onto the merged rest)."""
    top_k = top_k_edges(res.scores, k)
    if connect:
        top_k = bridge_components(top_k, res.scores)
    return len(top_k) + res.densify.get("retry_tried", 0) + res.densify.get("groups_tried", 0)


def bench_steps(scene: Scene, k: int, rows: list[str], overrides: dict | None = None) -> None:
    """Top-k with and without steps 2-4 against the exhaustive graph without them (``rows`` of
    ``STEPS_PLAN``), ``overrides`` (``Config`` fields) in every row; each row is printed as soon as it is measured
    (the exhaustive one takes long)."""
    n = len(scene.scans)
    n_all = n * (n - 1) // 2
    try:  # warm-up (imports, torch); two scans that do not overlap are fine for that
        pipeline.register(scene.scans[:2], Config(record=False, workers=1, k=1), log=lambda m: None)
    except InputError:
        pass
    t0 = time.perf_counter()
    print(
        f"\n#### {scene.name}: {n} scans, {n_all} pairs; tolerance {scene.max_deg:g}° / {scene.max_t:g} m; "
        f"load average {os.getloadavg()[0]:.1f} at start ({os.cpu_count()} cores)"
        + "".join(f"; {key}={value}" for key, value in (overrides or {}).items())
        + "\n"
    )
    print(
        "| graph | k | global registrations (% of all pairs) | retry registered / tried | groups moved / tried "
        "(edges) | loops closed / tried (ICP) | refined / tried | kept edges | registered / within tol. "
        "| registration recall | rot. err. mean / worst (°) | trans. err. mean / worst (m) | wall s "
        "| CPU s (this process) | flagged (of the misplaced) | unregistered |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|", flush=True)
    for row in rows:
        label, exhaustive, on = STEPS_PLAN[row]
        kk = n - 1 if exhaustive else k
        config = Config(
            **{
                **(overrides or {}),
                "k": kk,
                "record": False,
                "workers": 2,
                "refine": on,
                "loops": on,
                "retry": on,
                "groups": on,
            }
        )
        w0, cpu0 = time.perf_counter(), time.process_time()
        res = run_row(scene.scans, config, None)
        wall, cpu = time.perf_counter() - w0, time.process_time() - cpu0
        r = score_run(res, scene.gt, scene.max_deg, scene.max_t, scene)
        d = res.densify
        g = global_pairs(res, kk, config.connect)
        kept = int(np.sum(res.sync.weights > 0))
        unreg = ", ".join(u.rsplit(".", 1)[0] for u in r["unregistered"]) or "-"
        print(
            f"| {label} | {kk} | {g} ({100 * g / n_all:.0f} %) | {d.get('retry_registered', 0)}/"
            f"{d.get('retry_tried', 0)} | {d.get('groups_moved', 0)}/{d.get('groups_tried', 0)} "
            f"({d.get('group_edges', 0)}) | {d.get('loops_closed', 0)}/{d.get('loops_tried', 0)} "
            f"| {d.get('refined', 0)}/{d.get('refine_tried', 0)} | {kept} | {r['registered']} / {r['within']} "
            f"| {r['recalled']}/{r['recall_total']} = {r['recalled'] / r['recall_total']:.3f} "
            f"| {r['rot_mean']:.3f} / {r['rot_max']:.3f} | {r['t_mean']:.3f} / {r['t_max']:.3f} | {wall:.0f} "
            f"| {cpu:.0f} | {r['flagged']} ({r['caught']} of {r['misplaced']}) | {unreg} |",
            flush=True,
        )
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end; {time.perf_counter() - t0:.0f} s for the table")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--scenes", nargs="+", default=list(SCENES), choices=list(SCENES))
    ap.add_argument("--ks", nargs="+", type=int, default=None, help="default 2 3 4; 10 with --steps")
    ap.add_argument("--random-seeds", type=int, default=5)
    ap.add_argument(
        "--sim-rooms",
        type=int,
        nargs="+",
        default=[],
        help="instead of the real scenes: these simulated rooms (indices; the paper's scale)",
    )
    ap.add_argument("--sim-scans", type=int, default=50, help="scans per simulated room (default 50)")
    ap.add_argument(
        "--steps",
        nargs="*",
        choices=list(STEPS_PLAN),
        default=None,
        help="with --sim-rooms: top-k with/without steps 2-4 against exhaustive; no value: all three rows",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="with --steps: override a Config field in every row (repeatable)",
    )
    args = ap.parse_args(argv)
    if args.set and args.steps is None:
        ap.error("--set needs --steps")
    if args.steps is not None:
        if not args.sim_rooms:
            ap.error("--steps needs --sim-rooms")
        for index in args.sim_rooms:
            bench_steps(
                sim_scene(index, args.sim_scans),
                (args.ks or [10])[0],
                args.steps or list(STEPS_PLAN),
                parse_overrides(args.set, Config),
            )
        return 0
    args.ks = args.ks or [2, 3, 4]
    if args.sim_rooms:
        for index in args.sim_rooms:  # one exhaustive row: the learned-weights one registers the same 1225 pairs
            bench_scene(sim_scene(index, args.sim_scans), args.ks, args.random_seeds, exhaustive_learned=False)
        return 0
    if not (args.data / "MANIFEST.md").is_file():
        print(f"real data not found at {args.data} (set SGHR_DATA)")
        return 2
    for name in args.scenes:
        bench_scene(real_scene(name, args.data), args.ks, args.random_seeds)
    return 0


if __name__ == "__main__":
    sys.exit(main())
