"""Robustness to outlier edges: every synchronization method on pose graphs of the 8 real 3DMatch test scenes,
or (``--scenes gen200 gen1000``) of generated buildings of that many scans.

Graphs: ``data_tools.outlier_graphs.make_graph`` (top-10 GT-overlap graph, inliers with 2° / 5 cm noise, a
fraction ρ of edges replaced by ``random`` or ``structured`` outliers; see that module); a generated
building (``data_tools.building``) is drawn anew for every seed, with 3DMatch-like gt.log pairs and gt.info.
Methods: the project's ``synchronize`` for every entry of ``sghr_gtsam.sync.METHODS`` (the IRLS ones — history and the
paper's ablations constant g and no history — with both reweightings, ``authors`` and ``paper``, and the
default robust polish; ``history/authors`` also with the other polishes and on graphs whose initial weight
leaves out ``s`` or ``r``; ``spectral`` and ``lm`` as they are), every baseline of
``sghr_gtsam.sync.baselines`` and the oracle (gtsam LM told the inlier edges). HARA and LITS have no public
code and are not run.

Scores per run (one scene, one seed): the paper's registration recall over the scene's 3DMatch ``gt.log``
pairs with |i − j| > 1 (``evaluate.registration_recall``), the recall over all node pairs (5° / 0.2 m, which sees
a group of scans placed wrong where gt.log has few pairs), and the mean and median rotation error of the same
pairs; each averaged over scenes and seeds. Seconds: wall time of the method per scene, averaged over all runs.
At ρ = 0 both kinds are the same graph (the generator's inlier stream does not depend on the kind), so it is
run once and reported under both.

BLAS threads are set to 1 unless OPENBLAS_NUM_THREADS / OMP_NUM_THREADS is already set (tiny dense blocks;
a multithreaded BLAS on a busy 2-core machine spends its time synchronising threads); ``--jobs`` runs
graphs in parallel processes instead.

Run from the repository root (installed, or with ``PYTHONPATH=.``):
``python benchmarks/bench_robustness.py [--quick] [--seeds 5] [--first-seed 0] [--ratios 0 0.1 ...] [--methods ...]
[--kinds random structured] [--scenes gen200 ...] [--noisy-overlap] [--jobs 2] [--records runs.jsonl]``; instead of the
methods' tables, ``--identifiability``, ``--consensus`` or ``--disputes`` print what the graphs themselves say (each
function's doc)."""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", os.environ.get("OMP_NUM_THREADS", "1"))
os.environ.setdefault("OMP_NUM_THREADS", "1")  # open3d's OpenMP, same reason

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from dataclasses import asdict, dataclass, replace  # noqa: E402
from multiprocessing import Pool  # noqa: E402

import numpy as np  # noqa: E402

from benchmarks._results import save  # noqa: E402
from data_tools.outlier_graphs import GENERATED, KINDS, SCENES, ground_truth, make_graph  # noqa: E402
from sghr_gtsam.evaluate import registration_recall  # noqa: E402
from sghr_gtsam.io.atomic import atomic_write  # noqa: E402
from sghr_gtsam.se3 import inv_T, relative_errors  # noqa: E402
from sghr_gtsam.sync import METHODS, POLISHES, synchronize  # noqa: E402
from sghr_gtsam.sync.baselines import BASELINES, oracle  # noqa: E402
from sghr_gtsam.sync.consensus import MAX_DEG, consistent_edges, placement_support, translation_tolerance  # noqa: E402
from sghr_gtsam.sync.cycles import credibility  # noqa: E402
from sghr_gtsam.sync.irls import REWEIGHTS  # noqa: E402
from sghr_gtsam.types import PoseGraph, SyncResult  # noqa: E402

RATIOS = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7)
ALL_PAIRS_DEG, ALL_PAIRS_M = 5.0, 0.2
"""All-pairs recall: a node pair is right when its relative pose is within these of the GT one. It sees a
group of scans placed wrong even where gt.log has few pairs."""
IRLS_METHODS = ("history", "constant", "current")  # the METHODS entries that take a reweighting

