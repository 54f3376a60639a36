"""The SGHR pipeline, stage by stage (``_register``): scans -> local features -> global features and top-k graph ->
pairwise registration on graph edges -> synchronization (history-reweighted IRLS, gtsam polish) -> free space
overrules look-alike placements -> refinement, loop closure, retries and weak groups, synchronized again
(``_densify``) -> poses, parts and each scan's status (``_run_result``, ``verify``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from sghr_gtsam import local_frame
from sghr_gtsam.cache import Cache, pyramid_key, scan_key, unusable
from sghr_gtsam.config import Config
from sghr_gtsam.executor import kept_workers, start_server
from sghr_gtsam.features.local import FEATURES, scan_features
from sghr_gtsam.features.netvlad import DEFAULT_HEAD, codebook_features, global_features, load_default_head
from sghr_gtsam.graph import bridge_components, top_k_edges, top_k_graph
from sghr_gtsam.gtsam_api import pose_covariances
from sghr_gtsam.io.atomic import staged_folder
from sghr_gtsam.io.results import CACHE, check_output_folder, write_results
from sghr_gtsam.merged import merged_cloud
from sghr_gtsam.progress import QUIET, Progress
from sghr_gtsam.registration import WORKER_MODULES
from sghr_gtsam.registration.batch import register_edges
from sghr_gtsam.registration.densify import DensifyReport, close_loops, refine_edges, register_weak_groups, retry_weak
from sghr_gtsam.registration.edges import GUESSED, EdgeSet, edge_status
from sghr_gtsam.registration.overrule import Viewpoints, look_alikes, overruled_edges
from sghr_gtsam.registration.refine import PYRAMIDS, scan_pyramid
from sghr_gtsam.registration.retry import weak_scans
from sghr_gtsam.registration.visibility import viewpoint_conflicts
from sghr_gtsam.result import RunResult
from sghr_gtsam.scene import Log, check_given, load_scene, scene_voxel, too_few, usable_scans, voxel_doubt
from sghr_gtsam.se3 import inv_T
from sghr_gtsam.store import Attribute, Store, Stored
from sghr_gtsam.sync import synchronize, unverified
from sghr_gtsam.types import InputError, IterationRecord, PoseGraph, Scan, ScanStats, SyncResult
from sghr_gtsam.verify import Verdict, Verification, placement_turns, verify

if TYPE_CHECKING:
    from sghr_gtsam.recording import Recorder  # rerun is imported only for a run that records (~0.5 s)


class _Timer:
    def __init__(
        self, on_stage: Callable[[str], None] | None = None, on_end: Callable[[str, float], None] | None = None
    ) -> None:
        self.seconds: dict[str, float] = {}
        self._on_stage = on_stage  # told each stage's name as it starts (the recording's steps)
        self._on_end = on_end  # told each stage's name and seconds as it ends (the recording's data)

    @contextmanager
    def stage(self, name: str):
        if self._on_stage:
            self._on_stage(name)
        t0 = time.perf_counter()
        yield
        seconds = time.perf_counter() - t0
        self.seconds[name] = self.seconds.get(name, 0.0) + seconds
        if self._on_end:
            self._on_end(name, seconds)


def _global_features(features: Stored, counts: list[int], config: Config) -> tuple[np.ndarray, str]:
    """Unit global features (N, D) of the scans (``counts``: their descriptors), read one at a time, and what made
    them."""
    # FPFH, also when pairs are matched on learned descriptors: the codebook and the shipped head rank overlaps on it
    fpfh = features[0].fpfh is not None
    descriptors = Attribute(features, "fpfh" if fpfh else "descriptors")
    dim = descriptors[0].shape[1]
    kind = f"{dim}-d " + ("FPFH" if fpfh else "given descriptors")
    if config.overlap_head or config.global_feature == "learned":
        head = load_default_head(config.overlap_head)
        path = config.overlap_head or DEFAULT_HEAD
        if head.centroids.shape[1] != dim:
            raise InputError(
                f"overlap head {path} takes {head.centroids.shape[1]}-d descriptors, the scans have {kind}"
            )
        F = global_features(head, descriptors, seed=config.seed)
        return F, f"learned NetVLAD head ({path}) on {kind}"
    if config.global_feature != "vlad":
        raise InputError(f"unknown global feature {config.global_feature!r} (vlad, learned)")
    F, clusters = codebook_features(descriptors, seed=config.seed, counts=counts)
    return F, f"unsupervised VLAD codebook ({clusters} clusters of {kind}, k-means on this scene)"


OVERRULE_ROUNDS = 3
"""Synchronizations without overruled edges after each one with them, at most: each can bring new groups to light."""


@dataclass
class _Stages:
    """What the stages after the local features share in one ``register``: the usable scans and their stored
    features, the run's settings and observers, and what the early stages learn for the later ones."""

    scans: list[Scan]
    features: Stored
    centres: np.ndarray  # (N, 3): where each scan was centred (``local_frame``)
    voxel: float
    config: Config
    store: Store
    timer: _Timer
    log: Log
    recorder: Recorder | None
    progress: Progress
    cache: Cache | None
    scores: np.ndarray | None = None  # (N, N) overlap scores, from the global graph on
    views: Viewpoints | None = None  # the scans' free space (``config.free_space``), from the first synchronization on

    def pose_graph(self, edges: EdgeSet) -> PoseGraph:
        """The graph of ``edges`` for synchronization, the contradicted ones (``config.free_space``) at weight 0."""
        if self.config.free_space:
            with self.timer.stage("free_space"):
                new = edges.check_free_space(
                    self.features, self.voxel, self.centres, self.config.inlier_bar, self.views
                )
            if new:  # said again only when new registrations were checked (overrule rounds add none)
                registered = int(edges.registered(self.config.inlier_bar).sum())
                checked = int(np.isfinite(edges.conflict).sum())
                self.log(
                    f"free space: {int(edges.contradicted().sum())} of {registered} registrations "
                    f"contradicted ({registered - checked} not checkable: scans not seen from their "
                    f"origins{'' if self.views is None else ' nor vouched for'})"
                )
        graph = edges.pose_graph(len(self.features), self.scores, self.config.inlier_bar, self.config.initial_weight)
        if self.recorder:
            self.recorder.log_graph(graph, self.scores)
        return graph

    def synchronize(self, graph: PoseGraph, label: str) -> SyncResult:
        """Synchronize ``graph`` by ``config``'s method, each iteration shown (``label``) and recorded."""
        config, recorder = self.config, self.recorder
        with self.timer.stage("sync"):
            with self.progress.stage(label, config.iters) as tick:

                def observe(record: IterationRecord) -> None:
                    if recorder:
                        recorder.on_iteration(record)
                    tick(record)

                result = synchronize(
                    graph,
                    method=config.method,
                    iters=config.iters,
                    reweight=config.reweight,
                    polish=config.polish,
                    min_weight=config.min_weight,
                    on_iteration=observe,
                )
            if recorder:
                recorder.log_sync(result)
        return result

    def overrule(self, edges: EdgeSet, graph: PoseGraph, result: SyncResult) -> tuple[PoseGraph, SyncResult]:
        """Synchronize again without the edges that hold a group where the scans' free space rules it out
        (``registration.overrule``; no ``views``: no check), until none is left, at most ``OVERRULE_ROUNDS``
        times."""
        for _ in range(OVERRULE_ROUNDS if self.views is not None else 0):
            with self.timer.stage("free_space"):
                overruled = overruled_edges(self.views, graph, result) & ~edges.overruled
            if not overruled.any():
                break
            edges.overruled |= overruled
            self.log(
                f"free space: {int(overruled.sum())} registrations overruled (they held a group of scans where "
                f"the scans' free space rules it out)"
            )
            graph = self.pose_graph(edges)
            result = self.synchronize(graph, "synchronization (overruled edges out)")
        return graph, result


