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
   placement has a majority, or a kept new edge is not consistent with the updated poses
   (``sync.consensus.consistent_edges``: off by more than the registration tolerances and more than its own
   noise), the robust stage re-runs (``synchronize`` with the ``Config``'s method and polish, over every edge
   so far) and ISAM2 restarts from its poses and the edges it kept.
5. A caller's own factors join the live ISAM2 graph (a SLAM stack's odometry, GNSS fixes, priors): ``add_between``
   (a ``BetweenFactorPose3``, e.g. an odometry step; it places an end not placed yet), ``add_prior``
   (``PriorFactorPose3``), ``add_position`` (a GNSS fix of a point of a node: ``GPSFactorArm``), each in the input
   frames with its information, or ``add_factor``: any gtsam factor over the nodes' keys (``key``:
   ``gtsam.symbol('x', node)``, as ``gtsam_api.to_gtsam``'s). They are the caller's measurements: the robust stage
   judges the registrations only, and they stay through its restarts.

The world: with ``anchor`` (the default) the first node's frame, held by a stiff prior, so that ``add_prior`` and
``add_position`` are in the first node's frame; without, the caller's own factors fix the world (a prior, or priors
and positions together: a call after which they leave a node free is refused) and ``poses`` are in their frame.
A session needs no ``voxel`` for the back end alone (``add_node`` and the factors); ``add_scan`` does.

Factors carry each edge's calibrated information, as the batch polish's do (``factor_graph.edge_information``),
so a session fed every scan ends where batch synchronization of the same registrations does.
``run_result()`` returns a ``RunResult`` for ``gtsam_api`` and the writers (covariances from the calibrated
information, as for a batch run).

Georeferenced scans (``local_frame``): a scan farther than ``local_frame.FAR_VOXELS`` voxels from the origin is
registered centred at its median, in float64, with its normals towards its input frame's origin, as ``register``
does; the edges and ISAM2 live in those centred frames, and ``poses``, ``graph()`` and ``run_result()`` hand
everything back in the input frames. A node from ``add_node`` has no scan: its frame is its input frame.
``add_prior``, ``add_between`` and ``add_position`` map the caller's measurements into the centred frames; their
information is taken about the scan's centre (``centre``), where a rotation σ means what it says: about the input
frame's origin, thousands of kilometres away, it would bind the translation at the scan to nanoradians (and gtsam
cannot factor such an information). ``add_factor``, which cannot know what a factor measures, refuses such a scan.

A call refused (``InputError``) leaves the session as it was: its input is checked before anything changes, and a
back end that gtsam cannot solve (an information too ill-conditioned to fix the pose) is rolled back.
"""

from __future__ import annotations

import numbers
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np

from sghr_gtsam import local_frame
from sghr_gtsam.config import Config
from sghr_gtsam.features.local import ScanFeatures, compute_features
from sghr_gtsam.features.netvlad import global_features, load_default_head
from sghr_gtsam.gtsam_api import noise_model, pose_covariances
from sghr_gtsam.io.g2o import check_information
from sghr_gtsam.io.poses import unwritable_name
from sghr_gtsam.io.scans import finite_points
from sghr_gtsam.local_frame import graph_to_input_frame, translation
from sghr_gtsam.registration.pairwise import PairResult, register_pair
from sghr_gtsam.registration.refine import Pyramid, build_pyramid, confirms, refine_pair
from sghr_gtsam.result import RunResult
from sghr_gtsam.se3 import inv_T, non_rigid, rotation_angle
from sghr_gtsam.sync import synchronize
from sghr_gtsam.sync.consensus import MAX_DEG, consistent_edges, translation_tolerance
from sghr_gtsam.sync.rotation import connected_components, rotation_residuals
from sghr_gtsam.types import InputError, PoseGraph, SyncResult

PRIOR_PRECISION = 1e12
"""Anchor prior precision (the first scan is the world), stiff next to any edge of the weighted graph."""
SETTLE = 20
"""At most this many more ISAM2 updates after a caller's factor, until none relinearizes: one update is one
Gauss-Newton step, and a prior or a loop far from the current poses takes a few."""
RELINEARIZE = 1e-6
"""ISAM2 relinearizes a variable whose update exceeds this (radians / scene units), at every update: the
default (0.1 every 10th update) stops short of the batch optimum by more than an object scan's registration error."""
EDGE_RIGID_TOL = 1e-6
"""An edge's ``T`` is rigid when ``RᵀR`` is the identity and its last row ``0 0 0 1`` to within this (a
registration's rotation is orthonormal to ~1e-15; a scaled or sheared one is off by far more)."""