Runner = Callable[[PoseGraph, np.ndarray], SyncResult]  # (graph, outlier mask) -> result


def _project(method: str, reweight: str = "authors", polish: str = "loops") -> Runner:
    return lambda graph, _: synchronize(graph, method=method, reweight=reweight, polish=polish)


def _baseline(name: str) -> Runner:
    return lambda graph, _: BASELINES[name](graph)


WEIGHT_ABLATIONS = {"r": "history/authors, w0 = r (no s)", "s": "history/authors, w0 = s (no r)"}
"""Rows that run the default on graphs whose initial weights leave out the overlap score or the inlier count."""


def all_methods() -> dict[str, Runner]:
    """Every method of the table, by row name, in the table's order. Rows named in ``WEIGHT_ABLATIONS`` run
    on graphs generated with the other initial weight (``run_graph``)."""
    methods: dict[str, Runner] = {}
    for method in IRLS_METHODS:
        for reweight in REWEIGHTS:
            methods[f"{method}/{reweight}"] = _project(method, reweight)
    for polish in POLISHES:
        if polish != "loops":
            methods[f"history/authors, polish {polish}"] = _project("history", "authors", polish)
    for name in WEIGHT_ABLATIONS.values():
        methods[name] = _project("history")
    for method in METHODS:
        if method not in IRLS_METHODS:
            methods[method] = _project(method, polish="none")
    for name in BASELINES:
        methods[name] = _baseline(name)
    methods["oracle"] = lambda graph, outlier: oracle(graph, ~outlier)
    return methods


@dataclass
class Run:
    """One method on one graph."""

    method: str
    scene: str
    seed: int
    kind: str
    ratio: float
    recall: float
    rot_mean_deg: float
    rot_median_deg: float
    seconds: float
    all_pairs: float = float("nan")  # recall over every node pair (ALL_PAIRS_DEG / ALL_PAIRS_M)


def run_graph(task: tuple[str, int, str, float, bool, list[str]]) -> list[Run]:
    """Every method in ``names`` on one generated graph."""
    scene, seed, kind, ratio, noisy_overlap, names = task
    methods = all_methods()
    gt = ground_truth(scene, seed)
    graphs = {
        w: make_graph(scene, ratio, kind, seed, noisy_overlap=noisy_overlap, weight=w)
        for w in ["s*r", *(w for w, row in WEIGHT_ABLATIONS.items() if row in names)]
    }
    runs = []
    for name in names:
        weight = next((w for w, row in WEIGHT_ABLATIONS.items() if row == name), "s*r")
        graph, _, outlier = graphs[weight]
        start = time.perf_counter()
        result = methods[name](graph, outlier)
        seconds = time.perf_counter() - start
        recall = registration_recall(gt.ids, result.poses, gt.gt_log, gt.gt_info)
        index = {f: k for k, f in enumerate(gt.ids)}
        a = np.array([index[p] for p, _ in recall.pairs])
        b = np.array([index[q] for _, q in recall.pairs])
        estimated = inv_T(result.poses[a]) @ result.poses[b]
        rot, _ = relative_errors(estimated, np.stack([gt.gt_log[p] for p in recall.pairs]))
        runs.append(
            Run(
                name,
                scene,
                seed,
                kind,
                ratio,
                recall.recall,
                float(rot.mean()),
                float(np.median(rot)),
                seconds,
                all_pairs_recall(result.poses, gt.poses),
            )
        )
    return runs