def _also_recorded(log: Log, recorder: Recorder) -> Log:
    def both(message: str) -> None:
        log(message)
        recorder.log_message(message)

    return both


def _silent(message: str) -> None:
    """The API's default ``log``: it prints nothing (the CLI passes its own)."""


def register(
    scans: list[Scan],
    config: Config,
    recorder: Recorder | None = None,
    log: Log | None = None,
    skipped: dict[str, str] | None = None,
    scores: np.ndarray | None = None,
    progress: Progress = QUIET,
    cache: Cache | None = None,
    store: Store | None = None,
) -> RunResult:
    """Register ``scans`` (at least two) into one frame. The recorder and the progress only observe. ``log``: called
    with each stage message, a line of text (``log=print`` shows them as the command line does); by default nothing is
    printed.

    ``scores``: an (N, N) symmetric matrix of overlap scores to choose the top-k graph from instead of the
    global features (e.g. ground-truth overlaps or another method's), with their values as ``s`` in ``w⁰``.
    ``cache``: features, pyramids and pair registrations are read from it where it holds them and stored in it as
    they are computed (``cache.Cache``; ``run`` passes ``OUT/cache``). No stage holds every scan's points at once:
    the checks use their ``ScanStats`` and each parallel task reads its scan; no process holds every scan's
    features and grids either: they go to ``store`` (``store.Store``; default ``Store(cache)``: the cache's folder,
    or without one a temporary folder removed when the result is garbage collected) and are read back one scan at a
    time where they are needed, ``RunResult.features`` too.
    """
    config.validate()
    log = log or _silent
    scores = check_given(scans, scores)
    if recorder:
        log = _also_recorded(log, recorder)
    timer = _Timer(recorder.begin_stage if recorder else None, recorder.end_stage if recorder else None)
    skipped = dict(skipped or {})
    stats = [s.statistics() for s in scans]  # a scan given without them is read here, one at a time
    scans, stats, scores = usable_scans(scans, stats, scores, skipped, log, config.min_points)
    voxel = scene_voxel(config.voxel, stats)
    centres = local_frame.centres(np.array([st.median for st in stats]), voxel)
    scans = [replace(s, centre=c, stats=st) for s, c, st in zip(scans, centres, stats)]
    log(f"{len(scans)} scans, voxel {voxel:.4g}")
    listed = [s.name for s in scans]
    order = _content_order(stats)
    scans, centres = [scans[k] for k in order], centres[order]
    scores = None if scores is None else scores[np.ix_(order, order)]
    owned, store = store is None, store or Store(cache)
    try:
        with kept_workers(config.workers, config.ray):
            return _register(
                scans, listed, centres, voxel, config, store, recorder, log, skipped, timer, scores, progress, cache
            )
    except BaseException:
        if owned:  # a store it made goes with a failed run; the caller's is the caller's
            store.close()
        raise


