"""Overlap report: how well each global feature's scores rank the real pairs, and how fast scoring is.

Scenes (real evaluation data, never trained on): the 3DMatch kitchen (9 fragments; GT overlap from its
``gt/gt_overlap.log``) and the Stanford bunny (10 scans; GT overlap from ``data_tools.gt_overlap`` under the
GT poses, kitchen calibration scaled to the scene's voxel: radius 0.72 voxel on a 0.24-voxel grid,
symmetric mean). Local descriptors: FPFH from ``compute_features`` at the pipeline's default voxel.

Scores compared:
- **learned head**: the shipped ``sghr_gtsam/weights/netvlad_fpfh.pth`` (trained on simulated scans only);
- **VLAD codebook**: the pipeline's default, unsupervised feature (``netvlad.codebook_features``: a k-means
  codebook of this scene's own FPFH, ``NetVLAD.from_codebook``);
- **random**: uniform random scores (mean ± std over 1000 draws);
- **GT (oracle)**: the GT overlaps themselves, the best any score can do;
- kitchen 0–5 only: the authors' NetVLAD head on their YOHO descriptors (``sghr-reference``), for scale.

Metrics: Spearman correlation of the scores with GT overlap over all pairs; for k = 3 and 5 the sparse graph
``graph.top_k_edges`` (each scan's k best partners) and the fraction of its edges whose GT overlap > 0.1.

Speed: the global feature of one scan from its descriptors (5000 of them, as the pipeline samples), and the
all-pairs scores plus top-10 graph for N = 5000 random unit features (D = 64 × 33): ``graph.top_k_graph``
(one float32 Gram matrix, top-k straight from it), ``graph.overlap_scores`` + ``graph.top_k_edges`` (the full
float64 matrix), and graph.py as of commit 5cca2b2 for comparison, each path timed once per repeat,
interleaved, medians reported with the load average; the edges of the three paths are checked to be equal.

With ``--sim DIR`` it also scores the learned head and the per-scene codebook on every scene of a simulated
cache: made with another seed than the training cache (``python -m data_tools.simulate DIR --seed 1``), these
are unseen scenes from the head's own domain, so the head against the codebook there, and again on the real
scans, separates what training achieves from what is lost between simulated and real scans.

With ``--scenes`` (home_at, hotel_uc, studyroom: full 3DMatch test scenes) it also counts, for k = 6, 10, 15, 20, the
scene's gt.log pairs (the benchmark's pairs, GT overlap >= 30 %) that each score's top-k graph proposes: a pair
never proposed is never registered, whatever the registration does.

Run from the repository root: ``python benchmarks/bench_overlap.py [--head PATH] [--sim DIR]
[--scenes home_at hotel_uc studyroom] [--no-speed | --speed-only] [--repeats R]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import spearmanr

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data_tools.gt_overlap import overlap_matrix, relative_params  # noqa: E402
from data_tools.scene_gt import data_root, log_overlaps  # noqa: E402
from sghr_gtsam.evaluate import fragment_id  # noqa: E402
from sghr_gtsam.features.local import compute_features, default_voxel  # noqa: E402
from sghr_gtsam.features.netvlad import (  # noqa: E402
    DEFAULT_HEAD,
    VladHead,
    codebook_features,
    global_features,
    load_checkpoint,
)
from sghr_gtsam.graph import gram32, overlap_scores, top_k_edges, top_k_graph  # noqa: E402
from sghr_gtsam.io.poses import read_gt_log, read_poses  # noqa: E402
from sghr_gtsam.io.scans import load_scan  # noqa: E402

DATA = data_root()
KS = (3, 5)
THRESHOLD = 0.1
RANDOM_DRAWS = 1000


def kitchen(data: Path) -> tuple[list[str], list[np.ndarray], np.ndarray]:
    names, _ = read_poses(data / "kitchen" / "gt" / "gt_poses.txt")
    G = log_overlaps(data / "kitchen" / "gt" / "gt_overlap.log", [fragment_id(n) for n in names])
    return names, [load_scan(data / "kitchen" / n) for n in names], G


def bunny(data: Path) -> tuple[list[str], list[np.ndarray], np.ndarray]:
    names, poses = read_poses(data / "bunny" / "gt_poses.txt")
    scans = [load_scan(data / "bunny" / n) for n in names]
    radius, grid = relative_params(default_voxel(scans))
    return names, scans, overlap_matrix(scans, poses, radius, grid, mode="mean")


def codebook_scores(desc: list[np.ndarray], seed: int = 0) -> np.ndarray:
    """What the pipeline's default global feature scores."""
    return overlap_scores(codebook_features(desc, seed=seed)[0])


