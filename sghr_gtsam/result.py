"""What a run produced (``RunResult``), shared by the pipeline that fills it and the writers that save it."""

from __future__ import annotations

import resource
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from sghr_gtsam.features.local import ScanFeatures
from sghr_gtsam.registration.pairwise import PairResult
from sghr_gtsam.se3 import transform_points
from sghr_gtsam.types import PoseGraph, SyncResult
from sghr_gtsam.verify import REASONS, Verdict

FLAGS = {"unplaced": "no reliable registration joins it to the largest part", **REASONS}
"""What the run says of a scan it does not verify: unplaced, or doubtful for one of ``verify.REASONS``."""
DOUBTS = tuple(REASONS)
"""The reasons a placed scan can be doubtful for."""


@dataclass
class RunResult:
    """Everything a run produced; ``poses[k]`` maps ``names[k]`` into the world (the frame of the
    first scan of the largest connected part). Scans in ``unregistered`` have no pose; ``verdict`` says which
    placed scans the evidence holds, in rigid parts, with one status per scan (``verify``)."""

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
    covariances: np.ndarray | None = None
    """(N, 6, 6) covariance of each scan's pose relative to the world scan, gtsam order [rotation, translation]
    at the pose (``gtsam_api.pose_covariances``); NaN for unregistered scans. None: not computed yet."""

    cache: dict | None = None
    """What the resume cache gave (``cache.Cache.report``: per kind, results cached and computed); None without
    one."""
    verdict: Verdict | None = None
    """Parts and each scan's status (``verify.verify``). None: not verified yet."""
    centres: np.ndarray | None = None
    """(N, 3) the point each scan was centred at (``features`` and ``sync`` are in those centred frames; ``poses``,
    ``graph`` and ``covariances`` in the scans' input frames)."""

    @property
    def flags(self) -> dict[str, list[str]]:
        """The scans of each of ``FLAGS``, in its order: the unregistered, then the doubtful by reason."""
        doubts = {} if self.verdict is None else self.verdict.doubts
        return {
            "unplaced": list(self.unregistered),
            **{reason: [name for name in self.names if doubts.get(name) == reason] for reason in DOUBTS},
        }

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