def _content_order(stats: list[ScanStats]) -> np.ndarray:
    """The order the stages take the scans in: the most points first, then by their bounding box's diagonal, then
    the digest of the points, not by their names or where they are listed (a count and a diagonal, unlike a digest,
    are the same wherever a scan lies, to rounding: the same scans at a georeferenced offset run as near the origin;
    simulated scans often share a count). Registration is not symmetric: the first scan of a pair is the target, so
    the larger scan is, and GICP moves the smaller one, whose points then more often lie on the other and cost less;
    samples are drawn and ties broken in this order, and the first synchronization's frame decides which cells
    predict a loop's overlap: in listing order, the same scans listed the other way round gave another model
    (docs/benchmarks.md, stability). ``_in_listing_order`` turns the result back."""
    return np.array(
        sorted(range(len(stats)), key=lambda k: (-stats[k].points, stats[k].span, stats[k].digest)), dtype=np.int64
    )


def _register(
    scans: list[Scan],
    listed: list[str],
    centres: np.ndarray,
    voxel: float,
    config: Config,
    store: Store,
    recorder: Recorder | None,
    log: Log,
    skipped: dict[str, str],
    timer: _Timer,
    scores: np.ndarray | None,
    progress: Progress,
    cache: Cache | None,
) -> RunResult:
    """``register`` from the features on: ``scans`` checked, centred (at ``centres``) and in ``_content_order``;
    the result in the order of the names ``listed``."""
    scans, centres, features, counts, scores = _local_features(
        scans, centres, scores, voxel, config, store, skipped, timer, log, progress
    )
    position = {name: k for k, name in enumerate(listed)}
    listing = np.argsort([position[s.name] for s in scans], kind="stable")  # k-th listed scan -> its index here
    if recorder:  # coloured as listed
        recorder.log_scans([s.name for s in scans], Attribute(features, "points"), np.argsort(listing))
    stages = _Stages(scans, features, centres, voxel, config, store, timer, log, recorder, progress, cache)
    top_k, stages.scores, feature_kind = _global_graph(stages, counts, scores)

    edges = EdgeSet()
    with timer.stage("pairwise"), progress.stage("pairwise registration", len(top_k)) as tick:
        edges.add(top_k, register_edges(features, top_k, voxel, config, tick, cache), "top-k")
    log(f"pairwise: {len(edges.pairs)} pairs in {timer.seconds['pairwise']:.2f} s")
    graph = stages.pose_graph(edges)
    if not np.any(graph.weight > 0):
        doubt = voxel_doubt(voxel, [scans[k] for k in listing], given=config.voxel is not None)
        raise InputError(f"no pair of scans could be registered (do the scans overlap?{doubt})")
    result = stages.synchronize(graph, "synchronization")
    log(f"sync ({config.method}): {timer.seconds['sync']:.2f} s")
    if config.free_space:
        with timer.stage("free_space"):
            stages.views = Viewpoints(features, voxel, centres)
            vouched = stages.views.vouch(graph, result)
        judged = len(stages.views.images) if vouched else 0
        log(
            f"free space: the scans' frames {'are' if vouched else 'are not'} vouched for by the first "
            f"synchronization's loop-checked registrations (single registrations of {judged} scans judged from now on)"
        )
    graph, result = stages.overrule(edges, graph, result)
    graph, result, densify, first_weak = _densify(stages, edges, graph, result)
    graph, result, first_weak = _in_listing_order(stages, listing, edges, graph, result, first_weak)
    return _run_result(stages, edges, graph, result, densify, first_weak, skipped, feature_kind)