def metrics(S: np.ndarray, G: np.ndarray) -> dict[str, float]:
    iu = np.triu_indices(len(G), 1)
    out = {"spearman": float(spearmanr(S[iu], G[iu]).statistic)}
    for k in KS:
        edges = top_k_edges(S, k)
        out[f"p@{k}"] = float(np.mean(G[edges[:, 0], edges[:, 1]] > THRESHOLD))
        out[f"e@{k}"] = len(edges)
    return out


def random_metrics(G: np.ndarray, draws: int = RANDOM_DRAWS, seed: int = 0) -> dict[str, tuple[float, float]]:
    rng = np.random.default_rng(seed)
    rows = []
    for _ in range(draws):
        S = rng.uniform(size=G.shape)
        S = np.triu(S, 1) + np.triu(S, 1).T + np.eye(len(G))
        rows.append(metrics(S, G))
    return {key: (float(np.mean([r[key] for r in rows])), float(np.std([r[key] for r in rows]))) for key in rows[0]}


def _row(name: str, m: dict) -> str:
    def cell(key: str, fmt: str) -> str:
        v = m[key]
        return f"{v[0]:{fmt}} ± {v[1]:{fmt}}" if isinstance(v, tuple) else f"{v:{fmt}}"

    parts = [cell("spearman", ".3f")]
    for k in KS:
        parts.append(f"{cell(f'p@{k}', '.2f')} ({cell(f'e@{k}', '.0f')})")
    return f"| {name} | " + " | ".join(parts) + " |"


def report_scene(
    title: str,
    names: list[str],
    desc: list[np.ndarray],
    G: np.ndarray,
    head: VladHead,
    extra: dict[str, np.ndarray] | None = None,
) -> dict[str, dict]:
    iu = np.triu_indices(len(G), 1)
    n_pairs, n_good = len(iu[0]), int((G[iu] > THRESHOLD).sum())
    results = {
        "learned head": metrics(overlap_scores(global_features(head, desc)), G),
        "VLAD codebook (pipeline now)": metrics(codebook_scores(desc), G),
        "random": random_metrics(G),
        "GT (oracle)": metrics(G, G),
    }
    for name, S in (extra or {}).items():
        results[name] = metrics(S, G)
    print(f"\n### {title}: {len(names)} scans, {n_pairs} pairs, {n_good} with GT overlap > {THRESHOLD}\n")
    print("| scores | Spearman ρ | " + " | ".join(f"top-{k}: frac. GT > {THRESHOLD} (edges)" for k in KS) + " |")
    print("|---|---:|" + "---:|" * len(KS))
    for name, m in results.items():
        print(_row(name, m))
    return results


MATCH_SCENES = {
    "home_at": "sun3d-home_at-home_at_scan1_2013_jan_1",
    "hotel_uc": "sun3d-hotel_uc-scan3",
    "studyroom": "sun3d-mit_76_studyroom-76-1studyroom2",
}
MATCH_KS = (6, 10, 15, 20)


