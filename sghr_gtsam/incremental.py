"""Incremental registration for a SLAM stack that emits submaps: scans arrive one at a time.

``Session(config, voxel)``; ``add_scan(name, points)`` per scan:

1. its local features, and its global feature from the overlap head (``features.netvlad``: one scan at a time,
   so no scene codebook);
2. its top-``k`` partners among the scans so far by overlap score, each registered (``register_pair``) and,
   with ``Config.refine``, refined on finer grids from that registration as the batch refines its edges
   (``refine.refine_pair``, kept when it ``confirms``), with the calibrated information
   (``registration.information``);
3. ``add_node``: the back end alone (also for callers with their own front end). The scan is placed by its
   heaviest edge to a placed scan, its edges become ``BetweenFactorPose3`` in a ``gtsam.ISAM2``, and one
   update runs. A scan with no edge to a placed scan waits, and is placed when a later scan connects it.
4. Contradiction: where the new scan's edges propose different placements, those agreeing with the placement
   most of their weight proposes are kept and the rest rejected (``sync.consensus`` tolerances); when no
   placement has a majority, or a kept new edge is not consistent with the updated poses (``sync.consensus.consistent_edges``:
   off by more than the registration tolerances and more than its own noise), the robust stage re-runs
   (``synchronize`` with the ``Config``'s method and polish, over every edge so far) and ISAM2 restarts from
   its poses and the edges it kept.

Factors carry each edge's calibrated information, as the batch polish's do (``factor_graph.edge_information``),
so a session fed every scan ends where batch synchronization of the same registrations does.
``run_result()`` returns a ``RunResult`` for ``gtsam_api`` and the writers (covariances from the calibrated
information, as for a batch run).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import gtsam
import numpy as np

from .config import Config
from .features.local import ScanFeatures, compute_features
from .features.netvlad import global_features, load_default_head
from .gtsam_api import noise_model
from .registration.pairwise import PairResult, register_pair
from .registration.refine import Pyramid, build_pyramid, confirms, refine_pair
from .result import RunResult
from .se3 import inv_T
from .sync import synchronize
from .se3 import rotation_angle
from .sync.consensus import MAX_DEG, consistent_edges, translation_tolerance
from .sync.rotation import connected_components, rotation_residuals
from .types import InputError, PoseGraph, SyncResult

PRIOR_PRECISION = 1e12
"""Anchor prior precision (the first scan is the world), stiff next to any edge of the weighted graph."""
RELINEARIZE = 1e-6
"""ISAM2 relinearizes a variable whose update exceeds this (radians / scene units), at every update: the
default (0.1 every 10th update) stops short of the batch optimum by more than a bunny registration's error."""


@dataclass
class Edge:
    """A registered pair: ``T`` maps scan ``j`` into scan ``i``; ``weight`` is ``w⁰`` (score × inliers)."""

    i: int
    j: int
    T: np.ndarray
    weight: float
    information: np.ndarray
    kept: bool = True  # False once the robust stage rejected it
    in_isam: bool = False  # its factor is in ISAM2


@dataclass
class Step:
    """What ``add_scan`` / ``add_node`` did: the new node's index, its edges, whether it (and any scan that
    waited) got placed, whether the robust stage re-ran, and the seconds of the front and back end."""

    node: int
    edges: int
    placed: bool
    robust: bool
    front_seconds: float = 0.0
    back_seconds: float = 0.0


