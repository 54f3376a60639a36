"""Data passed between the pipeline stages. Frame convention: ``T_ij`` maps points of scan j into
the frame of scan i; ``T_i`` maps scan i into the world; ``T_ij = inv(T_i) @ T_j`` (gtsam ``between``)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field

import numpy as np

from sghr_gtsam.errors import InputError  # noqa: F401 - re-exported: the stages import it with the types


@dataclass
class Keypoints:
    """Local features of one scan computed elsewhere (e.g. the SGHR authors' YOHO): ``points`` (K, 3)
    float64 keypoints in the scan's own frame, ``descriptors`` (K, D) float32, row k describing point k.
    Construction checks shapes and values and raises a one-line ``InputError``."""

    points: np.ndarray
    descriptors: np.ndarray

    def __post_init__(self) -> None:
        for label, a, columns in (("keypoints", self.points, "3"), ("descriptors", self.descriptors, "D")):
            if not isinstance(a, np.ndarray) or a.dtype.kind not in "iuf":
                raise InputError(f"{label} are not a numeric array ({getattr(a, 'dtype', type(a).__name__)})")
            if a.ndim != 2 or a.size == 0:
                raise InputError(f"{label} have shape {a.shape}, expected a non-empty (K, {columns}) array")
            if not np.isfinite(a).all():
                raise InputError(f"{label} hold {int(np.count_nonzero(~np.isfinite(a)))} non-finite values")
        if self.points.shape[1] != 3:
            raise InputError(f"keypoints have shape {self.points.shape}, expected (K, 3)")
        if len(self.points) != len(self.descriptors):
            raise InputError(f"{len(self.points)} keypoints but {len(self.descriptors)} descriptors")
        self.points = np.ascontiguousarray(self.points, dtype=np.float64)
        self.descriptors = np.ascontiguousarray(self.descriptors, dtype=np.float32)


@dataclass(frozen=True, eq=False)
class ScanStats:
    """What the checks before registration need of a scan's points, so that the points need not be held: the
    count of finite ``points``, ``extent`` (the diagonal of the box of their 1st-99th percentiles: the unit check),
    ``span`` (their bounding box's diagonal: the stray-point check and the default voxel), ``median`` (3,) (where a
    georeferenced scan is centred) and ``digest`` (sha1 of the points as float64: duplicates, the resume cache)."""

    points: int
    extent: float
    span: float
    median: np.ndarray
    digest: str

    @classmethod
    def of(cls, points: np.ndarray) -> ScanStats:
        """The statistics of finite (P, 3) float64 ``points``; column by column, so that the percentiles' working
        copy is a third of the points."""
        low, high, median = np.zeros(3), np.zeros(3), np.zeros(3)
        for k in range(3):
            column = points[:, k].copy()
            median[k] = np.median(column, overwrite_input=True)
            low[k], high[k] = np.percentile(column, [1, 99], overwrite_input=True)
        span = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
        return cls(len(points), float(np.linalg.norm(high - low)), span, median, _digest(points))


def _digest(points: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(points)).hexdigest()


@dataclass(eq=False)
class Scan:
    """One scan to register: its ``name``; its ``source``, a scan file (read when a stage needs its points, by
    ``io.scans.load_scan``) or its (P, 3) points given in memory; optional ``keypoints`` given with it (they
    replace FPFH), in the same frame; the ``centre`` (3,) the stages see it moved by (set by the pipeline for
    georeferenced scans); and its ``stats``, when known (``load_scene`` keeps them from its one reading)."""

    name: str
    source: str | os.PathLike | np.ndarray
    keypoints: Keypoints | None = None
    centre: np.ndarray = field(default_factory=lambda: np.zeros(3))
    stats: ScanStats | None = None

    def input_points(self) -> np.ndarray:
        """The scan's finite points in its input frame, (P, 3) float64, read from its file if it has one
        (``InputError`` when it cannot be read or would not fit in memory: ``io.scans.check_memory``)."""
        from sghr_gtsam.io.scans import check_memory, finite_points, load_scan  # io builds on this module

        if isinstance(self.source, (str, os.PathLike)):
            check_memory(self.source)
            points = load_scan(self.source)
        else:
            points = np.asarray(self.source, dtype=np.float64)
            if points.ndim != 2 or points.shape[1] != 3:
                raise InputError(f"scan {self.name}: points must be (N, 3), got shape {points.shape}")
        points, _ = finite_points(points)
        if not len(points):
            raise InputError(f"scan {self.name} has no finite points")
        return points

    def statistics(self) -> ScanStats:
        """``stats``, or computed from the points when not known (reading the scan once)."""
        return self.stats if self.stats is not None else ScanStats.of(self.input_points())

    def read(self) -> tuple[np.ndarray, Keypoints | None]:
        """The scan's finite points and its given keypoints (or None), both moved by ``-centre``, in float64."""
        given = self.keypoints
        if given is not None and self.centre.any():
            given = Keypoints(given.points - self.centre, given.descriptors)
        points = self.input_points()
        # The resume cache files a scan's results under the digest of its points as first read: a file changed since
        # would put other points' results under that key (a wrong answer for every later run).
        if self.stats is not None and _digest(points) != self.stats.digest:
            raise InputError(f"scan {self.name} changed while the run was using it: start the run again")
        return points - self.centre, given


@dataclass
class PoseGraph:
    """Relative-pose measurements between ``n`` nodes.

    ``i, j``: (E,) node indices; ``T``: (E, 4, 4) measured ``T_ij``; ``weight``: (E,) initial weight
    ``w0`` (SGHR: overlap score x inlier count); ``information``: optional (E, 6, 6) in gtsam's tangent
    order [rotation, translation], used instead of ``weight`` by the least-squares back ends.
    """

    n: int
    i: np.ndarray
    j: np.ndarray
    T: np.ndarray
    weight: np.ndarray
    information: np.ndarray | None = None

    @property
    def num_edges(self) -> int:
        return int(len(self.i))


@dataclass
class IterationRecord:
    """State after one IRLS iteration, robust-polish stage or LM iteration, for the recording and the report."""

    stage: str  # "irls", "consensus", "gnc", "loops/irls", "loops/grow", "loops/odds" or "lm"
    iteration: int
    poses: np.ndarray  # (N, 4, 4) T_i
    weights: np.ndarray  # (E,)
    residual_deg: np.ndarray  # (E,) rotation residual of each edge, degrees
    cost: float = float("nan")


@dataclass
class SyncResult:
    """Output of synchronization: absolute poses, final edge weights and the per-iteration history.

    ``component``: (N,) label of each node's connected part (0 = largest); every part is anchored at
    one of its own nodes, so poses of different parts are not comparable.
    """

    poses: np.ndarray  # (N, 4, 4)
    weights: np.ndarray  # (E,)
    residual_deg: np.ndarray  # (E,)
    component: np.ndarray  # (N,)
    history: list[IterationRecord] = field(default_factory=list)
    loop_support: np.ndarray | None = None  # (E,) consistent triangles per edge (polish "loops"), else None
    held: np.ndarray | None = None
    """(E,) bool (polish "loops"), else None: kept edges past the consistency tolerances, kept because they alone
    join two parts (``sync._holding``); no loop checks the placement they give (``sync.unverified``)."""