def match_scene(data: Path, name: str) -> tuple[list[np.ndarray], np.ndarray, set[tuple[int, int]]]:
    """A full 3DMatch test scene's FPFH (fragments in ``gt_poses.txt`` order), its GT overlap matrix
    (``gt_overlap.log``) and its gt.log pairs (the benchmark's pairs: GT overlap >= 30 %)."""
    folder, gt = data / "3dmatch-scenes" / name, data / "3dmatch-test-gt" / "3DMatch" / MATCH_SCENES[name]
    names, _ = read_poses(folder / "gt_poses.txt")
    ids = {fragment_id(n): k for k, n in enumerate(names)}
    G = log_overlaps(gt / "gt_overlap.log", list(ids))
    scans = [load_scan(folder / n) for n in names]
    voxel = default_voxel(scans)
    pairs = {tuple(sorted((ids[a], ids[b]))) for a, b in read_gt_log(gt / "gt.log")}
    return [compute_features(P, voxel).fpfh for P in scans], G, pairs


def report_match_scene(
    name: str, desc: list[np.ndarray], G: np.ndarray, pairs: set[tuple[int, int]], head: VladHead
) -> None:
    """The share of the scene's gt.log pairs that each score's top-k graph proposes (a pair never proposed is
    never registered), for k in ``MATCH_KS``, with the graph's size and its edges between scans that barely
    overlap (GT overlap below ``THRESHOLD``)."""
    n = len(G)
    scores = {
        "VLAD codebook (pipeline now)": codebook_scores(desc),
        "learned head": overlap_scores(global_features(head, desc)),
        "GT overlap (oracle)": G,
    }
    print(f"\n### {name}: {n} fragments, {n * (n - 1) // 2} pairs, {len(pairs)} gt.log pairs\n")
    print(
        "| scores | "
        + " | ".join(
            f"top-{k}: gt.log pairs proposed (edges, % of all pairs; edges of GT overlap < {THRESHOLD})"
            for k in MATCH_KS
        )
        + " |"
    )
    print("|---|" + "---:|" * len(MATCH_KS))
    for label, S in scores.items():
        cells = []
        for k in MATCH_KS:
            edges = {tuple(e) for e in np.sort(top_k_edges(S, k), axis=1).tolist()}
            hit = len(pairs & edges)
            blind = sum(G[i, j] < THRESHOLD for i, j in edges)
            cells.append(
                f"{hit}/{len(pairs)} = {hit / len(pairs):.3f} ({len(edges)}, {len(edges) / (n * (n - 1) / 2):.0%}; "
                f"{blind} below {THRESHOLD})"
            )
        print(f"| {label} | " + " | ".join(cells) + " |")


def previous_scores_top_k(F: np.ndarray, k: int) -> np.ndarray:
    """graph.py as of commit 5cca2b2 (2.05 s at N = 5000): numpy ``F32 @ F32.T``, clip, float64 scores, then
    ``np.partition`` on a float64 copy and ``np.unique(axis=0)``; kept here to time it under the same load."""
    F32 = np.asarray(F, dtype=np.float32)
    S = (np.clip(F32 @ F32.T, -1.0, 1.0).astype(np.float64) + 1.0) / 2.0
    neg = -S
    np.fill_diagonal(neg, np.inf)
    kth = np.partition(neg, k - 1, axis=1)[:, k - 1 : k]
    better, ties = neg < kth, neg == kth
    need = k - better.sum(axis=1)
    chosen = better | ties
    crowded = np.flatnonzero(ties.sum(axis=1) > need)
    chosen[crowded] = better[crowded] | (ties[crowded] & (np.cumsum(ties[crowded], axis=1) <= need[crowded, None]))
    return np.unique(np.sort(np.stack(np.nonzero(chosen), axis=1), axis=1), axis=0)