@dataclass
class Session:
    """Scans in, poses out, one scan at a time (module doc). ``voxel``: the grid size in scene units (as
    ``Config.voxel``; it cannot be derived from scans not seen yet)."""

    config: Config
    voxel: float
    names: list[str] = field(default_factory=list)
    features: list[ScanFeatures] = field(default_factory=list)
    edges: list[Edge] = field(default_factory=list)
    pairs: list[PairResult] = field(default_factory=list)
    robust_runs: int = 0

    def __post_init__(self) -> None:
        self.config.validate()
        if not (self.voxel > 0):
            raise InputError(f"voxel must be positive; got {self.voxel!r}")
        self._head = None
        self._F: list[np.ndarray] = []
        self._pyramids: list[Pyramid | None] = []  # the refinement grids, None without Config.refine
        self._placed: dict[int, np.ndarray] = {}
        self._reset_isam()

    # --- front end -------------------------------------------------------------------------------
    def add_scan(self, name: str, points: np.ndarray) -> Step:
        """Register scan ``points`` (P, 3) against its top-k partners so far and update the poses."""
        start = time.perf_counter()
        cfg = self.config
        try:
            f = compute_features(np.asarray(points, dtype=float), self.voxel, cfg.normal_radius, cfg.fpfh_radius,
                                 descriptor=cfg.descriptor)
        except InputError as e:
            raise InputError(f"{name}: {e}") from None
        if self._head is None:
            self._head = load_default_head(cfg.overlap_head)
        F = global_features(self._head, [f.fpfh], seed=cfg.seed)[0]
        self.features.append(f)
        self._F.append(F)
        scores = (np.array([F @ G for G in self._F[:-1]]) + 1.0) / 2.0
        found = []
        pyramid = build_pyramid(points, self.voxel) if cfg.refine else None
        self._pyramids.append(pyramid)
        for i in np.argsort(-scores, kind="stable")[: cfg.k]:
            pair = register_pair(self.features[i], f, self.voxel, matcher=cfg.matcher,
                                 icp_distance=cfg.icp_distance, seed=cfg.seed)
            if pair.inliers >= cfg.inlier_bar and cfg.refine:
                # The batch's refinement, from the registration itself: the session has no synchronized
                # guess before the scan is placed, and from either start ICP lands in the same basin.
                refined, near = refine_pair(self.features[i], f, self._pyramids[i], pyramid, pair.T, self.voxel,
                                            cfg.icp_distance, pair.matches)
                if confirms(refined, near, cfg.inlier_bar):
                    pair = refined
            self.pairs.append(pair)
            if pair.inliers >= cfg.inlier_bar and pair.information is not None:
                found.append((int(i), pair.T, float(scores[i] * pair.inliers), pair.information))
        front = time.perf_counter() - start
        step = self.add_node(name, found)
        step.front_seconds = front
        return step

    # --- back end --------------------------------------------------------------------------------
    def add_node(self, name: str, edges: list[tuple[int, np.ndarray, float, np.ndarray]]) -> Step:
        """Add node ``len(names)`` named ``name`` with ``edges`` ``(partner, T_partner_new, w⁰, information)``
        (information in gtsam order, calibrated) and update the poses."""
        start = time.perf_counter()
        node = len(self.names)
        self.names.append(name)
        new = []
        for i, T, w, info in edges:
            if not 0 <= i < node:
                raise InputError(f"{name}: edge to unknown node {i}")
            self.edges.append(Edge(i, node, np.asarray(T, dtype=float), float(w), np.asarray(info, dtype=float)))
            new.append(len(self.edges) - 1)
        robust = False
        if node == 0:
            self._place(0, np.eye(4))
            self._isam_add([], {0: np.eye(4)}, prior=True)
        else:
            robust = not self._local_consensus(node, new)
            if not robust:
                self._place_waiting()
                robust = self._contradicted(new)
            if robust:
                self._robust()
        return Step(node, len(new), node in self._placed, robust, back_seconds=time.perf_counter() - start)

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) current poses, scan 0 exactly the identity; NaN for scans not placed yet."""
        out = np.full((len(self.names), 4, 4), np.nan)
        estimate = self._isam.calculateEstimate()
        for k in self._placed:
            out[k] = estimate.atPose3(k).matrix()
        if len(out):  # the stiff but finite prior leaves scan 0 a hair off the identity
            out = inv_T(out[0])[None] @ out
        return out

    def graph(self) -> PoseGraph:
        """Every edge so far as a ``PoseGraph`` (``information``: the calibrated one)."""
        e = self.edges
        return PoseGraph(n=len(self.names), i=np.array([x.i for x in e], dtype=np.int64),
                         j=np.array([x.j for x in e], dtype=np.int64),
                         T=np.stack([x.T for x in e]) if e else np.zeros((0, 4, 4)),
                         weight=np.array([x.weight for x in e]),
                         information=np.stack([x.information for x in e]) if e else None)

    def run_result(self) -> RunResult:
        """The session as a ``RunResult`` (world = the first scan; scans not placed are unregistered)."""
        poses = self.poses
        graph = self.graph()
        n = len(self.names)
        kept = np.array([x.kept and x.i in self._placed and x.j in self._placed for x in self.edges], dtype=bool)
        placed = np.isin(np.arange(n), list(self._placed))
        component = connected_components(n, graph.i, graph.j, kept)
        component = np.where(placed, 0, component + 1)  # every placed scan hangs off scan 0
        poses = np.where(placed[:, None, None], poses, np.eye(4))
        weights = np.where(kept, graph.weight, 0.0)
        residual = np.degrees(rotation_residuals(poses[:, :3, :3], graph.i, graph.j, graph.T[:, :3, :3]))
        F = np.stack(self._F) if self._F else np.zeros((0, 1))
        sync = SyncResult(poses=poses, weights=weights, residual_deg=residual, component=component)
        return RunResult(names=list(self.names), poses=poses, voxel=self.voxel, scores=(F @ F.T + 1.0) / 2.0,
                         graph=graph, pairs=[], sync=sync,
                         unregistered=[self.names[k] for k in range(n) if not placed[k]], skipped={},
                         features=list(self.features), global_feature="learned NetVLAD head, one scan at a time")

    # --- internals -------------------------------------------------------------------------------
    def _reset_isam(self) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(RELINEARIZE)
        params.relinearizeSkip = 1
        self._isam = gtsam.ISAM2(params)

    def _factor(self, e: Edge) -> gtsam.BetweenFactorPose3:
        kernel = self.config.kernel if self.config.kernel != "tls" else "none"
        return gtsam.BetweenFactorPose3(e.i, e.j, gtsam.Pose3(e.T), noise_model(e.information, kernel))

    def _isam_add(self, edges: list[int], values: dict[int, np.ndarray], prior: bool = False) -> None:
        factors = gtsam.NonlinearFactorGraph()
        for k in edges:
            factors.add(self._factor(self.edges[k]))
        if prior:
            factors.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(), gtsam.noiseModel.Isotropic.Precision(6, PRIOR_PRECISION)))
        initial = gtsam.Values()
        for k, T in values.items():
            initial.insert(k, gtsam.Pose3(T))
        self._isam.update(factors, initial)

    def _place(self, k: int, T: np.ndarray) -> None:
        self._placed[k] = T

    def _place_waiting(self) -> None:
        """Place every scan with a kept edge to a placed one (heaviest edge first), then add the edges whose
        ends are both placed and not yet in ISAM2."""
        estimate = self._isam.calculateEstimate()
        current = {k: estimate.atPose3(k).matrix() for k in self._placed if estimate.exists(k)}
        new_values: dict[int, np.ndarray] = {}
        moved = True
        while moved:
            moved = False
            best: dict[int, tuple[float, np.ndarray]] = {}
            for e in self.edges:
                if not e.kept:
                    continue
                for a, b, T in ((e.i, e.j, e.T), (e.j, e.i, inv_T(e.T))):
                    if a in self._placed and b not in self._placed and e.weight > best.get(b, (-1.0, None))[0]:
                        best[b] = (e.weight, current.get(a, self._placed[a]) @ T)
            for b, (_, T) in best.items():
                self._place(b, T)
                current[b] = new_values[b] = T
                moved = True
        edges = [k for k, e in enumerate(self.edges)
                 if e.kept and not e.in_isam and e.i in self._placed and e.j in self._placed]
        for k in edges:
            self.edges[k].in_isam = True
        if edges or new_values:
            self._isam_add(edges, new_values)

    def _local_consensus(self, node: int, new: list[int]) -> bool:
        """Where the new scan's edges to placed scans disagree, keep those agreeing with the placement most of
        their weight proposes and reject the rest (a wrong registration of the new scan, settled without the
        batch stage). False when no placement has more than half of the weight: only the batch can tell."""
        linked = [k for k in new if self.edges[k].i in self._placed]
        if len(linked) < 2:
            return True
        estimate = self._isam.calculateEstimate()
        proposals = np.stack([estimate.atPose3(self.edges[k].i).matrix() @ self.edges[k].T for k in linked])
        weights = np.array([self.edges[k].weight for k in linked])
        D = inv_T(proposals)[:, None] @ proposals[None]
        agree = ((np.degrees(rotation_angle(D[..., :3, :3])) <= MAX_DEG)
                 & (np.linalg.norm(D[..., :3, 3], axis=-1) <= translation_tolerance(self.graph())))
        support = agree @ weights
        best = int(np.argmax(support))
        if support[best] <= 0.5 * weights.sum():
            return False
        for k, ok in zip(linked, agree[best]):
            self.edges[k].kept = bool(ok)
        return True

    def _contradicted(self, new: list[int]) -> bool:
        """Does an edge just added disagree with the updated poses?"""
        idx = [k for k in new if self.edges[k].kept and self.edges[k].i in self._placed and self.edges[k].j in self._placed]
        if not idx:
            return False
        graph = self.graph()
        sub = PoseGraph(n=graph.n, i=graph.i[idx], j=graph.j[idx], T=graph.T[idx], weight=graph.weight[idx],
                        information=graph.information[idx])
        poses = np.where(np.isnan(self.poses), 0.0, self.poses)
        # The fixed tolerances scale with the median edge length: measure it on every edge so far.
        return not consistent_edges(sub, poses, max_trans=translation_tolerance(graph)).all()

    def _robust(self) -> None:
        """The batch robust stage over every edge so far; ISAM2 restarts from its poses and kept edges."""
        self.robust_runs += 1
        graph = self.graph()
        cfg = self.config
        result = synchronize(graph, method=cfg.method, iters=cfg.iters, reweight=cfg.reweight, polish=cfg.polish,
                             min_weight=cfg.min_weight)
        main = result.component == result.component[0]  # the world is scan 0's part
        poses = inv_T(result.poses[0])[None] @ result.poses
        for k, e in enumerate(self.edges):
            e.kept = bool(result.weights[k] > 0 and main[e.i] and main[e.j])
            e.in_isam = e.kept
        self._placed = {int(k): poses[k] for k in np.flatnonzero(main)}
        self._reset_isam()
        self._isam_add([k for k, e in enumerate(self.edges) if e.kept], dict(self._placed), prior=True)
