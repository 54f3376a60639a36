"""Everything rerun: a recording of a run for review in the Rerun viewer. It only observes.

Layout of the recording (timeline ``iteration``: IRLS iterations 1..M, then one step per robust-polish
stage (consensus, GNC, consensus) and per LM iteration):
- ``world/scans/<name>``: the voxelised scan in its own frame (static) under a ``Transform3D``
  that follows its pose at every iteration;
- ``world/edges``: one line per pose-graph edge between scan centres, coloured by weight
  (red = down-weighted to nothing, green = full weight), labelled ``i-j``;
- ``residuals``: one series per edge (named ``i-j``), its rotation residual in degrees; ``weights``: its
  weight relative to the largest (one entity each, not one per edge: logging 2·E entities every iteration
  cost 5 s of CPU a synchronization at 390 edges); ``metrics/*``: median residual, kept edges, LM cost;
  ``log``: stage messages with their seconds;
- ``world/uncertainty/<name>`` (last step): the 3σ ellipsoid of each scan's position from its pose covariance,
  magnified ``ELLIPSOID_GAIN``× so that millimetres show at room scale, and ``uncertainty/<name>/*``: the
  σ of its rotation (degrees) and translation (scene units) along their longest axes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import rerun as rr

from .types import IterationRecord, PoseGraph

TIMELINE = "iteration"
ELLIPSOID_GAIN = 10.0
"""Ellipsoids are drawn this many times their 3σ size (a well-registered scan's is sub-millimetre)."""


def _weight_colours(w: np.ndarray) -> np.ndarray:
    """Relative weights in [0, 1] -> RGB from red (0) through yellow to green (1)."""
    w = np.clip(w, 0.0, 1.0)[:, None]
    red = np.array([220, 40, 40])
    yellow = np.array([230, 200, 40])
    green = np.array([40, 180, 70])
    c = np.where(w < 0.5, red + (yellow - red) * (w * 2), yellow + (green - yellow) * (w * 2 - 1))
    return c.astype(np.uint8)


def _quaternion(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


class Recorder:
    """Streams one run to ``path`` (an .rrd file). Call ``close`` to flush it."""

    def __init__(self, path: str | Path, application_id: str = "sghr_gtsam"):
        self.rec = rr.RecordingStream(application_id)
        self.rec.save(str(path))
        self._names: list[str] = []
        self._centres = np.zeros((0, 3))
        self._graph: PoseGraph | None = None
        self._labels: list[str] = []
        self._step = 0

    def log_message(self, text: str) -> None:
        self.rec.log("log", rr.TextLog(text), static=False)

    def log_scans(self, names: list[str], points: list[np.ndarray]) -> None:
        """The (voxelised) scans, each in its own frame; poses come with every iteration."""
        self._names = list(names)
        self._centres = np.array([p.mean(0) if len(p) else np.zeros(3) for p in points])
        rng = np.random.default_rng(0)
        for k, (name, P) in enumerate(zip(names, points)):
            colour = rng.integers(60, 255, 3).astype(np.uint8)
            self.rec.log(f"world/scans/{rr.escape_entity_path_part(name)}",
                         rr.Points3D(P.astype(np.float32), colors=colour, radii=rr.Radius.ui_points(1.5)),
                         static=True)

    def log_graph(self, graph: PoseGraph, scores: np.ndarray) -> None:
        """The sparse pose graph chosen from the overlap scores (static)."""
        self._graph = graph
        self.rec.log("graph/overlap_scores", rr.Tensor(scores.astype(np.float32)), static=True)
        self._labels = [f"{a}-{b}" for a, b in zip(graph.i, graph.j)]
        for entity in ("residuals", "weights"):
            self.rec.log(entity, rr.SeriesLines(names=self._labels), static=True)

    def on_iteration(self, record: IterationRecord) -> None:
        # IRLS iterations at their own numbers; every later record (robust polish stages, LM) one step on.
        step = record.iteration if record.stage == "irls" else self._step + 1
        self._step = step
        self.rec.set_time(TIMELINE, sequence=step)
        self.log_poses(record.poses)
        if self._graph is not None and len(record.weights):
            self._log_edges(record)
        self.rec.log("metrics/median_residual_deg", rr.Scalars(float(np.median(record.residual_deg))))
        if np.isfinite(record.cost):
            self.rec.log("metrics/cost", rr.Scalars(float(record.cost)))

    def log_poses(self, poses: np.ndarray) -> None:
        for name, T in zip(self._names, poses):
            self.rec.log(f"world/scans/{rr.escape_entity_path_part(name)}",
                         rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))

    def _log_edges(self, record: IterationRecord) -> None:
        g = self._graph
        w_rel = record.weights / max(float(record.weights.max()), 1e-300)
        centres = np.einsum("nij,nj->ni", record.poses[:, :3, :3], self._centres) + record.poses[:, :3, 3]
        strips = np.stack([centres[g.i], centres[g.j]], axis=1)
        self.rec.log("world/edges", rr.LineStrips3D(strips.astype(np.float32), colors=_weight_colours(w_rel),
                                                    labels=self._labels, radii=rr.Radius.ui_points(2.0)))
        self.rec.log("metrics/kept_edges", rr.Scalars(float((w_rel > 1e-3).sum())))
        self.rec.log("residuals", rr.Scalars(np.asarray(record.residual_deg, dtype=float)))
        self.rec.log("weights", rr.Scalars(w_rel))

    def log_final(self, poses: np.ndarray, unregistered: list[str], unverified: list[str],
                  contested: list[str]) -> None:
        self.rec.set_time(TIMELINE, sequence=self._step + 1)
        self.log_poses(poses)
        for label, names in (("unregistered", unregistered), ("unverified", unverified), ("contested", contested)):
            if names:
                self.rec.log("log", rr.TextLog(f"{label}: " + ", ".join(names), level=rr.TextLogLevel.WARN))

    def log_covariances(self, poses: np.ndarray, covariances: np.ndarray) -> None:
        """Per scan with a finite covariance (gtsam order, at the pose): its position ellipsoid in the world and
        its σ scalars (module doc), at the last step."""
        from .gtsam_api import sigmas

        self.rec.set_time(TIMELINE, sequence=self._step + 1)
        rot, trans = sigmas(covariances)
        for name, T, C, r, t in zip(self._names, poses, covariances, rot, trans):
            if not np.isfinite(C).all():
                continue
            path = rr.escape_entity_path_part(name)
            # A translation ξ_t at the pose moves the scan by R ξ_t in the world.
            values, vectors = np.linalg.eigh(T[:3, :3] @ C[3:, 3:] @ T[:3, :3].T)
            vectors = vectors * np.sign(np.linalg.det(vectors))
            half = 3.0 * ELLIPSOID_GAIN * np.sqrt(np.maximum(values, 0.0))
            self.rec.log(f"world/uncertainty/{path}", rr.Ellipsoids3D(
                centers=[T[:3, 3]], half_sizes=[half],
                quaternions=[rr.Quaternion(xyzw=_quaternion(vectors))], fill_mode="majorwireframe"))
            self.rec.log(f"uncertainty/{path}/sigma_rotation_deg", rr.Scalars(float(r)))
            self.rec.log(f"uncertainty/{path}/sigma_translation", rr.Scalars(float(t)))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
