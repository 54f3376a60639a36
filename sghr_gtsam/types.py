"""Data passed between the pipeline stages. Frame convention: ``T_ij`` maps points of scan j into
the frame of scan i; ``T_i`` maps scan i into the world; ``T_ij = inv(T_i) @ T_j`` (gtsam ``between``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class InputError(ValueError):
    """Bad user input; the CLI prints its message on one line and exits non-zero."""


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

    stage: str  # "irls", "consensus", "gnc", "loops/irls", "loops/grow" or "lm"
    iteration: int
    poses: np.ndarray  # (N, 4, 4) T_i
    weights: np.ndarray  # (E,)
    residual_deg: np.ndarray  # (E,) rotation residual of each edge, degrees
    cost: float = float("nan")


@dataclass
class SyncResult:
    """Output of synchronization: absolute poses, final edge weights and the per-iteration history.

    ``component``: (N,) label of each node's connected part (0 = largest); every part is anchored at
    its own first node, so poses of different parts are not comparable.
    """

    poses: np.ndarray  # (N, 4, 4)
    weights: np.ndarray  # (E,)
    residual_deg: np.ndarray  # (E,)
    component: np.ndarray  # (N,)
    history: list[IterationRecord] = field(default_factory=list)
    loop_support: np.ndarray | None = None  # (E,) consistent triangles per edge (polish "loops"), else None