def _local_features(
    scans: list[Scan],
    centres: np.ndarray,
    scores: np.ndarray | None,
    voxel: float,
    config: Config,
    store: Store,
    skipped: dict[str, str],
    timer: _Timer,
    log: Log,
    progress: Progress,
) -> tuple[list[Scan], np.ndarray, Stored, list[int], np.ndarray | None]:
    """The scans with features, their centres, their features in ``store``, their counts of descriptors and their
    rows of the given ``scores`` (or None); the others go to ``skipped``."""
    # Each task reads its scan where it runs: full-resolution points live only in the scans in flight; its features
    # go to the store as they arrive, and this process keeps their count of descriptors (or why there are none).
    keys = [scan_key(s, voxel, config) for s in scans]
    shared = _feature_settings(voxel, config)
    with timer.stage("features"), progress.stage("features", len(scans)) as tick:
        counts = store.map(
            FEATURES,
            scan_features,
            shared,
            scans,
            keys,
            config.workers,
            tick,
            config.ray,
            keep=lambda f: f if isinstance(f, str) else len(f.descriptors),
        )
    for s, count in zip(scans, counts):
        if isinstance(count, str):  # no features: a stray point far away (too many voxels), keypoints off the scan
            skipped[s.name] = count
            log(f"skipped {s.name}: {count}")
    usable = [k for k, count in enumerate(counts) if not isinstance(count, str)]
    scans, centres, counts = [scans[k] for k in usable], centres[usable], [counts[k] for k in usable]
    if len(scans) < 2:
        raise too_few(scans, skipped)
    features = store.sequence(FEATURES, [keys[k] for k in usable], _again(scan_features, shared, scans))
    return scans, centres, features, counts, None if scores is None else scores[np.ix_(usable, usable)]


