"""The registered pairs of a run as they grow: global registrations of the top-k graph, then refinements,
loop closures and retries (``EdgeSet``), and the ``PoseGraph`` they make."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from sghr_gtsam.registration.information import FREE_FLOOR
from sghr_gtsam.registration.pairwise import PairResult
from sghr_gtsam.registration.visibility import conflicts, contradicted
from sghr_gtsam.store import Stored
from sghr_gtsam.types import PoseGraph

if TYPE_CHECKING:
    from sghr_gtsam.registration.overrule import Viewpoints
    from sghr_gtsam.result import RunResult

ORIGINS = ("top-k", "loop", "retry", "group")
"""How an edge entered: the sparse graph (with its bridges), a loop closure, a retry of a weak scan, or an ICP
from where a weak group's registration as a whole puts it (``groups``)."""
GUESSED = ("loop", "group")
"""The origins of edges registered by ICP from a guess of the poses rather than globally."""

EDGE_STATUS = {
    "kept": "in graph.g2o: synchronization kept it and both scans are registered",
    "rejected": "registered, but inconsistent with the result (graph_rejected.g2o)",
    "failed": "the registration failed (too few inliers): no measurement (graph_rejected.g2o)",
    "contradicted": "registered, but it puts one scan's surfaces where the other saw empty space: no measurement "
    "(registration.visibility, or overrule.Viewpoints once vouched for; graph_rejected.g2o)",
    "overruled": "registered, but it held a group of scans where their free space rules them out, against a place "
    "other registrations agree on: no measurement (registration.overrule; graph_rejected.g2o)",
    "unplaced": "kept, but between scans outside the largest part, which have no pose (graph_rejected.g2o)",
}


def _information(pairs: list[PairResult]) -> np.ndarray | None:
    """(E, 6, 6) the pairs' information; None when none has any. A pair without (under the inlier bar, fewer than 3
    matches, or under ``information.MIN_PAIRS`` close points: a failed registration) gets ``FREE_FLOOR`` of the
    weakest measured information on each axis: positive definite, as synchronization and the g2o files ask, and too
    weak to pull.
    A single such pair (a featureless scan) used to take the information of every edge, calibrated covariances
    and g2o included."""
    measured = [p.information for p in pairs if p.information is not None]
    if not measured:
        return None
    weakest = np.diag(FREE_FLOOR * np.diagonal(np.stack(measured), axis1=1, axis2=2).min(axis=0))
    return np.stack([weakest if p.information is None else p.information for p in pairs])


def edge_status(result: RunResult) -> list[str]:
    """The ``EDGE_STATUS`` key of every edge of ``result.graph``."""
    g = result.graph
    placed = np.zeros(len(result.names), dtype=bool)
    placed[result.registered] = True
    ruled_out = (
        np.zeros(g.num_edges, dtype=bool) if result.edge_conflict is None else contradicted(result.edge_conflict)
    )
    overruled = np.zeros(g.num_edges, dtype=bool) if result.edge_overruled is None else result.edge_overruled
    return [
        ("contradicted" if ruled_out[e] else "overruled" if overruled[e] else "failed")
        if g.weight[e] <= 0
        else "rejected"
        if result.sync.weights[e] <= 0
        else "kept"
        if placed[g.i[e]] and placed[g.j[e]]
        else "unplaced"
        for e in range(g.num_edges)
    ]