def graph_speed(D: int, n: int = 5000, k: int = 10, repeats: int = 5) -> None:
    """Scores + top-k for ``n`` random unit features: the paths interleaved in each repeat; medians."""
    rng = np.random.default_rng(0)
    F = rng.normal(size=(n, D))
    F /= np.linalg.norm(F, axis=1, keepdims=True)
    top_k_graph(F[:100], k)  # warm-up (BLAS threads, torch)
    times: dict[str, list[float]] = {key: [] for key in ("gram", "fused", "fused_full", "scores", "topk", "previous")}
    load_before = os.getloadavg()[0]
    for _ in range(repeats):
        t0 = time.perf_counter()
        gram32(F)
        t1 = time.perf_counter()
        fused, _ = top_k_graph(F, k)
        t2 = time.perf_counter()
        top_k_graph(F, k, full_scores=True)
        t2b = time.perf_counter()
        S = overlap_scores(F)
        t3 = time.perf_counter()
        edges = top_k_edges(S, k)
        t4 = time.perf_counter()
        del S
        previous = previous_scores_top_k(F, k)
        t5 = time.perf_counter()
        for key, dt in zip(times, (t1 - t0, t2 - t1, t2b - t2, t3 - t2b, t4 - t3, t5 - t4)):
            times[key].append(dt)
    load_after = os.getloadavg()[0]
    same = np.array_equal(fused, edges) and np.array_equal(fused, previous)
    full = np.array(times["scores"]) + np.array(times["topk"])

    def cell(values) -> str:
        return f"{np.median(values):.2f} s ({np.min(values):.2f}–{np.max(values):.2f})"

    print(
        f"\nN = {n} scans, D = {D}, k = {k}, {repeats} repeats, median (min–max); load average "
        f"{load_before:.1f} before, {load_after:.1f} after; {len(fused)} edges, same for all three paths: {same}\n"
    )
    print("| what | time | target |")
    print("|---|---:|---:|")
    print(f"| `graph.gram32`: float32 Gram matrix (ssyrk + tiled mirror) | {cell(times['gram'])} | |")
    print(
        f"| **`graph.top_k_graph(F, {k})`: scores + top-k, fused (Gram + torch.topk + exact ties)** | "
        f"**{cell(times['fused'])}** | ≤ 1 s |"
    )
    print(
        f"| `graph.top_k_graph(F, {k}, full_scores=True)`: the same plus the full float64 matrix | "
        f"{cell(times['fused_full'])} | |"
    )
    print(f"| `graph.overlap_scores(F)`: full float64 matrix | {cell(times['scores'])} | |")
    print(f"| `graph.top_k_edges(scores, {k})` on that matrix | {cell(times['topk'])} | |")
    print(f"| overlap_scores + top_k_edges | {cell(full)} | ≤ 1 s |")
    print(f"| graph.py before (commit 5cca2b2): scores + top-k | {cell(times['previous'])} | |")