def _feature_settings(voxel: float, config: Config) -> tuple:
    """What ``scan_features`` takes besides the scan."""
    return voxel, config.normal_radius, config.fpfh_radius, config.descriptor


def _global_graph(stages: _Stages, counts: list[int], scores: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, str]:
    """The top-k pairs to register (bridged across parts with ``config.connect``), the (N, N) overlap scores
    (the caller's ``scores``, or from the global features) and what made them."""
    config, n = stages.config, len(stages.scans)
    with stages.timer.stage("global_graph"):
        if scores is None:
            F, feature_kind = _global_features(stages.features, counts, config)
            top_k, _, scores = top_k_graph(F, config.k, full_scores=True)
        else:
            feature_kind = "overlap scores given by the caller"
            top_k = top_k_edges(scores, config.k)
        if config.connect:
            top_k = bridge_components(top_k, scores)
    seconds = stages.timer.seconds
    stages.log(
        f"features: {seconds['features']:.2f} s; pose graph: {len(top_k)} of {n * (n - 1) // 2} pairs "
        f"(top-{config.k}) in {seconds['global_graph']:.2f} s"
    )
    return top_k, scores, feature_kind


def _densify(
    stages: _Stages, edges: EdgeSet, graph: PoseGraph, result: SyncResult
) -> tuple[PoseGraph, SyncResult, DensifyReport, np.ndarray]:
    """Steps 2-4 of the front end (refine, close loops, retry weak scans, register weak groups whole), then
    synchronize again, while they change the graph (at most ``config.rounds`` times); also the (N,) scans weak after
    the first synchronization, and those of the groups the group stage moved."""
    config, timer, progress = stages.config, stages.timer, stages.progress
    scans, features, voxel, cache = stages.scans, stages.features, stages.voxel, stages.cache
    densify = DensifyReport()
    # Retries go to scans beyond a bridge only: also retrying those beyond one scan took three of five simulated
    # rooms past the 40 % budget of global registrations (benchmarks/bench_pipeline.py).
    first_weak = weak_scans(
        len(scans), graph.i, graph.j, result.weights > 0, result.component, unverified(graph, result, one_scan=False)
    )
    pyramids = None
    for _ in range(config.rounds):
        changed = 0
        if (config.refine or config.loops or config.groups) and pyramids is None:
            grid_keys = [pyramid_key(key) for key in features.keys]
            with timer.stage("pyramids"), progress.stage("pyramids", len(scans)) as tick:
                stages.store.map(
                    PYRAMIDS,
                    scan_pyramid,
                    voxel,
                    scans,
                    grid_keys,
                    config.workers,
                    tick,
                    config.ray,
                    keep=lambda p: None,
                )
            pyramids = stages.store.sequence(PYRAMIDS, grid_keys, _again(scan_pyramid, voxel, scans))
        if config.refine:
            with timer.stage("refine"):
                changed += refine_edges(features, pyramids, edges, result, voxel, config, densify, progress, cache)
        if config.loops:
            with timer.stage("loops"):
                changed += close_loops(features, pyramids, edges, result, voxel, config, densify, progress, cache)
        if config.retry:
            with timer.stage("retry"):
                changed += retry_weak(
                    features,
                    stages.scores,
                    edges,
                    result,
                    unverified(graph, result, one_scan=False),
                    voxel,
                    config,
                    densify,
                    progress,
                    cache,
                )
        if config.groups:
            with timer.stage("groups"):
                changed += register_weak_groups(
                    features,
                    pyramids,
                    edges,
                    graph,
                    result,
                    unverified(graph, result),
                    voxel,
                    config,
                    densify,
                    progress,
                    cache,
                )
        if not changed:
            break
        densify.rounds += 1
        graph = stages.pose_graph(edges)
        stages.log(
            f"round {densify.rounds}: {densify.refined} edges refined, {densify.loops_closed} loops closed, "
            f"{densify.retry_registered} retry pairs registered, {densify.group_edges} group edges; "
            f"{graph.num_edges} edges"
        )
        result = stages.synchronize(graph, f"synchronization (round {densify.rounds})")
        graph, result = stages.overrule(edges, graph, result)
    first_weak[densify.moved_scans()] = True  # a group that one registration moved is as weak as a weak scan
    return graph, result, densify, first_weak