@dataclass
class EdgeSet:
    """``ij`` (E, 2) scan pairs, ``pairs[e]`` the registration of ``ij[e]`` (``T_ij``), ``origin[e]`` one of
    ``ORIGINS``, ``refined[e]`` whether ``pairs[e]`` comes from multi-scale refinement, ``conflict[e]`` its
    ``visibility.free_space_conflict`` or, in a scene whose frames are vouched for where it cannot judge,
    ``overrule.Viewpoints.fraction`` (NaN: not checked, or not checkable), ``overruled[e]``
    whether it held a group where the scans' free space rules it out (``overrule``)."""

    ij: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    pairs: list[PairResult] = field(default_factory=list)
    origin: list[str] = field(default_factory=list)
    refined: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    conflict: np.ndarray = field(default_factory=lambda: np.zeros(0))
    overruled: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    _checked: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool), repr=False)
    _coarse: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool), repr=False)  # judged by ``views``

    def add(self, ij: np.ndarray, pairs: list[PairResult], origin: str) -> None:
        self.ij = np.concatenate([self.ij, np.asarray(ij, dtype=np.int64).reshape(-1, 2)])
        self.pairs.extend(pairs)
        self.origin.extend([origin] * len(pairs))
        self.refined = np.concatenate([self.refined, np.zeros(len(pairs), dtype=bool)])
        self.conflict = np.concatenate([self.conflict, np.full(len(pairs), np.nan)])
        self.overruled = np.concatenate([self.overruled, np.zeros(len(pairs), dtype=bool)])
        self._checked = np.concatenate([self._checked, np.zeros(len(pairs), dtype=bool)])
        self._coarse = np.concatenate([self._coarse, np.zeros(len(pairs), dtype=bool)])

    def replace(self, e: int, pair: PairResult, origin: str | None = None) -> None:
        """Edge ``e`` takes the refined registration ``pair`` (and ``origin``), to be checked again."""
        self.pairs[e], self.refined[e], self._checked[e] = pair, True, False
        if origin is not None:
            self.origin[e] = origin

    def check_free_space(
        self, features: Stored, voxel: float, centres: np.ndarray, min_inliers: int, views: Viewpoints | None = None
    ) -> int:
        """``conflict`` of the registrations (at least ``min_inliers`` inliers: a failed one is no measurement, and
        its verdict would change nothing) added or replaced since the last check (``visibility.conflicts``), and,
        once ``views`` vouches for the scene's frames (``overrule.Viewpoints.vouch``), of those it leaves unjudged
        the coarse ``Viewpoints.fraction``; returns how many edges were judged anew. Fused RGB-D fragments are
        not seen from one origin (``visibility``), so only the coarse check judges them: in a scene of repeated
        desks, the look-alike registrations, 57 of its 127 wrong ones, none of its 256 right ones
        (the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""
        registered = self.registered(min_inliers)
        todo = np.flatnonzero(~self._checked & registered)
        if len(todo):
            T = np.stack([self.pairs[e].T for e in todo])
            self.conflict[todo] = conflicts(features, self.ij[todo], T, voxel, centres)
            self._checked[todo], self._coarse[todo] = True, False
        if views is None or not views.vouched:
            return len(todo)
        coarse = np.flatnonzero(registered & ~self._coarse & np.isnan(self.conflict))
        for e in coarse:
            self.conflict[e] = views.fraction(int(self.ij[e, 0]), int(self.ij[e, 1]), self.pairs[e].T)
        self._coarse[coarse] = True
        return len(np.union1d(todo, coarse))

    def contradicted(self) -> np.ndarray:
        """(E,) bool: edges whose transform puts one scan's surfaces where the other saw nothing
        (``visibility.contradicted``)."""
        return contradicted(self.conflict)

    def registered(self, min_inliers: int) -> np.ndarray:
        """(E,) bool: the pairs whose registration has at least ``min_inliers`` inliers (the others failed)."""
        return np.array([p.inliers >= min_inliers for p in self.pairs], dtype=bool)

    def contains(self, n: int) -> np.ndarray:
        """(n, n) bool: the pairs already registered, either way round."""
        has = np.zeros((n, n), dtype=bool)
        has[self.ij[:, 0], self.ij[:, 1]] = has[self.ij[:, 1], self.ij[:, 0]] = True
        return has

    def pose_graph(self, n: int, scores: np.ndarray, min_inliers: int, initial_weight: str) -> PoseGraph:
        """The graph synchronization sees: ``w⁰ = s · r`` (or the ``initial_weight`` ablation), 0 for pairs
        with fewer than ``min_inliers`` inliers (a failed pair is no measurement at all) and for ``contradicted``
        and ``overruled`` ones (a transform the scans' free space rules out is none either)."""
        i, j = self.ij[:, 0].copy(), self.ij[:, 1].copy()
        s = scores[i, j]
        r = np.array([p.inliers for p in self.pairs], dtype=float)
        r[~self.registered(min_inliers) | self.contradicted() | self.overruled] = 0.0
        return PoseGraph(
            n=n,
            i=i,
            j=j,
            T=np.stack([p.T for p in self.pairs]) if self.pairs else np.zeros((0, 4, 4)),
            weight={"s*r": s * r, "s": np.where(r > 0, s, 0.0), "r": r}[initial_weight],
            information=_information(self.pairs),
        )