def speed(head: VladHead, desc: list[np.ndarray], n: int = 5000, repeats: int = 5) -> None:
    D = head.centroids.size
    d5000 = [d if len(d) >= 5000 else np.concatenate([d] * (5000 // len(d) + 1))[:5000] for d in desc]
    global_features(head, d5000[:1])  # warm-up
    per_scan = []
    for _ in range(3):
        for d in d5000:
            t0 = time.perf_counter()
            global_features(head, [d])
            per_scan.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    codebook_scores(desc)
    codebook_total = time.perf_counter() - t0

    load = os.getloadavg()[0]
    print(f"\n### Speed (this machine: {os.cpu_count()} cores, load average {load:.1f} when measured; medians)\n")
    print("| what | time | target |")
    print("|---|---:|---:|")
    print(
        f"| global feature of one scan, learned head, 5000 FPFH descriptors ({len(d5000)} kitchen scans "
        f"x 3; numpy, as global_features runs it) | {1e3 * np.median(per_scan):.1f} ms | ≤ 50 ms |"
    )
    print(
        f"| VLAD codebook, k-means + features of the whole kitchen ({len(desc)} scans) | "
        f"{1e3 * codebook_total:.0f} ms ({1e3 * codebook_total / len(desc):.0f} ms a scan) | |"
    )
    graph_speed(D, n, repeats=repeats)


def simulated(head: VladHead, cache: Path) -> None:
    """Spearman ρ of the head and of the per-scene codebook on every scene of ``cache``, by kind and in all,
    with the paired difference (mean ± standard error) and the scenes each side wins."""
    from sghr_gtsam.train import evaluate, evaluate_codebook, load_cache

    scenes = load_cache(cache)
    rho = np.array([[evaluate(head, [s])["spearman"], evaluate_codebook([s])["spearman"]] for s in scenes])
    kinds = np.array([s.kind for s in scenes])
    print(
        f"\n### Simulated scenes of {cache.name} ({len(scenes)} scenes, {sum(len(s.descriptors) for s in scenes)} "
        f"scans; Spearman ρ over each scene's pairs, averaged)\n"
    )
    print("| scenes | learned head | VLAD codebook (pipeline now) | head − codebook | scenes won: head / codebook |")
    print("|---|---:|---:|---:|---:|")
    for name in [*sorted(set(kinds)), "all"]:
        r = rho if name == "all" else rho[kinds == name]
        d = r[:, 0] - r[:, 1]
        se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else float("nan")
        print(
            f"| {name} ({len(r)}) | {r[:, 0].mean():.3f} | {r[:, 1].mean():.3f} | {d.mean():+.3f} ± {se:.3f} "
            f"| {(d > 0).sum()} / {(d < 0).sum()} |"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--head", type=Path, default=DEFAULT_HEAD, help="learned head checkpoint")
    parser.add_argument(
        "--sim",
        type=Path,
        help="also score every scene of this simulated cache (make it with another seed than the training cache's)",
    )
    parser.add_argument(
        "--scenes",
        nargs="*",
        default=[],
        choices=list(MATCH_SCENES),
        help="also these full 3DMatch test scenes: the gt.log pairs each top-k graph proposes",
    )
    parser.add_argument("--no-speed", action="store_true")
    parser.add_argument(
        "--speed-only", "--only-speed", dest="only_speed", action="store_true", help="skip the overlap tables"
    )
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the N = 5000 graph timing")
    args = parser.parse_args(argv)
    if not (args.data / "MANIFEST.md").is_file():
        print(f"real data not found at {args.data} (set SGHR_DATA)")
        return 2
    head = load_checkpoint(str(args.head))
    print(
        f"# Overlap report\n\nlearned head: `{args.head.name}` ({head.centroids.shape[0]} clusters × "
        f"{head.centroids.shape[1]}-d FPFH); GT overlap > {THRESHOLD} counts as a good edge."
    )

    names, scans, G = kitchen(args.data)
    voxel = default_voxel(scans)
    desc = [compute_features(P, voxel).fpfh for P in scans]
    if args.only_speed:
        speed(head, desc, repeats=args.repeats)
        return 0
    report_scene(f"3DMatch kitchen (voxel {100 * voxel:.2f} cm; GT: gt_overlap.log)", names, desc, G, head)

    # The authors' head on their YOHO descriptors exists for fragments 0-5 only: the same 6 scans, all scores.
    ref = args.data / "sghr-reference"
    six = [names.index(f"cloud_bin_{i}.ply") for i in range(6)]
    authors = load_checkpoint(str(ref / "netvlad_overlap_model_best.pth"))
    yoho = [np.load(ref / "yoho" / f"cloud_bin_{i}.desc.npy") for i in range(6)]
    report_scene(
        "kitchen fragments 0–5 only",
        [names[k] for k in six],
        [desc[k] for k in six],
        G[np.ix_(six, six)],
        head,
        extra={"authors' head on YOHO (reference)": overlap_scores(global_features(authors, yoho))},
    )

    b_names, b_scans, b_G = bunny(args.data)
    b_voxel = default_voxel(b_scans)
    b_desc = [compute_features(P, b_voxel).fpfh for P in b_scans]
    report_scene(
        f"Stanford bunny (voxel {1000 * b_voxel:.2f} mm; GT: gt_overlap tool, symmetric)", b_names, b_desc, b_G, head
    )

    for name in args.scenes:
        report_match_scene(name, *match_scene(args.data, name), head)
    if args.sim:
        simulated(head, args.sim)
    if not args.no_speed:
        speed(head, desc, repeats=args.repeats)
    return 0


if __name__ == "__main__":
    sys.exit(main())