EdgeInput = tuple[int, np.ndarray, float, np.ndarray]


@dataclass
class Edge:
    """A registered pair: ``T`` maps scan ``j`` into scan ``i`` (their centred frames, ``Session._centre_rows``);
    ``weight`` is ``w⁰`` (score × inliers); ``pair`` the registration it came from (for a caller's edge from
    ``add_node``: its ``T`` and information, no inliers)."""

    i: int
    j: int
    T: np.ndarray
    weight: float
    information: np.ndarray
    pair: PairResult
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
    ``Config.voxel``, which None falls back to; it cannot be derived from scans not seen yet, and only ``add_scan``
    needs it). ``anchor``: the first node is the world (module doc).
    ``features[k]`` is node k's (in its centred frame), None for a node from ``add_node``; ``pairs`` every
    registration ``add_scan`` ran, kept or not."""

    config: Config
    voxel: float | None
    names: list[str] = field(default_factory=list)
    features: list[ScanFeatures | None] = field(default_factory=list)
    edges: list[Edge] = field(default_factory=list)
    pairs: list[PairResult] = field(default_factory=list)
    robust_runs: int = 0
    anchor: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.config, Config):
            raise InputError(f"config must be a Config; got {type(self.config).__name__}")
        self.config.validate()
        voxel = self.config.voxel if self.voxel is None else self.voxel
        if voxel is None:  # the back end alone: add_scan says what is missing
            self._head = None
            self._start()
            return
        if not _real(voxel):
            raise InputError(f"voxel must be a number (the grid size in scene units); got {voxel!r}")
        if not (np.isfinite(voxel) and voxel > 0):
            raise InputError(f"voxel must be positive and finite; got {voxel!r}")
        self.voxel = float(voxel)
        self._head = None
        self._start()

    def _start(self) -> None:
        self._F: list[np.ndarray | None] = []  # global features, None for a node without a scan
        self._pyramids: list[Pyramid | None] = []  # the refinement grids, None without Config.refine or a scan
        self._centres: list[np.ndarray] = []  # where each node's scan is centred (local_frame)
        self._placed: dict[int, np.ndarray] = {}
        self._factors: list[tuple[gtsam.NonlinearFactor, tuple[int, ...]]] = []  # the caller's, with their nodes
        self._reset_isam()

    @property
    def _centre_rows(self) -> np.ndarray:
        """(N, 3) the point each node's scan is centred at (zero near the origin and for ``add_node``'s nodes)."""
        return np.array(self._centres).reshape(-1, 3)

    # --- front end -------------------------------------------------------------------------------
    def add_scan(self, name: str, points: np.ndarray) -> Step:
        """Register scan ``points`` (P, 3) against its top-k partners so far and update the poses. Rows with a
        non-finite coordinate are dropped (as the batch loader does); fewer than ``Config.min_points`` left is
        an ``InputError``."""
        start = time.perf_counter()
        cfg = self.config
        if self.voxel is None:
            raise InputError(
                "add_scan: give the session a voxel (the grid size in scene units; Config.voxel is not "
                "set either, and a session cannot derive it from scans not seen yet)"
            )
        self._check_name(name)
        try:
            P = np.asarray(points, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"{name}: points must be a numeric (P, 3) array") from None
        if P.ndim != 2 or P.shape[1] != 3:
            raise InputError(f"{name}: points must be (P, 3), got shape {P.shape}")
        P, _ = finite_points(P)
        if len(P) < cfg.min_points:
            raise InputError(f"{name}: only {len(P)} finite points (< min_points {cfg.min_points})")
        centre = local_frame.centres(np.median(P, axis=0)[None], self.voxel)[0]
        P = P - centre
        try:
            f = compute_features(
                P, self.voxel, cfg.normal_radius, cfg.fpfh_radius, sensor=-centre, descriptor=cfg.descriptor
            )
        except InputError as e:
            raise InputError(f"{name}: {e}") from None
        if self._head is None:
            self._head = load_default_head(cfg.overlap_head)
        F = global_features(self._head, [f.fpfh], seed=cfg.seed)[0]
        scanned = [k for k, G in enumerate(self._F) if G is not None]  # add_node's nodes have nothing to match
        scores = (np.array([F @ self._F[k] for k in scanned]) + 1.0) / 2.0
        pyramid = build_pyramid(P, self.voxel) if cfg.refine else None
        tried, edges = [], []
        node = len(self.names)
        for s in np.argsort(-scores, kind="stable")[: cfg.k]:
            i = scanned[s]
            pair = register_pair(
                self.features[i],
                f,
                self.voxel,
                matcher=cfg.matcher,
                icp_distance=cfg.icp_distance,
                seed=cfg.seed,
                min_inliers=cfg.inlier_bar,
            )
            if pair.inliers >= cfg.inlier_bar and cfg.refine:
                # The batch's refinement, from the registration itself: the session has no synchronized
                # guess before the scan is placed, and from either start ICP lands in the same basin.
                refined, converged = refine_pair(
                    self.features[i],
                    f,
                    self._pyramids[i],
                    pyramid,
                    pair.T,
                    self.voxel,
                    cfg.icp_distance,
                    cfg.inlier_bar,
                    pair.matches,
                )
                if confirms(refined, converged, cfg.inlier_bar):
                    pair = refined
            tried.append(pair)
            if pair.inliers >= cfg.inlier_bar and pair.information is not None:
                edges.append(Edge(i, node, pair.T, float(scores[s] * pair.inliers), pair.information, pair))
        front = time.perf_counter() - start
        step = self._add_node(name, centre, f, F, pyramid, edges, tried)
        step.front_seconds = front
        return step

    # --- back end --------------------------------------------------------------------------------
    def add_node(self, name: str, edges: Sequence[EdgeInput]) -> Step:
        """Add node ``len(names)`` named ``name`` with ``edges`` ``(partner, T_partner_new, w⁰, information)``
        (the partner's index; ``T`` rigid 4×4 in the input frames; ``w⁰`` finite ≥ 0; the information 6×6
        symmetric positive definite, as the robust stage's ``sync.checked_graph`` requires, gtsam order,
        calibrated) and update the poses."""
        self._check_name(name)
        node = len(self.names)
        try:
            given = list(edges)
        except TypeError:
            raise InputError(f"{name}: edges must be a list of (partner, T, weight, information)") from None
        checked = []
        for k, edge in enumerate(given):
            try:
                i, T, w, info = edge
            except (TypeError, ValueError):
                raise InputError(f"{name}: edge {k} is not a (partner, T, weight, information) tuple") from None
            what = f"{name}: edge {k}"
            if isinstance(i, bool) or not isinstance(i, numbers.Integral) or not 0 <= i < node:
                raise InputError(f"{what}: partner {i!r} is not the index of a node so far (0..{node - 1})")
            T = _rigid(T, f"{what}: T")
            if not (_real(w) and np.isfinite(w) and w >= 0):
                raise InputError(f"{what}: weight must be a finite number >= 0; got {w!r}")
            info = _information(info, what)
            T = translation(-self._centres[i]) @ T  # the new node has no scan: its centred frame is its input frame
            pair = PairResult(T=T, inliers=0, fitness=float("nan"), rmse=float("nan"), information=info, seconds=0.0)
            checked.append(Edge(int(i), node, T, float(w), info, pair))
        return self._add_node(name, np.zeros(3), None, None, None, checked, [])

    # --- the caller's factors ------------------------------------------------------------------------
    def key(self, node: int | str) -> int:
        """The gtsam key of ``node`` (its index in ``names``, or its name): ``gtsam.symbol('x', index)``."""
        return _key(self._node(node, "key"))

    def centre(self, node: int | str) -> np.ndarray:
        """(3,) where ``node``'s scan was centred in its input frame (module doc): zero near the origin and for a
        node without a scan. A factor's rotation information acts about this point."""
        return self._centres[self._node(node, "centre")].copy()

    def add_factor(self, factor: gtsam.NonlinearFactor) -> None:
        """Add any gtsam factor over placed nodes' keys (``key``) to the live graph and update the poses. It acts in
        the frames ISAM2 holds, which are the input frames (world: module doc) unless a scan was registered centred
        (``local_frame``): then the first node's and that scan's factors go through ``add_prior``,
        ``add_between`` and ``add_position``, which map them."""
        if not isinstance(factor, gtsam.NonlinearFactor):
            raise InputError(f"add_factor: a gtsam factor, please; got {type(factor).__name__}")
        nodes = []
        for k in factor.keys():
            node = _node_of(k, len(self.names))
            if node is None:
                raise InputError(f"add_factor: key {gtsam.DefaultKeyFormatter(k)} is not a node's key (Session.key)")
            if node not in self._placed:
                raise InputError(
                    f"add_factor: node {node} ({self.names[node]}) is not placed yet (add_between or "
                    f"add_prior places it)"
                )
            nodes.append(node)
        centred = [k for k in {0, *nodes} if self._centres[k].any()]
        if centred:
            raise InputError(
                f"add_factor: node {centred[0]} ({self.names[centred[0]]}) was registered centred (far "
                f"from the origin): give its factors by add_prior, add_between or add_position"
            )
        self._add_factor(factor, tuple(nodes), {}, "add_factor")

    def add_prior(self, node: int | str, pose: np.ndarray, information: np.ndarray) -> None:
        """A ``PriorFactorPose3``: ``node``'s pose (rigid 4×4, the input frame into the world) with its 6×6
        information (gtsam order [rotation, translation] at the pose, positive definite; a scan registered centred:
        about its centre, ``centre``). A node not placed yet is placed there."""
        k = self._node(node, "add_prior")
        info = _information(information, "add_prior")
        T = translation(-self._centres[0]) @ _rigid(pose, "add_prior: pose") @ translation(self._centres[k])
        factor = gtsam.PriorFactorPose3(_key(k), gtsam.Pose3(T), noise_model(info))
        self._add_factor(factor, (k,), {} if k in self._placed else {k: T}, "add_prior")

    def add_between(self, a: int | str, b: int | str, T: np.ndarray, information: np.ndarray) -> None:
        """A ``BetweenFactorPose3`` (an odometry step): ``T`` (rigid 4×4) maps ``b``'s input frame into ``a``'s
        (``T_ab = T_a⁻¹ T_b``), with its 6×6 information (gtsam order at ``b``, positive definite; a scan registered
        centred: about its centre, ``centre``). One end may not be placed yet: it is placed from the other."""
        i, j = self._node(a, "add_between"), self._node(b, "add_between")
        if i == j:
            raise InputError(f"add_between: both ends are node {i}")
        info = _information(information, "add_between")
        T = translation(-self._centres[i]) @ _rigid(T, "add_between: T") @ translation(self._centres[j])
        values = {}
        if i in self._placed and j not in self._placed:
            values[j] = self._estimate(i) @ T
        elif j in self._placed and i not in self._placed:
            values[i] = self._estimate(j) @ inv_T(T)
        elif i not in self._placed:
            raise InputError(f"add_between: neither node {i} nor node {j} is placed yet")
        factor = gtsam.BetweenFactorPose3(_key(i), _key(j), gtsam.Pose3(T), noise_model(info))
        self._add_factor(factor, (i, j), values, "add_between")

    def add_position(
        self, node: int | str, position: np.ndarray, information: np.ndarray, point: np.ndarray = (0.0, 0.0, 0.0)
    ) -> None:
        """A GNSS fix (``GPSFactorArm``): ``point`` (3,) of ``node``'s input frame (the antenna; default its origin)
        is at ``position`` (3,) in the world, with its 3×3 information (positive definite). It leaves the rotation
        free, so it cannot place a node: the node must be placed already."""
        k = self._node(node, "add_position")
        q = _array(position, (3,), "add_position: position")
        p = _array(point, (3,), "add_position: point")
        info = _array(information, (3, 3), "add_position: information")
        info = (info + info.T) / 2.0
        if (
            np.abs(info - np.asarray(information, dtype=float)).max() > 1e-9 * np.abs(info).max()
            or np.linalg.eigvalsh(info)[0] <= 0
        ):
            raise InputError("add_position: information is not symmetric positive definite")
        if k not in self._placed:
            raise InputError(
                f"add_position: node {k} ({self.names[k]}) is not placed yet (a position leaves its "
                f"rotation free: add_prior or add_between places it)"
            )
        factor = gtsam.GPSFactorArm(
            _key(k), q - self._centres[0], p - self._centres[k], gtsam.noiseModel.Gaussian.Information(info)
        )
        self._add_factor(factor, (k,), {}, "add_position")

    @property
    def poses(self) -> np.ndarray:
        """(N, 4, 4) current poses in the input frames into the world (module doc): with ``anchor`` scan 0 exactly the
        identity; NaN for scans not placed yet."""
        c = self._centre_rows
        # anchored, scan 0: S(c₀) S(-c₀), exactly the identity
        return translation(c[:1]) @ self._local_poses(self.anchor) @ translation(-c)

    def graph(self) -> PoseGraph:
        """Every edge so far as a ``PoseGraph`` in the input frames (``information``: the calibrated one)."""
        g = self._graph()
        graph_to_input_frame(g, self._centre_rows)
        return g

    def run_result(self) -> RunResult:
        """The session as a ``RunResult`` in the input frames (world = the first scan, also without ``anchor``; scans
        not placed are unregistered; the caller's factors are not in it), each edge with its registration in ``pairs``
        and the pose covariances computed in the centred frames. A node from ``add_node`` has no points (an empty
        grid in ``features``)."""
        n = len(self.names)
        if not n:
            raise InputError("run_result: the session has no scans yet")
        graph = self._graph()
        kept = np.array([x.kept and x.i in self._placed and x.j in self._placed for x in self.edges], dtype=bool)
        placed = np.isin(np.arange(n), list(self._placed))
        component = connected_components(n, graph.i, graph.j, kept)
        component = np.where(placed, 0, component + 1)  # every placed scan hangs off scan 0
        poses = np.where(placed[:, None, None], self._local_poses(True), np.eye(4))
        weights = np.where(kept, graph.weight, 0.0)
        residual = np.degrees(rotation_residuals(poses[:, :3, :3], graph.i, graph.j, graph.T[:, :3, :3]))
        scores = np.full((n, n), np.nan)  # unknown where a node has no scan
        scanned = [k for k, F in enumerate(self._F) if F is not None]
        if scanned:
            F = np.stack([self._F[k] for k in scanned])
            scores[np.ix_(scanned, scanned)] = (F @ F.T + 1.0) / 2.0
        voxel = float("nan") if self.voxel is None else self.voxel  # the back end alone: no grid
        features = [f if f is not None else _no_points(voxel) for f in self.features]
        sync = SyncResult(poses=poses.copy(), weights=weights, residual_deg=residual, component=component)
        out = RunResult(
            names=list(self.names),
            poses=poses,
            voxel=voxel,
            scores=scores,
            graph=graph,
            pairs=[e.pair for e in self.edges],
            sync=sync,
            unregistered=[self.names[k] for k in range(n) if not placed[k]],
            skipped={},
            features=features,
            global_feature="learned NetVLAD head, one scan at a time",
        )
        out.covariances = np.full((n, 6, 6), np.nan)
        if weights.any():
            try:
                out.covariances = pose_covariances(out)
            except RuntimeError:  # gtsam: the kept edges leave a pose's marginal indeterminate (as in a batch run)
                pass
        out.covariances[0] = 0.0  # the world scan, also when no edge is kept
        local_frame.to_input_frame(out, self._centre_rows)
        return out

    # --- internals -------------------------------------------------------------------------------
    def _node(self, node: object, what: str) -> int:
        """``node`` (an index in ``names`` or a name) as an index, else a one-line ``InputError``."""
        if isinstance(node, str):
            if node not in self.names:
                raise InputError(f"{what}: no node is named {node!r}")
            return self.names.index(node)
        if isinstance(node, bool) or not isinstance(node, numbers.Integral) or not 0 <= node < len(self.names):
            raise InputError(f"{what}: {node!r} is not the index of a node so far (0..{len(self.names) - 1})")
        return int(node)

    def _add_factor(
        self, factor: gtsam.NonlinearFactor, nodes: tuple[int, ...], values: dict[int, np.ndarray], what: str
    ) -> None:
        """Add the caller's checked ``factor`` on ``nodes`` (placing ``values``' nodes there first), settle, and place
        any scan that waited for them; all undone if gtsam cannot solve it."""
        saved = self._save()
        try:
            for k, T in values.items():
                self._place(k, T)
            self._factors.append((factor, nodes))
            self._isam_add([], values, extra=[factor])
            self._settle()
            self._place_waiting()
        except BaseException as e:
            self._restore(saved)
            if isinstance(e, RuntimeError):  # gtsam: an indeterminate system
                first = (str(e).strip() or type(e).__name__).splitlines()[0]
                raise InputError(f"{what}: the back end cannot take it ({first})") from None
            raise

    def _settle(self) -> None:
        for _ in range(SETTLE):
            if not self._isam.update().getVariablesRelinearized():
                break

    def _estimate(self, k: int) -> np.ndarray:
        """Node ``k``'s current pose in ISAM2 (centred frames)."""
        return self._isam.calculateEstimate().atPose3(_key(k)).matrix()

    def _check_name(self, name: str) -> None:
        """``InputError`` unless ``name`` is new and reads back from a pose file (one name a line, stripped, '#'
        starting a comment: ``io.poses``)."""
        if why := unwritable_name(name):
            raise InputError(
                f"scan name {name!r} {why} (a pose file: one name a line, read back stripped, '#' starting a comment)"
            )
        if name in self.names:
            raise InputError(f"scan name {name!r} is already in the session (node {self.names.index(name)})")

    def _add_node(
        self,
        name: str,
        centre: np.ndarray,
        features: ScanFeatures | None,
        F: np.ndarray | None,
        pyramid: Pyramid | None,
        edges: list[Edge],
        tried: list[PairResult],
    ) -> Step:
        """Append the node and its checked ``edges`` (centred frames) and run the back end; all undone if it fails."""
        start = time.perf_counter()
        saved = self._save()
        node = len(self.names)
        self.names.append(name)
        self._centres.append(centre)
        self.features.append(features)
        self._F.append(F)
        self._pyramids.append(pyramid)
        new = list(range(len(self.edges), len(self.edges) + len(edges)))
        self.edges.extend(edges)
        try:
            robust = self._update(node, new)
        except BaseException as e:
            self._restore(saved)
            if isinstance(e, (RuntimeError, InputError)):  # gtsam (an indeterminate system), the robust stage's checks
                first = (str(e).strip() or type(e).__name__).splitlines()[0]
                raise InputError(f"{name}: the back end cannot place it ({first})") from None
            raise
        self.pairs.extend(tried)
        return Step(node, len(new), node in self._placed, robust, back_seconds=time.perf_counter() - start)

    def _update(self, node: int, new: list[int]) -> bool:
        """Place node ``node`` with its ``new`` edges; whether the robust stage ran."""
        if node == 0:
            self._place(0, np.eye(4))
            self._isam_add([], {0: np.eye(4)}, prior=self.anchor)
            return False
        robust = not self._local_consensus(node, new)
        if not robust:
            self._place_waiting()
            robust = self._contradicted(new)
        if robust:
            self._robust()
        return robust

    def _save(self) -> tuple:
        """What ``_add_node`` changes, to undo it (gtsam's ISAM2 copy constructor copies its Bayes tree)."""
        return (
            len(self.names),
            len(self.edges),
            [(e.kept, e.in_isam) for e in self.edges],
            dict(self._placed),
            self.robust_runs,
            gtsam.ISAM2(self._isam),
            len(self._factors),
        )

    def _restore(self, saved: tuple) -> None:
        """The session as ``_save`` found it."""
        n, m, flags, placed, runs, isam, factors = saved
        del self._factors[factors:]
        for column in (self.names, self._centres, self.features, self._F, self._pyramids):
            del column[n:]
        del self.edges[m:]
        for e, (kept, in_isam) in zip(self.edges, flags):
            e.kept, e.in_isam = kept, in_isam
        self._placed, self.robust_runs, self._isam = placed, runs, isam

    def _local_poses(self, relative: bool) -> np.ndarray:
        """(N, 4, 4) the poses in the centred frames, with ``relative`` scan 0 exactly the identity; NaN for scans
        not placed."""
        out = np.full((len(self.names), 4, 4), np.nan)
        estimate = self._isam.calculateEstimate()
        for k in self._placed:
            out[k] = estimate.atPose3(_key(k)).matrix()
        if relative and len(out):  # the stiff but finite prior leaves scan 0 a hair off the identity
            out = inv_T(out[0])[None] @ out
            out[0] = np.eye(4)
        return out

    def _graph(self) -> PoseGraph:
        """Every edge so far as a ``PoseGraph`` in the centred frames."""
        e = self.edges
        return PoseGraph(
            n=len(self.names),
            i=np.array([x.i for x in e], dtype=np.int64),
            j=np.array([x.j for x in e], dtype=np.int64),
            T=np.stack([x.T for x in e]) if e else np.zeros((0, 4, 4)),
            weight=np.array([x.weight for x in e]),
            information=np.stack([x.information for x in e]) if e else None,
        )

    def _reset_isam(self) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(RELINEARIZE)
        params.relinearizeSkip = 1
        self._isam = gtsam.ISAM2(params)

    def _factor(self, e: Edge) -> gtsam.BetweenFactorPose3:
        kernel = self.config.kernel if self.config.kernel != "tls" else "none"
        return gtsam.BetweenFactorPose3(_key(e.i), _key(e.j), gtsam.Pose3(e.T), noise_model(e.information, kernel))

    def _isam_add(
        self,
        edges: list[int],
        values: dict[int, np.ndarray],
        prior: bool = False,
        extra: Sequence[gtsam.NonlinearFactor] = (),
    ) -> None:
        """One ISAM2 update with ``edges``' factors, ``extra`` ones, the anchor's prior with ``prior``, and
        ``values`` (node -> initial pose)."""
        factors = gtsam.NonlinearFactorGraph()
        for k in edges:
            factors.add(self._factor(self.edges[k]))
        for factor in extra:
            factors.add(factor)
        if prior:
            stiff = gtsam.noiseModel.Isotropic.Precision(6, PRIOR_PRECISION)
            factors.add(gtsam.PriorFactorPose3(_key(0), gtsam.Pose3(), stiff))
        initial = gtsam.Values()
        for k, T in values.items():
            initial.insert(_key(k), gtsam.Pose3(T))
        self._isam.update(factors, initial)

    def _place(self, k: int, T: np.ndarray) -> None:
        self._placed[k] = T

    def _place_waiting(self) -> None:
        """Place every scan with a kept edge to a placed one (heaviest edge first), then add the edges whose
        ends are both placed and not yet in ISAM2."""
        estimate = self._isam.calculateEstimate()
        current = {k: estimate.atPose3(_key(k)).matrix() for k in self._placed if estimate.exists(_key(k))}
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
        edges = [
            k
            for k, e in enumerate(self.edges)
            if e.kept and not e.in_isam and e.i in self._placed and e.j in self._placed
        ]
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
        proposals = np.stack([estimate.atPose3(_key(self.edges[k].i)).matrix() @ self.edges[k].T for k in linked])
        weights = np.array([self.edges[k].weight for k in linked])
        D = inv_T(proposals)[:, None] @ proposals[None]
        agree = (np.degrees(rotation_angle(D[..., :3, :3])) <= MAX_DEG) & (
            np.linalg.norm(D[..., :3, 3], axis=-1) <= translation_tolerance(self._graph())
        )
        support = agree @ weights
        best = int(np.argmax(support))
        if support[best] <= 0.5 * weights.sum():
            return False
        for k, ok in zip(linked, agree[best]):
            self.edges[k].kept = bool(ok)
        return True

    def _contradicted(self, new: list[int]) -> bool:
        """Does an edge just added disagree with the updated poses?"""
        idx = [
            k for k in new if self.edges[k].kept and self.edges[k].i in self._placed and self.edges[k].j in self._placed
        ]
        if not idx:
            return False
        graph = self._graph()
        sub = PoseGraph(
            n=graph.n,
            i=graph.i[idx],
            j=graph.j[idx],
            T=graph.T[idx],
            weight=graph.weight[idx],
            information=graph.information[idx],
        )
        poses = np.nan_to_num(self._local_poses(True))
        # The fixed tolerances scale with the median edge length: measure it on every edge so far.
        return not consistent_edges(sub, poses, max_trans=translation_tolerance(graph)).all()

    def _robust(self) -> None:
        """The batch robust stage over every edge so far; ISAM2 restarts from its poses, its kept edges and the
        caller's factors. Scan 0's part is placed as the stage places it (in the caller's world without ``anchor``,
        through scan 0's current pose); a part that the caller's factors hold too, through its first node placed."""
        self.robust_runs += 1
        graph = self._graph()
        cfg = self.config
        result = synchronize(
            graph,
            method=cfg.method,
            iters=cfg.iters,
            reweight=cfg.reweight,
            polish=cfg.polish,
            min_weight=cfg.min_weight,
        )
        estimate = self._isam.calculateEstimate()
        before = {k: estimate.atPose3(_key(k)).matrix() for k in self._placed}
        parts = {int(result.component[0]): 0}  # part -> its node placed before, through which it is placed again
        for _, nodes in self._factors:
            for k in nodes:
                parts.setdefault(int(result.component[k]), k)
        keep = np.isin(result.component, list(parts))
        poses = np.full_like(result.poses, np.nan)
        for part, ref in parts.items():
            at = before[ref] if (ref or not self.anchor) else np.eye(4)
            members = result.component == part
            poses[members] = at @ inv_T(result.poses[ref]) @ result.poses[members]
        for k, e in enumerate(self.edges):
            e.kept = bool(result.weights[k] > 0 and keep[e.i] and keep[e.j])
            e.in_isam = e.kept
        self._placed = {int(k): poses[k] for k in np.flatnonzero(keep)}
        self._reset_isam()
        self._isam_add(
            [k for k, e in enumerate(self.edges) if e.kept],
            dict(self._placed),
            prior=self.anchor,
            extra=[factor for factor, _ in self._factors],
        )
        if self._factors:
            self._settle()