def _in_listing_order(
    stages: _Stages, order: np.ndarray, edges: EdgeSet, graph: PoseGraph, result: SyncResult, first_weak: np.ndarray
) -> tuple[PoseGraph, SyncResult, np.ndarray]:
    """The stages' scans, features, scores and viewpoints, the edges, the graph, the synchronization and the weak
    scans relabelled from ``_content_order`` to the order the scans were listed in (``order[k]``: the k-th listed):
    the world is then the first listed scan of the largest part, and every output lists the scans as given."""
    new = np.argsort(order)  # old index -> new
    stages.scans = [stages.scans[k] for k in order]
    keys = [stages.features.keys[k] for k in order]
    again = _again(scan_features, _feature_settings(stages.voxel, stages.config), stages.scans)
    stages.features = stages.store.sequence(FEATURES, keys, again)
    stages.centres, stages.scores = stages.centres[order], stages.scores[np.ix_(order, order)]
    if stages.views is not None:
        stages.views = stages.views.reordered(order)
    edges.ij = new[edges.ij]
    graph = replace(graph, i=new[graph.i], j=new[graph.j])
    history = [replace(r, poses=r.poses[order]) for r in result.history]
    result = replace(result, poses=result.poses[order], component=result.component[order], history=history)
    if stages.recorder:
        stages.recorder.reorder(order, graph)
    return graph, result, first_weak[order]


def _run_result(
    stages: _Stages,
    edges: EdgeSet,
    graph: PoseGraph,
    result: SyncResult,
    densify: DensifyReport,
    first_weak: np.ndarray,
    skipped: dict[str, str],
    feature_kind: str,
) -> RunResult:
    """The last synchronization's poses anchored at the first scan of the largest part, the covariances, the parts
    and each scan's status (``verify``), back in the input frame."""
    log, names, n = stages.log, [s.name for s in stages.scans], len(stages.scans)
    main_part = result.component == 0
    main = np.flatnonzero(main_part)
    poses = inv_T(result.poses[main[0]])[None] @ result.poses  # the other parts have no reliable pose
    unregistered = [names[k] for k in range(n) if result.component[k] != 0]
    free_space = stages.config.free_space
    out = RunResult(
        names=names,
        poses=poses,
        voxel=float(stages.voxel),
        scores=stages.scores,
        graph=graph,
        pairs=edges.pairs,
        edge_origin=edges.origin,
        edge_conflict=edges.conflict if free_space else None,
        edge_overruled=edges.overruled if free_space else None,
        densify=densify.as_dict(),
        sync=result,
        unregistered=unregistered,
        skipped=skipped,
        features=stages.features,
        timings=stages.timer.seconds,
        global_feature=feature_kind,
        cache=stages.cache.report() if stages.cache else None,
    )
    with stages.timer.stage("covariances"):
        try:
            out.covariances = pose_covariances(out)
        except RuntimeError:  # gtsam: an indeterminate system (e.g. identical scans: no information across them)
            out.covariances = np.full((n, 6, 6), np.nan)
            log("covariances: the kept edges leave the poses' marginals indeterminate; written as NaN")
    with stages.timer.stage("verify"):
        out.verdict = _verdict(stages, edges, out, first_weak)
    densify.rescued = [names[k] for k in np.flatnonzero(first_weak) if out.verdict.status[names[k]] == "verified"]
    out.densify = densify.as_dict()
    if stages.recorder:
        stages.recorder.log_final(poses, out.flags)
        stages.recorder.log_parts(poses, out.verdict.parts)
        stages.recorder.log_edge_status(poses, edge_status(out))
        stages.recorder.log_covariances(poses, out.covariances)
    local_frame.to_input_frame(out, stages.centres)
    return out