def right_pairs(poses: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every node pair ``a < b`` and whether its relative pose is within ``ALL_PAIRS_DEG`` / ``ALL_PAIRS_M`` of
    the truth (pairs in different parts of a result count with whatever relative pose their anchors give them)."""
    a, b = np.triu_indices(len(truth), 1)
    rot, trans = relative_errors(inv_T(poses[a]) @ poses[b], inv_T(truth[a]) @ truth[b])
    return a, b, (rot <= ALL_PAIRS_DEG) & (trans <= ALL_PAIRS_M)


def all_pairs_recall(poses: np.ndarray, truth: np.ndarray) -> float:
    """Share of all node pairs that are right (``right_pairs``)."""
    return float(np.mean(right_pairs(poses, truth)[2]))


def table_rows(
    runs: list[Run], names: list[str], kinds: list[str], ratios: list[float]
) -> list[tuple[str, str, list[str], list[list]]]:
    """Per kind: registration recall (with seconds a scene), recall over all node pairs, then mean / median rotation
    error, by method and ratio; each as (key, title, columns, rows)."""
    out = []
    for kind in kinds:
        mine = [r for r in runs if r.kind == kind]
        cell = {(r.method, r.ratio): [] for r in mine}
        for r in mine:
            cell[(r.method, r.ratio)].append(r)
        header = ["method", *(f"ρ={x:g}" for x in ratios)]
        recall, all_pairs, rotation = [], [], []
        for name in names:
            rs = [cell.get((name, x), []) for x in ratios]
            seconds = np.mean([r.seconds for group in rs for r in group]) if any(rs) else float("nan")
            recall.append(
                [name, *(f"{np.mean([r.recall for r in g]):.3f}" if g else "–" for g in rs), f"{seconds:.2f}"]
            )
            all_pairs.append([name, *(f"{np.mean([r.all_pairs for r in g]):.3f}" if g else "–" for g in rs)])
            rotation.append(
                [
                    name,
                    *(
                        f"{np.mean([r.rot_mean_deg for r in g]):.2f} / {np.mean([r.rot_median_deg for r in g]):.2f}"
                        if g
                        else "–"
                        for g in rs
                    ),
                ]
            )
        out += [
            (f"{kind}_recall", f"{kind} outliers: registration recall", [*header, "s / scene"], recall),
            (
                f"{kind}_all_pairs",
                f"{kind} outliers: recall over all node pairs ({ALL_PAIRS_DEG:g}° / {ALL_PAIRS_M:g} m)",
                header,
                all_pairs,
            ),
            (
                f"{kind}_rotation",
                f"{kind} outliers: rotation error of the gt.log pairs, mean / median (°)",
                header,
                rotation,
            ),
        ]
    return out


def tables(runs: list[Run], names: list[str], kinds: list[str], ratios: list[float]) -> str:
    """Markdown of ``table_rows``."""
    out = []
    for _, title, columns, rows in table_rows(runs, names, kinds, ratios):
        out += [f"\n### {title}\n", "| " + " | ".join(columns) + " |", "|---|" + "---:|" * (len(columns) - 1)]
        out += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(out)


VOTES = {"w0": lambda graph: graph.weight, "credibility": credibility}
"""What a placement's support sums in ``identifiability``: the initial weights, or the default's first votes
(``cycles.credibility``: counts, heavier edges up to twice)."""


def _outvoted(graph: PoseGraph, P: np.ndarray, votes: np.ndarray) -> np.ndarray:
    """(N,) bool: with every other scan at its GT pose ``P``, a placement the scan's edges propose away from its GT
    pose has more ``votes`` than the GT pose (``consensus.placement_support``: the consensus step's agreement test)."""
    voted = replace(graph, weight=votes)
    tol = translation_tolerance(graph)
    bad = np.zeros(graph.n, dtype=bool)
    for scan in range(graph.n):
        edges = np.flatnonzero((graph.i == scan) | (graph.j == scan))
        _, support, current, right, _ = placement_support(voted, P, scan, edges, MAX_DEG, tol)
        bad[scan] = support[~right].max(initial=0.0) > current
    return bad


def identifiability(
    scenes: list[str],
    kinds: list[str],
    ratios: list[float],
    seeds: int,
    noisy_overlap: bool = False,
    vote: str = "w0",
    first_seed: int = 0,
) -> str:
    """Markdown: what the graphs themselves say, before any method runs. With every other scan at its GT
    pose, a scan is *outvoted* when a placement its edges propose, away from its GT pose, has more support
    (the ``vote`` of the agreeing edges, ``VOTES``) than the GT pose (``consensus.placement_support``: the
    consensus step's agreement test). A method that only sees the graph cannot be expected to place an
    outvoted scan right; what is left is the share of gt.log pairs (|i − j| > 1) with neither scan outvoted,
    and the share of all node pairs the oracle gets right with neither scan outvoted. An estimate, not a bound:
    a method's partners are not all at their GT poses, and its evidence is not one scan's edges alone."""
    out = ["| kind | " + " | ".join(f"ρ={x:g}" for x in ratios) + " |", "|---|" + "---:|" * len(ratios)]
    for kind in kinds:
        cells = []
        for ratio in ratios:
            outvoted, log_left, all_left = [], [], []
            for scene in scenes:
                for seed in range(first_seed, first_seed + seeds):
                    gt = ground_truth(scene, seed)
                    index = {f: k for k, f in enumerate(gt.ids)}
                    pairs = [(index[a], index[b]) for a, b in gt.gt_log if a in index and b in index and abs(a - b) > 1]
                    graph, P, outlier = make_graph(scene, ratio, kind, seed, noisy_overlap=noisy_overlap)
                    bad = _outvoted(graph, P, VOTES[vote](graph))
                    outvoted.append(bad.mean())
                    log_left.append(np.mean([not (bad[a] or bad[b]) for a, b in pairs]))
                    a, b, ok = right_pairs(oracle(graph, ~outlier).poses, P)
                    all_left.append(np.mean(ok & ~bad[a] & ~bad[b]))
            cells.append(f"{np.mean(outvoted):.3f} / {np.mean(log_left):.3f} / {np.mean(all_left):.3f}")
        out.append(f"| {kind} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def _placed_right(poses: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(N,) bool: scans whose relative pose to at least half of the other scans is right (``right_pairs``)."""
    a, b, ok = right_pairs(poses, truth)
    right = np.bincount(a, ok, len(truth)) + np.bincount(b, ok, len(truth))
    return right >= (len(truth) - 1) / 2


def _per_cell(
    per_graph: Callable[[tuple[str, int, str, float, bool]], object],
    scenes: list[str],
    kinds: list[str],
    ratios: list[float],
    seeds: int,
    noisy_overlap: bool,
    first_seed: int,
    jobs: int,
) -> list[tuple[tuple[str, float], list]]:
    """``per_graph`` of every scene and seed, over ``jobs`` processes, grouped by (kind, ratio)."""
    cells = [(kind, ratio) for kind in kinds for ratio in ratios]
    with Pool(jobs) as pool:
        return [
            (
                cell,
                pool.map(
                    per_graph,
                    [
                        (scene, seed, *cell, noisy_overlap)
                        for scene in scenes
                        for seed in range(first_seed, first_seed + seeds)
                    ],
                ),
            )
            for cell in cells
        ]


def _disputed_graph(task: tuple[str, int, str, float, bool]) -> np.ndarray:
    """On one graph, the scans the default places right and ``polish robust`` wrong, then the reverse; of each,
    how many are outvoted (``_outvoted``) by counts (``cycles.credibility``), by w⁰, by both: a (2, 4) array."""
    scene, seed, kind, ratio, noisy_overlap = task
    graph, P, _ = make_graph(scene, ratio, kind, seed, noisy_overlap=noisy_overlap)
    loops = _placed_right(synchronize(graph).poses, P)
    robust = _placed_right(synchronize(graph, polish="robust").poses, P)
    by_count, by_w0 = _outvoted(graph, P, credibility(graph)), _outvoted(graph, P, graph.weight)
    return np.array(
        [
            [m.sum(), (m & by_count).sum(), (m & by_w0).sum(), (m & by_count & by_w0).sum()]
            for m in (loops & ~robust, robust & ~loops)
        ]
    )


def disputes(
    scenes: list[str],
    kinds: list[str],
    ratios: list[float],
    seeds: int,
    noisy_overlap: bool,
    first_seed: int,
    jobs: int,
) -> str:
    """Markdown: where the default (``loops``) and ``polish robust`` place a scan differently, what its edges say.
    A scan is placed right when it is right against at least half of the others (``_placed_right``); for the
    scans only one of the two places right, how many are outvoted by counts, by w⁰ and by both (``_outvoted``):
    a polish that places an outvoted scan right has kept it where it was, not followed the evidence."""
    out = [
        "| kind | ρ | right by the default only: scans / outvoted by counts / by w⁰ / by both | right by "
        "`robust` only: the same |",
        "|---|---:|---|---|",
    ]
    for (kind, ratio), rows in _per_cell(
        _disputed_graph, scenes, kinds, ratios, seeds, noisy_overlap, first_seed, jobs
    ):
        total = np.sum(rows, axis=0)
        out.append(f"| {kind} | {ratio:g} | " + " | ".join(" / ".join(map(str, row)) for row in total) + " |")
    return "\n".join(out)


def _consensus_graph(task: tuple[str, int, str, float, bool]) -> dict:
    """The default's answer, ``polish robust``'s, the oracle's and the GT poses on one graph: all-pairs and gt.log
    recall, and the edges each leaves consistent (``consensus.consistent_edges``): how many, how many of them
    outliers, their votes."""
    scene, seed, kind, ratio, noisy_overlap = task
    gt = ground_truth(scene, seed)
    graph, P, outlier = make_graph(scene, ratio, kind, seed, noisy_overlap=noisy_overlap)
    votes = {"count": np.ones(graph.num_edges), "credibility": credibility(graph), "w0": graph.weight}
    row = {}
    for name, poses in (
        ("default", synchronize(graph).poses),
        ("robust", synchronize(graph, polish="robust").poses),
        ("oracle", oracle(graph, ~outlier).poses),
        ("GT", P),
    ):
        kept = consistent_edges(graph, poses)
        row[name] = {
            "all_pairs": all_pairs_recall(poses, P),
            "wrong": int((kept & outlier).sum()),
            "gt_log": registration_recall(gt.ids, poses, gt.gt_log, gt.gt_info).recall,
            **{v: float(w[kept].sum()) for v, w in votes.items()},
        }
    return row


def consensus(
    scenes: list[str],
    kinds: list[str],
    ratios: list[float],
    seeds: int,
    noisy_overlap: bool,
    first_seed: int,
    jobs: int,
) -> str:
    """Markdown: is the truth the answer the graph's own consistency prefers? Per kind and ratio, the edges
    consistent with the default's answer, the oracle's and the GT poses, and on how many graphs the default's
    answer leaves more of them (by count, by the default's votes ``cycles.credibility``, by w⁰) than the oracle's.
    Where it does, a method that picks the answer most edges agree with cannot prefer the truth. Then, from the
    same runs, where the default's remaining gaps lie (``_gaps``)."""
    out = [
        "| kind | ρ | all pairs: default / oracle | consistent edges: default / oracle / GT | of them outliers: "
        "default / oracle / GT | graphs where the default's answer leaves more consistent than the oracle's: "
        "count / credibility / w⁰ |",
        "|---|---:|---|---|---|---|",
    ]
    cells = _per_cell(_consensus_graph, scenes, kinds, ratios, seeds, noisy_overlap, first_seed, jobs)
    for (kind, ratio), rows in cells:
        means = {
            (who, what): np.mean([r[who][what] for r in rows])
            for who in ("default", "oracle", "GT")
            for what in ("all_pairs", "count", "wrong")
        }
        more = [sum(r["default"][v] > r["oracle"][v] for r in rows) for v in ("count", "credibility", "w0")]
        out.append(
            f"| {kind} | {ratio:g} | {means['default', 'all_pairs']:.3f} / {means['oracle', 'all_pairs']:.3f} | "
            + " / ".join(f"{means[w, 'count']:.1f}" for w in ("default", "oracle", "GT"))
            + " | "
            + " / ".join(f"{means[w, 'wrong']:.1f}" for w in ("default", "oracle", "GT"))
            + " | "
            + " / ".join(map(str, more))
            + f" of {len(rows)} |"
        )
    return "\n".join(out) + "\n\n" + _gaps(cells)


def _gaps(cells: list[tuple[tuple[str, float], list[dict]]]) -> str:
    """Markdown: where the default's two remaining gaps lie (``consensus``'s rows). Its all-pairs gap to the oracle,
    and the part of it on graphs where the default's answer carries at least as many of its own votes
    (``cycles.credibility`` of the consistent edges) as the GT poses: there a better search of the default's
    objective would not find the truth. And ``polish robust``'s gt.log gain over the default on the graphs where
    it is higher, and the part of it on graphs where the default's answer carries more votes than ``robust``'s:
    there ``robust`` is ahead by an answer the graph supports less, not by a search the default missed. Each is a
    sum over the graphs with a gap (a gain), divided by the number of all graphs: a share of the cell's mean."""
    out = [
        "| kind | ρ | all pairs: default / oracle | gap to the oracle | of it where the default's answer carries "
        "≥ GT's votes | graphs with a gap: of them so | gt.log: default / `robust` | `robust`'s gain | of it "
        "where the default's answer carries more votes than `robust`'s | graphs where `robust` gains: of them so |",
        "|---|---:|---|---:|---:|---|---|---:|---:|---|",
    ]
    for (kind, ratio), rows in cells:
        n = len(rows)
        gap = np.array([r["oracle"]["all_pairs"] - r["default"]["all_pairs"] for r in rows])
        held = np.array([r["default"]["credibility"] >= r["GT"]["credibility"] for r in rows])
        gain = np.array([r["robust"]["gt_log"] - r["default"]["gt_log"] for r in rows])
        preferred = np.array([r["default"]["credibility"] > r["robust"]["credibility"] for r in rows])
        lost, won = gap > 0, gain > 0
        mean = {
            (w, m): np.mean([r[w][m] for r in rows])
            for w in ("default", "robust", "oracle")
            for m in ("all_pairs", "gt_log")
        }
        out.append(
            f"| {kind} | {ratio:g} | {mean['default', 'all_pairs']:.3f} / {mean['oracle', 'all_pairs']:.3f} | "
            f"{gap[lost].sum() / n:.3f} | {gap[lost & held].sum() / n:.3f} | {lost.sum()}: "
            f"{(lost & held).sum()} | {mean['default', 'gt_log']:.3f} / {mean['robust', 'gt_log']:.3f} | "
            f"{gain[won].sum() / n:.3f} | {gain[won & preferred].sum() / n:.3f} | {won.sum()}: "
            f"{(won & preferred).sum()} |"
        )
    return "\n".join(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, default=5, help="seeds per scene (default 5)")
    parser.add_argument(
        "--first-seed",
        type=int,
        default=0,
        help="first seed (default 0); report on seeds other than those a method was developed on",
    )
    parser.add_argument("--ratios", type=float, nargs="+", default=list(RATIOS), help="outlier ratios")
    parser.add_argument("--methods", nargs="+", help="row names (default: all); see --list")
    parser.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS)
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=list(SCENES),
        metavar="SCENE",
        help="3DMatch test scenes (default: all 8) or generated buildings gen<N>, e.g. gen200 "
        "gen1000 (data_tools.building; one building per seed)",
    )
    parser.add_argument("--quick", action="store_true", help="1 seed, ratios 0 and 0.5")
    parser.add_argument(
        "--noisy-overlap",
        action="store_true",
        help="top-k by overlap + N(0, 0.1) instead of the GT overlap (make_graph's variant)",
    )
    parser.add_argument("--jobs", type=int, default=2, help="parallel processes (default 2)")
    parser.add_argument("--records", help="write every run as a JSON line to this file")
    parser.add_argument(
        "--tables-from",
        nargs="+",
        metavar="JSONL",
        help="no runs: print the tables of the --methods rows of these --records files",
    )
    parser.add_argument("--list", action="store_true", help="list the methods and exit")
    parser.add_argument(
        "--identifiability",
        action="store_true",
        help="only the table of outvoted scans and the recall they leave (only the oracle runs)",
    )
    parser.add_argument(
        "--consensus",
        action="store_true",
        help="only the tables of the edges consistent with the default's answer, the oracle's and GT, "
        "and of where the default's gaps lie",
    )
    parser.add_argument(
        "--disputes",
        action="store_true",
        help="only the table of scans the default and polish robust place differently, and "
        "whether their edges outvote them",
    )
    parser.add_argument(
        "--vote",
        choices=sorted(VOTES),
        default="w0",
        help="with --identifiability: what a placement's support sums (default w0)",
    )
    args = parser.parse_args()
    unknown = [s for s in args.scenes if s not in SCENES and not GENERATED.fullmatch(s)]
    if unknown:
        parser.error(f"unknown scenes {unknown}: the 3DMatch test scenes or gen<N>")
    names = list(all_methods())
    if args.list:
        print("\n".join(names))
        return
    if args.methods:
        unknown = sorted(set(args.methods) - set(names))
        if unknown:
            parser.error(f"unknown methods {unknown}; --list shows them")
        names = [n for n in names if n in args.methods]
    seeds, ratios = (1, [0.0, 0.5]) if args.quick else (args.seeds, sorted(args.ratios))
    if args.tables_from:
        runs = [Run(**json.loads(line)) for path in args.tables_from for line in open(path)]
        print(tables([r for r in runs if r.ratio in ratios], names, args.kinds, ratios))
        return
    graphs = (
        f"{len(args.scenes)} scenes × {seeds} seeds from {args.first_seed}, top-k by "
        f"{'noisy' if args.noisy_overlap else 'GT'} overlap"
    )
    if args.identifiability:
        print(f"outvoted scans / gt.log recall left / all pairs left, votes {args.vote}, {graphs}")
        print(
            identifiability(
                args.scenes,
                args.kinds,
                [x for x in ratios if x > 0],
                seeds,
                args.noisy_overlap,
                args.vote,
                args.first_seed,
            )
        )
        return
    if args.disputes:
        print(graphs)
        print(
            disputes(
                args.scenes,
                args.kinds,
                [x for x in ratios if x > 0],
                seeds,
                args.noisy_overlap,
                args.first_seed,
                args.jobs,
            )
        )
        return
    if args.consensus:
        print(graphs)
        print(
            consensus(
                args.scenes,
                args.kinds,
                [x for x in ratios if x > 0],
                seeds,
                args.noisy_overlap,
                args.first_seed,
                args.jobs,
            )
        )
        return

    # Ratio 0 is the same graph for both kinds: run it once, under the first kind.
    tasks = [
        (scene, seed, kind, ratio, args.noisy_overlap, names)
        for kind in args.kinds
        for ratio in ratios
        if ratio > 0 or kind == args.kinds[0]
        for scene in args.scenes
        for seed in range(args.first_seed, args.first_seed + seeds)
    ]
    start = time.perf_counter()
    runs: list[Run] = []
    with Pool(args.jobs) as pool:
        for k, batch in enumerate(pool.imap_unordered(run_graph, tasks), 1):
            runs += batch
            print(f"\r{k}/{len(tasks)} graphs, {time.perf_counter() - start:.0f} s", end="", flush=True)
    print()
    runs += [Run(**{**asdict(r), "kind": kind}) for r in runs if r.ratio == 0 for kind in args.kinds[1:]]
    if args.records:
        with atomic_write(args.records) as f:
            f.writelines(json.dumps(asdict(r)) + "\n" for r in runs)
    print(f"{graphs}, {args.jobs} processes, {time.perf_counter() - start:.0f} s")
    print(tables(runs, names, args.kinds, ratios))
    scenes = "3dmatch" if args.scenes == list(SCENES) else "_".join(args.scenes)
    tables_ = {key: (columns, rows) for key, _, columns, rows in table_rows(runs, names, args.kinds, ratios)}
    for kind in args.kinds:  # the page's table: all pairs / gt.log recall in one cell
        columns, recall = tables_[f"{kind}_recall"]
        _, all_pairs = tables_[f"{kind}_all_pairs"]
        rows = [[a[0], *(f"{x} / {y}" for x, y in zip(a[1:], r[1:-1]))] for a, r in zip(all_pairs, recall)]
        save(
            f"robustness_{scenes}_{kind}",
            rows,
            columns[:-1],
            section="Synchronization",
            title=f"{kind} outliers: recall over all node pairs (5° / 0.2 m) / the paper's gt.log recall, {graphs}",
        )


if __name__ == "__main__":
    main()