def _key(node: int) -> int:
    """Node ``node``'s gtsam key: ``gtsam.symbol('x', node)``, as ``gtsam_api.to_gtsam``'s default."""
    return gtsam.symbol("x", node)


def _node_of(key: int, n: int) -> int | None:
    """The node of gtsam ``key`` among ``n`` nodes, None for another key."""
    symbol = gtsam.Symbol(key)
    return int(symbol.index()) if symbol.chr() == ord("x") and symbol.index() < n else None


def _real(x: object) -> bool:
    """A real number, not a bool (``True`` is an int to Python, never a voxel or a weight)."""
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _array(value: object, shape: tuple[int, ...], what: str) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``, else a one-line ``InputError`` naming ``what``."""
    size = "x".join(map(str, shape))
    try:
        M = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a numeric {size} array") from None
    if M.shape != shape:
        raise InputError(f"{what} must be {size}; got shape {M.shape}")
    if not np.isfinite(M).all():
        raise InputError(f"{what} has non-finite entries")
    return M


def _rigid(value: object, what: str) -> np.ndarray:
    """``value`` as a rigid 4×4 transform (``EDGE_RIGID_TOL``): a scale, shear or reflection would reach the poses."""
    T = _array(value, (4, 4), what)
    if non_rigid(T, EDGE_RIGID_TOL, EDGE_RIGID_TOL):
        raise InputError(f"{what} is not a rigid transform (rotation orthonormal with det +1, last row 0 0 0 1)")
    return T


def _information(value: object, what: str) -> np.ndarray:
    """``value`` as a 6×6 information as the g2o files hold it (``io.g2o.check_information``), made exactly
    symmetric, and positive definite: a direction it leaves free would stop every later robust stage
    (``sync.checked_graph`` refuses the graph)."""
    try:
        info = check_information(value)
    except InputError as e:
        raise InputError(f"{what}: {e}") from None
    info = (info + info.T) / 2.0
    if np.linalg.eigvalsh(info)[0] <= 0:
        raise InputError(f"{what}: information is not positive definite")
    return info


def _no_points(voxel: float) -> ScanFeatures:
    """The features of a node without a scan (``add_node``): an empty grid."""
    empty = np.zeros((0, 3))
    return ScanFeatures(empty, empty, None, voxel, empty, np.zeros((0, 33), dtype=np.float32))