def _verdict(stages: _Stages, edges: EdgeSet, run: RunResult, first_weak: np.ndarray) -> Verdict:
    """Parts and scan status (``verify``). A registration that started from the pose it would check (loop closures
    and group edges, ``GUESSED``) is no independent evidence for a scan weak after the first synchronization: it
    confirms that scan where it is, right or wrong."""
    graph, n = run.graph, len(run.names)
    placed = np.zeros(n, dtype=bool)
    placed[run.registered] = True
    guessed = np.isin(np.array(run.edge_origin), GUESSED) & (first_weak[graph.i] | first_weak[graph.j])
    kept = run.sync.weights > 0
    if run.sync.held is not None:  # past the tolerances, kept only to join two parts: they check nothing
        kept &= ~run.sync.held
    information, free = None, None
    if graph.information is not None:  # the covariances' information: free directions bounded by the overlap alone
        information = np.stack(
            [info if p.bounded is None else p.bounded for p, info in zip(run.pairs, graph.information)]
        )
        free = np.stack([np.zeros((6, 6)) if p.loose is None else p.loose for p in run.pairs])
    conflicts, alike = None, []
    if stages.views is not None:  # config.free_space
        with stages.timer.stage("free_space"):
            alike = look_alikes(stages.views, graph, run.sync)
    if stages.config.free_space:
        turns = placement_turns(graph, kept, run.poses)
        conflicts = viewpoint_conflicts(stages.features, run.poses, placed, stages.voxel, stages.centres, turns)

    return verify(
        run.names,
        graph,
        kept,
        run.poses,
        placed,
        Verification(max_sigma=stages.config.max_sigma),
        Attribute(stages.features, "points"),
        information,
        free,
        conflicts,
        guessed,
        alike,
    )


def _again(fn: Callable, shared: object, tasks: list) -> Callable[[int], object]:
    """``k -> fn(shared, tasks[k])``: how the store makes a stage's item k again (``store.Store.sequence``)."""
    return lambda k: fn(shared, tasks[k])


def run(
    scene_dir: str | Path, out_dir: str | Path, config: Config, log: Log | None = None, progress: Progress = QUIET
) -> RunResult:
    """Load ``scene_dir``, register its scans and write every output into ``out_dir``, which is replaced as a
    whole when the run completes (``io.atomic.staged_folder``): stopped or failed, it leaves ``out_dir`` as it
    was. ``out_dir`` must be new, empty or an earlier run's results (``InputError`` otherwise). ``progress``
    observes the long stages (``progress.TerminalProgress`` draws bars). ``log``: called with each stage message
    (``log=print`` shows them as the command line does); by default nothing is printed."""
    config.validate()
    log = log or _silent
    started = time.perf_counter()
    out = Path(out_dir)
    check_output_folder(out, Path(scene_dir))
    start_server(WORKER_MODULES, config.workers, config.ray)  # its imports overlap the loading
    timer = _Timer()
    with timer.stage("load"):
        scans, skipped = load_scene(scene_dir, config, log)
    with staged_folder(out, carry=CACHE) as stage:
        cache = Cache(out / CACHE) if config.cache else None  # written in place: kept across the swap
        if cache and (why := unusable(cache.folder)):
            log(f"the cache {cache.folder} cannot be used ({why}): this run keeps none")
            cache = None
        store = Store(cache, scratch=stage)  # without a cache, removed before the swap (and with the stage)
        try:
            recorder = None
            if config.record:
                from sghr_gtsam.recording import Recorder

                name = f"{Path(scene_dir).resolve().name} → {out.resolve().name}"  # two runs side by side told apart
                recorder = Recorder(stage / "recording.rrd", min_weight=config.min_weight, name=name)
                recorder.end_stage("load", timer.seconds["load"])
            try:
                result = register(scans, config, recorder, log, skipped, progress=progress, cache=cache, store=store)
            finally:
                if recorder:
                    recorder.close()
            result.timings = {**timer.seconds, **result.timings}
            write_results(stage, result, config, started, merged_cloud(result))
        finally:
            store.close()
    return result
