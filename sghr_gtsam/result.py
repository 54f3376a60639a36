"""What a run produced (``RunResult``), shared by the pipeline that fills it and the writers that save it."""

from __future__ import annotations

import resource
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from .features.local import ScanFeatures
from .registration.pairwise import PairResult
from .se3 import transform_points
from .types import PoseGraph, SyncResult


FLAGS = {"unregistered": "", "unverified": "pose rests on one registration, or one scan, that no loop checks",
         "contested": "dropped registrations outweigh the kept ones",
         "ambiguous": "dropped registrations agree on another placement that free space cannot rule out",
         "contradicted": "placed where other scans saw empty space",
         "underdetermined": "not fixed to a voxel in some direction"}
"""Each way a run can doubt a scan (a ``RunResult`` field naming the scans), in the order they are reported,
with what it means in a line."""
DOUBTS = tuple(flag for flag in FLAGS if flag != "unregistered")
"""The flags a placed scan can carry."""


@dataclass
class RunResult:
    """Everything a run produced; ``poses[k]`` maps ``names[k]`` into the world (the frame of the
    first scan of the largest connected part). Scans in ``unregistered`` have no reliable pose; scans in
    ``unverified`` have one that rests on a single registration, or a single scan's registrations, that no loop
    checks (``sync.unverified``), or that are held mostly to scans the free space contradicts
    (``registration.visibility.held_by_contradicted``); scans in
    ``contested`` have one against which the graph holds more registration evidence than for it
    (``sync.contested``); scans in ``ambiguous`` have another placement that dropped registrations agree on and the
    scans' free space cannot rule out (``registration.overrule.look_alikes``); scans in ``contradicted`` have one
    that puts them where other scans saw empty space, or them seeing empty space where others are, blamed on the
    scans already doubted first (``registration.visibility.contradicted_placements``); scans in
    ``underdetermined`` have one their edges leave free in some direction."""

    names: list[str]
    poses: np.ndarray
    voxel: float
    scores: np.ndarray
    graph: PoseGraph
    pairs: list[PairResult]
    sync: SyncResult
    unregistered: list[str]
    skipped: dict[str, str]
    features: Sequence[ScanFeatures]
    """Scan k's voxel-grid features at ``features[k]``, in its centred frame. From ``pipeline.register``: read from
    the run's store on access, one scan at a time (``store.Stored``; computed again from the scan when the store's
    temporary folder is gone)."""
    timings: dict[str, float] = field(default_factory=dict)
    global_feature: str = ""
    unverified: list[str] = field(default_factory=list)
    contested: list[str] = field(default_factory=list)
    ambiguous: list[str] = field(default_factory=list)
    contradicted: list[str] = field(default_factory=list)
    edge_origin: list[str] = field(default_factory=list)
    """Per edge of ``graph``: how it entered (``registration.edges.ORIGINS``)."""
    edge_conflict: np.ndarray | None = None
    """(E,) per edge of ``graph``: the free space its transform contradicts (``registration.visibility``; weight 0
    above ``visibility.CONFLICT``), NaN where not checked. None: no check."""
    edge_overruled: np.ndarray | None = None
    """(E,) bool per edge of ``graph``: it held a group of scans where their free space rules them out (weight 0;
    ``registration.overrule``). None: no check."""
    densify: dict = field(default_factory=dict)
    """What refinement, loop closure and retries did (``registration.densify.DensifyReport``), and the
    scans they rescued (weak after the first synchronization, placed and verified at the end)."""
    underdetermined: list[str] = field(default_factory=list)
    """Scans whose pose the kept edges do not fix to within a voxel in some direction (a scan seen as a plane,
    a corridor, a cylinder; ``registration.information.underdetermined``): placed, but not certain there."""
    covariances: np.ndarray | None = None
    """(N, 6, 6) covariance of each scan's pose relative to the world scan, gtsam order [rotation, translation]
    at the pose (``gtsam_api.pose_covariances``); NaN for unregistered scans. None: not computed yet."""

    cache: dict | None = None
    """What the resume cache gave (``cache.Cache.report``: per kind, results cached and computed); None without
    one."""
    centres: np.ndarray | None = None
    """(N, 3) the point each scan was centred at (``features`` and ``sync`` are in those centred frames; ``poses``,
    ``graph`` and ``covariances`` in the scans' input frames)."""

    @property
    def flags(self) -> dict[str, list[str]]:
        """The scans of each of ``FLAGS``, in its order."""
        return {flag: getattr(self, flag) for flag in FLAGS}

    @property
    def registered(self) -> list[int]:
        bad = set(self.unregistered)
        return [k for k, n in enumerate(self.names) if n not in bad]

    def world_points(self, k: int) -> np.ndarray:
        """Scan k's voxel-grid points under its pose: ``features`` are in the centred frames, ``poses`` in the input
        frames (``local_frame``)."""
        centre = 0.0 if self.centres is None else self.centres[k]
        return transform_points(self.poses[k], self.features[k].points + centre)


def peak_memory_mb() -> float:
    """Peak resident memory of this process (Linux reports ru_maxrss in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
