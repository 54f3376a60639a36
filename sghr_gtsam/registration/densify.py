"""What the first synchronization teaches the front end: refine the kept edges from the
synchronized poses, close the loops those poses predict, and give the weak scans more partners. Each stage
adds to or improves the ``EdgeSet``; the pipeline synchronizes again while they change it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sghr_gtsam.cache import Cache
from sghr_gtsam.config import Config
from sghr_gtsam.progress import QUIET, Progress
from sghr_gtsam.registration.batch import register_edges
from sghr_gtsam.registration.edges import EdgeSet
from sghr_gtsam.registration.groups import merged, register_group, weak_groups
from sghr_gtsam.registration.loops import predicted_overlap, propose_loops
from sghr_gtsam.registration.refine import confirms, register_from_guesses, stays_near
from sghr_gtsam.registration.retry import retry_pairs, weak_scans
from sghr_gtsam.se3 import inv_T
from sghr_gtsam.store import Attribute, Stored
from sghr_gtsam.sync.consensus import MIN_AGREEING
from sghr_gtsam.types import PoseGraph, SyncResult


@dataclass
class DensifyReport:
    """What each stage did over all rounds: edges re-registered and confirmed by refinement, loop pairs tried
    and closed, pairs tried for weak scans and how many of them registered, the rounds run, and the scans
    rescued (weak after the first synchronization, placed and verified at the end)."""

    refined: int = 0
    refine_tried: int = 0
    loops_closed: int = 0
    loops_tried: int = 0
    retry_registered: int = 0
    retry_tried: int = 0
    groups_tried: int = 0
    groups_moved: int = 0
    group_edges: int = 0
    rounds: int = 0
    rescued: list[str] = field(default_factory=list)
    _tried: set = field(default_factory=set, repr=False)  # pairs any stage already re-registered
    _groups: set = field(default_factory=set, repr=False)  # weak groups already registered whole
    _moved: set = field(default_factory=set, repr=False)  # scans of the groups that registration moved
    _retried: set = field(default_factory=set, repr=False)  # scans given retries already

    def as_dict(self) -> dict:
        return {k: v for k, v in vars(self).items() if not k.startswith("_")}

    def or_tried(self, pairs: np.ndarray) -> np.ndarray:
        """(n, n) bool ``pairs`` with the pairs some stage already re-registered marked too, either way round."""
        for a, b in self._tried:
            pairs[a, b] = pairs[b, a] = True
        return pairs

    def moved_scans(self) -> list[int]:
        """The scans of the weak groups that their registration as a whole moved (``register_weak_groups``)."""
        return sorted(self._moved)


def _kept(edges: EdgeSet, sync: SyncResult) -> np.ndarray:
    """(E,) bool over the edge set: kept by the last synchronization (edges added since are not)."""
    kept = np.zeros(len(edges.ij), dtype=bool)
    kept[: len(sync.weights)] = sync.weights > 0
    return kept


def _guesses(poses: np.ndarray, ij: np.ndarray) -> np.ndarray:
    return inv_T(poses[ij[:, 0]]) @ poses[ij[:, 1]]


def refine_edges(
    features: Stored,
    pyramids: Stored,
    edges: EdgeSet,
    sync: SyncResult,
    voxel: float,
    config: Config,
    report: DensifyReport,
    progress: Progress = QUIET,
    cache: Cache | None = None,
) -> int:
    """Re-register every kept edge of the largest part not refined yet by multi-scale ICP from the
    synchronized ``T_i⁻¹ T_j``; an edge takes the result when it passes (``refine.confirms``). Returns the count."""
    main = sync.component == 0
    todo = np.flatnonzero(_kept(edges, sync) & ~edges.refined & main[edges.ij[:, 0]] & main[edges.ij[:, 1]])
    if not len(todo):
        return 0
    guesses = _guesses(sync.poses, edges.ij[todo])
    with progress.stage("refinement", len(todo)) as tick:
        results, near = register_from_guesses(
            features,
            pyramids,
            edges.ij[todo],
            guesses,
            voxel,
            config,
            [edges.pairs[e].matches for e in todo],
            tick,
            cache,
        )
    changed = 0
    for e, result, ok in zip(todo, results, near):
        edges.refined[e] = True
        if confirms(result, ok, config.inlier_bar):
            edges.replace(e, result)
            changed += 1
    report.refine_tried += len(todo)
    report.refined += changed
    return changed


def close_loops(
    features: Stored,
    pyramids: Stored,
    edges: EdgeSet,
    sync: SyncResult,
    voxel: float,
    config: Config,
    report: DensifyReport,
    progress: Progress = QUIET,
    cache: Cache | None = None,
) -> int:
    """Register the pairs of the largest part that overlap under the synchronized poses but have no kept edge,
    by multi-scale ICP from the synchronized guess: pairs never tried, and pairs whose global registration
    synchronization rejected (a wrong registration of a right pair). Those that pass (``refine.confirms``) enter
    as loop edges (a rejected edge's registration is replaced). Each pair is tried once a run."""
    n = len(features)
    skip = report.or_tried(_kept_pairs(edges, sync, n))
    tried, closed = _register_guessed(
        features,
        pyramids,
        edges,
        sync.poses,
        sync.component == 0,
        skip,
        voxel,
        config,
        report,
        progress,
        cache,
        "loop",
        "loop closure",
    )
    report.loops_tried += tried
    report.loops_closed += closed
    return closed


def register_weak_groups(
    features: Stored,
    pyramids: Stored,
    edges: EdgeSet,
    graph: PoseGraph,
    sync: SyncResult,
    flagged: np.ndarray,
    voxel: float,
    config: Config,
    report: DensifyReport,
    progress: Progress = QUIET,
    cache: Cache | None = None,
) -> int:
    """Each weak group (``groups.weak_groups`` of the ``flagged`` scans), merged, registered globally onto the
    merged verified rest of the largest part (``groups.register_group``); where that moves it, the pairs across its
    border that overlap at the new place are registered by ICP from it and those that pass enter as group
    edges (a rejected edge's registration is replaced). Each group is tried once a run. Returns the edges added."""
    n = len(features)
    rest = (sync.component == 0) & ~flagged
    todo = [g for g in weak_groups(graph, sync, flagged) if frozenset(g.tolist()) not in report._groups]
    if not todo or not rest.any():
        return 0
    kept = _kept_pairs(edges, sync, n)
    report._groups.update(frozenset(g.tolist()) for g in todo)
    report.groups_tried += len(todo)
    added = 0
    with progress.stage("group registration", len(todo)) as tick:
        target = merged(features, sync.poses, np.flatnonzero(rest), voxel, config)
        moves = []
        for k, group in enumerate(todo):
            moves.append(register_group(target, features, sync.poses, group, voxel, config))
            tick(k, moves[-1])
    for group, move in zip(todo, moves):
        if move is None or move.inliers < config.inlier_bar or stays_near(move.T, np.eye(4), voxel):
            continue  # no placement, or the one it has: nothing to add that loop closure would not
        report.groups_moved += 1
        report._moved.update(group.tolist())
        poses = sync.poses.copy()
        poses[group] = move.T @ poses[group]
        member = np.zeros(n, dtype=bool)
        member[group] = True
        skip = kept | ~(member[:, None] & rest[None, :] | rest[:, None] & member[None, :])  # across its border only
        _, closed = _register_guessed(
            features,
            pyramids,
            edges,
            poses,
            rest | member,
            skip,
            voxel,
            config,
            report,
            progress,
            cache,
            "group",
            "group closure",
            MIN_AGREEING,
        )
        report.group_edges += closed
        added += closed
    return added


def _kept_pairs(edges: EdgeSet, sync: SyncResult, n: int) -> np.ndarray:
    """(n, n) bool: the pairs with an edge the last synchronization kept, either way round."""
    kept = np.zeros((n, n), dtype=bool)
    ij_kept = edges.ij[_kept(edges, sync)]
    kept[ij_kept[:, 0], ij_kept[:, 1]] = kept[ij_kept[:, 1], ij_kept[:, 0]] = True
    return kept


def _register_guessed(
    features: Stored,
    pyramids: Stored,
    edges: EdgeSet,
    poses: np.ndarray,
    placed: np.ndarray,
    skip: np.ndarray,
    voxel: float,
    config: Config,
    report: DensifyReport,
    progress: Progress,
    cache: Cache | None,
    origin: str,
    label: str,
    min_entered: int = 1,
) -> tuple[int, int]:
    """Multi-scale ICP from ``poses`` of the ``placed`` pairs that overlap under them (``loops.propose_loops``; not
    those in ``skip``, (n, n) bool); those that pass (``refine.confirms``) enter with ``origin``, replacing the pair's
    earlier registration if it has one. Returns the pairs tried and those that entered."""
    overlap = predicted_overlap(Attribute(features, "points"), poses, placed, voxel)
    ij = propose_loops(overlap, skip, config.k)
    if not len(ij):
        return 0, 0
    report._tried.update(map(tuple, ij.tolist()))
    index = {(int(a), int(b)): e for e, (a, b) in enumerate(edges.ij)}
    ij = np.array([(b, a) if (b, a) in index else (a, b) for a, b in ij.tolist()], dtype=np.int64)  # as registered
    guesses = _guesses(poses, ij)
    known = [edges.pairs[index[(int(a), int(b))]].matches if (int(a), int(b)) in index else None for a, b in ij]
    with progress.stage(label, len(ij)) as tick:
        results, near = register_from_guesses(features, pyramids, ij, guesses, voxel, config, known, tick, cache)
    passing = [
        (a, b, result) for (a, b), result, ok in zip(ij, results, near) if confirms(result, ok, config.inlier_bar)
    ]
    if len(passing) < min_entered:
        return len(ij), 0
    entered = 0
    for a, b, result in passing:
        entered += 1
        e = index.get((int(a), int(b)))
        if e is None:
            edges.add(np.array([[a, b]]), [result], origin)
            edges.refined[-1] = True
        else:
            edges.replace(e, result, origin)
    return len(ij), entered


def retry_weak(
    features: Stored,
    scores: np.ndarray,
    edges: EdgeSet,
    sync: SyncResult,
    unverified: np.ndarray,
    voxel: float,
    config: Config,
    report: DensifyReport,
    progress: Progress = QUIET,
    cache: Cache | None = None,
) -> int:
    """Global registration of each weak scan (``retry.weak_scans``) against its next ``config.k`` candidates
    by overlap score; the pairs that register enter as retry edges. A scan placed in the largest part is retried
    once a run; only one left outside it is retried again (on a scene of repeated desks a second round of
    retries for every weak scan cost 15 s for two kept right edges:
    the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md). Returns how many registered."""
    n = len(features)
    weak = weak_scans(n, edges.ij[:, 0], edges.ij[:, 1], _kept(edges, sync), sync.component, unverified)
    again = np.zeros(n, dtype=bool)
    again[list(report._retried)] = True
    weak &= ~(again & (sync.component == 0))
    report._retried.update(np.flatnonzero(weak).tolist())
    tried = report.or_tried(edges.contains(n))
    ij = retry_pairs(weak, scores, tried, config.k)
    if not len(ij):
        return 0
    report._tried.update(map(tuple, ij.tolist()))
    with progress.stage("retry", len(ij)) as tick:
        results = register_edges(features, ij, voxel, config, tick, cache)
    good = [k for k, p in enumerate(results) if p.inliers >= config.inlier_bar]
    edges.add(ij[good], [results[k] for k in good], "retry")
    report.retry_tried += len(ij)
    report.retry_registered += len(good)
    return len(good)
