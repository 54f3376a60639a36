"""Everything rerun: a recording of a run for review in the Rerun viewer. It only observes.

The recording opens on its own layout (``blueprint``): the 3D scene, the pose graph, the stages, the residual,
weight and metric series in tabs, and the text log. Layout of the data:

- timeline ``step``: one step per pipeline stage (``begin_stage``: features, pairwise, refine, ...), per
  synchronization record (IRLS iteration, polish stage, LM iteration) and per synchronization result
  (``log_sync``); ``stage`` names each step (a ``StateChange``: ``sync 2 · irls``, ``refine``, ...), so the
  stage timeline view reads as a Gantt chart of the run and a message lands on the step of its stage;
- ``world/scans/<name>``: the voxelised scan in its own frame (static), in its colour from a fixed
  categorical palette (``scan_colours``), with its frame's axes, under a ``Transform3D`` that follows its pose;
  ``world/scans/<name>/flag`` (last step): a box around a doubtful scan, coloured and labelled by its reason
  (``log_final``: ``result.FLAGS``); ``world/parts/<id>`` (last step, ``log_parts``): a box around each part's scans
  in the part's colour, labelled with its size and, for a part apart from the world, why its join failed; the graph
  nodes take their part's colour;
- ``world``: its ``ViewCoordinates`` (last step, static): the scans' up axis (``up_axis``), so that the viewer
  opens the scene upright instead of guessing;
- ``world/edges``: one line per pose-graph edge between scan centres: kept edges in ``KEPT``, their width
  growing with the log of weight ÷ the largest (weights span orders of magnitude), rejected ones thin in
  ``REJECTED``; labelled ``a.ply–b.ply``; at the last step every edge in the colour of its status
  (``log_edge_status``: ``palette.EDGE_COLOURS``), its class (an ``AnnotationContext``) naming the status;
- ``pose_graph``: the scans as nodes (labels carry the flags) and the registered edges (after ``log_graph``),
  then the kept ones (after each ``log_sync``), for the graph view;
- ``residuals``: one series per edge named ``a.ply–b.ply``, its rotation residual in degrees; ``weights``: log10
  of its weight ÷ the largest, rejected edges at ``WEIGHT_FLOOR`` (one entity each, not one per edge: logging
  2·E entities every iteration cost 5 s of CPU a synchronization at 390 edges); ``metrics/*``: median
  residual, kept edges, LM cost; ``seconds/<stage>``: each pipeline stage's seconds as it ends (``end_stage``);
  ``log``: stage messages with their seconds; ``overlap_scores``: the matrix;
- ``world/uncertainty_3sigma_x10/<name>`` (last step): the 3σ ellipsoid of each scan's position from its pose
  covariance, magnified ``ELLIPSOID_GAIN``× so that millimetres show at room scale (the gain in the entity's name
  and its label), and ``uncertainty/<name>/*``: the σ of its rotation (degrees) and translation (scene units)
  along their longest axes.

The recording is named after its run (``Recorder(name=...)``: the scene's folder and the results folder, with the
start time), its recording id too (with a few random characters), so that two runs open side by side can be told
apart; its application id stays "sghr_gtsam", under which the viewer keeps a layout the user arranged.
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from sghr_gtsam.palette import EDGE_COLOURS, REJECTED, first_flags, label_colours, scan_colours
from sghr_gtsam.registration.edges import EDGE_STATUS
from sghr_gtsam.sync.irls import NEGLIGIBLE, kept_edges
from sghr_gtsam.types import IterationRecord, PoseGraph, SyncResult

if TYPE_CHECKING:
    from sghr_gtsam.verify import Part

TIMELINE = "step"
ELLIPSOID_GAIN = 10.0
"""Ellipsoids are drawn this many times their 3σ size (a well-registered scan's is sub-millimetre)."""
ELLIPSOIDS = f"world/uncertainty_3sigma_x{ELLIPSOID_GAIN:g}"
"""Where the ellipsoids are: the gain in the name, so that nobody reads them at their drawn size."""
KEPT = (60, 200, 255)
"""Colour of the edges a synchronization keeps (light blue; the rejected ones: ``palette.REJECTED``)."""
WEIGHT_FLOOR = float(np.log10(NEGLIGIBLE)) - 1.0
"""log10 of weight ÷ the largest at which the ``weights`` series shows a rejected (zero-weight) edge: below every
weight synchronization can keep (``irls.NEGLIGIBLE``)."""
FLAG_OTHER = (255, 255, 255)
"""Box colour of a flag without one in ``palette.FLAG_COLOURS`` (a box takes its first flag's colour)."""
_EDGE_POINTS = (0.75, 3.5)  # line radius in UI points of a rejected edge / the heaviest kept edge
_SEP = "–"  # between the two scan names of an edge


_RADIUS_DECADES = 3
"""Kept edges' line radius grows over this many decades of weight below the largest (lighter ones: the minimum)."""


def edge_radii(w: np.ndarray, kept: np.ndarray) -> np.ndarray:
    """Line radius (UI points) of each edge: kept edges from ``_EDGE_POINTS[0]`` at ``10^-_RADIUS_DECADES`` times the
    largest weight to ``_EDGE_POINTS[1]`` at the largest, on a log scale; rejected ones at the minimum."""
    rel = w / max(float(w.max(initial=0.0)), 1e-300)
    t = np.clip(1.0 + np.log10(np.maximum(rel, 10.0**-_RADIUS_DECADES)) / _RADIUS_DECADES, 0.0, 1.0)
    lo, hi = _EDGE_POINTS
    return np.where(kept, lo + (hi - lo) * t, lo).astype(np.float32)


_VIEWS = {
    (axis, sign): getattr(rr.ViewCoordinates, f"RIGHT_HAND_{'XYZ'[axis]}_{'UP' if sign > 0 else 'DOWN'}")
    for axis in range(3)
    for sign in (1, -1)
}


def _corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(8, 3) the corners of the box from ``lo`` to ``hi``."""
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def up_axis(scatter: np.ndarray, mean: np.ndarray, sensors: np.ndarray) -> tuple[int, int]:
    """The world axis (0, 1, 2 for x, y, z) and sign that is up for the scans whose points have covariance
    ``scatter`` (3, 3) about ``mean`` (3,), seen from ``sensors`` (N, 3, the scans' frame origins): the axis nearest
    the points' direction of least extent (a room's or a site's vertical, the axis summary.png looks down), its
    sign the side of the points' mean that the sensors are on (scanners and cameras look down on floors and the
    ground more than up at ceilings: a 3DMatch fragment's camera frame comes out y down, a survey's z up).
    Axis-aligned because Rerun's ``ViewCoordinates`` are."""
    _, vectors = np.linalg.eigh(scatter)
    axis = int(np.argmax(np.abs(vectors[:, 0])))
    return axis, 1 if np.median(sensors[:, axis]) >= mean[axis] else -1


def _run_name(name: str) -> str:
    """The recording's name and id: ``name`` (the run's) and the time it started, so two runs of a scene differ."""
    return f"{name or 'sghr_gtsam'} · {time.strftime('%Y-%m-%d %H:%M:%S')}"


def blueprint() -> rrb.Blueprint:
    """The layout the recording opens on."""
    series = rrb.Tabs(
        rrb.TimeSeriesView(origin="/residuals", name="rotation residual (deg)"),
        rrb.TimeSeriesView(origin="/weights", name="log10 weight ÷ largest"),
        rrb.TimeSeriesView(origin="/metrics", name="metrics"),
        rrb.TimeSeriesView(origin="/uncertainty", name="pose σ"),
        rrb.TimeSeriesView(origin="/seconds", name="stage seconds"),
        rrb.TensorView(origin="/overlap_scores", name="overlap scores"),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(
                rrb.Spatial3DView(origin="/world", name="scans and edges"),
                rrb.StateTimelineView(origin="/stage", name="stages"),
                row_shares=[6, 1],
            ),
            rrb.Vertical(
                rrb.GraphView(origin="/pose_graph", name="pose graph"),
                series,
                rrb.TextLogView(origin="/log", name="log"),
                row_shares=[3, 3, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=TIMELINE, state="expanded"),
    )


def _quaternion(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_quat()


class _Pump:
    """Rerun's file sink writes into a pipe (``sink``) and this thread copies it to ``path``. Rerun's own writer
    reports a failed write (a full disk) only in its log on stderr, then raises "File-writer thread shut down
    prematurely" or hangs in ``flush`` for ever; here the first error is kept, the pipe drained to its end so
    that rerun never meets it, and ``close`` raises it."""

    def __init__(self, path: str | Path) -> None:
        self._file = open(path, "wb")
        read, self._write = os.pipe()
        self.sink = f"/dev/fd/{self._write}"  # held open until ``close``: rerun opens its own end by this name
        self._error: OSError | None = None
        self._thread = threading.Thread(target=self._copy, args=(read,), name="recording", daemon=True)
        self._thread.start()

    def _copy(self, read: int) -> None:
        with os.fdopen(read, "rb", buffering=0) as pipe:
            while chunk := pipe.read(1 << 20):
                try:
                    if self._error is None:
                        self._file.write(chunk)
                except OSError as e:
                    self._error = e

    def close(self) -> None:
        """Once rerun has closed its end: the rest copied and the file closed, or the first write error raised."""
        os.close(self._write)
        self._thread.join()
        try:
            self._file.close()
        except OSError as e:
            self._error = self._error or e
        if self._error is not None:
            raise self._error


class Recorder:
    """Streams one run to ``path`` (an .rrd file, with its ``blueprint``). Call ``close`` to flush it; it raises
    the ``OSError`` of a write that failed.

    ``min_weight``: as ``Config.min_weight``, so that an IRLS edge counts as kept where synchronization
    keeps it. ``name``: the run's (``pipeline.run``: the scene's folder and the results folder), with the start
    time the recording's name and id."""

    def __init__(self, path: str | Path, application_id: str = "sghr_gtsam", min_weight: float = 1e-3, name: str = ""):
        title = _run_name(name)
        # the id also tells apart two runs started in the same second
        self.rec = rr.RecordingStream(application_id, recording_id=f"{title} #{uuid.uuid4().hex[:6]}")
        self._pump = _Pump(path)
        self.rec.save(self._pump.sink, default_blueprint=blueprint())
        self.rec.send_recording_name(title)
        self.min_weight = min_weight
        self._names: list[str] = []
        self._paths: list[str] = []
        self._centres = np.zeros((0, 3))
        self._boxes: list[tuple[np.ndarray, np.ndarray]] = []  # per scan: its bounding box in its own frame
        self._moments: list[tuple[int, np.ndarray, np.ndarray]] = []  # per scan: count, mean, covariance (own frame)
        self._colours = np.zeros((0, 3), dtype=np.uint8)
        self._graph: PoseGraph | None = None
        self._scores = np.zeros((0, 0))
        self._labels: list[str] = []
        self._step = -1
        self._stage = ""
        self._syncs = 0  # synchronizations finished (log_sync)
        self._poses: list[tuple[int, np.ndarray]] = []  # (step, (N, 3, 4)) not sent yet (``_send_poses``)
        self.begin_stage("start")

    def begin_stage(self, name: str) -> None:
        """A step of its own for a pipeline stage: what is logged next lands on it."""
        self._next_step(name)

    def _next_step(self, stage: str) -> None:
        self._step += 1
        self.rec.set_time(TIMELINE, sequence=self._step)
        if stage != self._stage:
            self._stage = stage
            self.rec.log("stage", rr.StateChange(state=stage))

    def end_stage(self, name: str, seconds: float) -> None:
        """A pipeline stage's seconds, as data (``seconds/<name>``), on the step where it ends."""
        self.rec.log(f"seconds/{rr.escape_entity_path_part(name)}", rr.Scalars(float(seconds)))

    def log_message(self, text: str) -> None:
        self.rec.log("log", rr.TextLog(text))

    def log_scans(self, names: list[str], points: Sequence[np.ndarray], ranks: Sequence[int] | None = None) -> None:
        """The (voxelised) scans, each in its own frame with its axes; poses come with every iteration.
        ``points[k]`` is read once, one scan at a time. ``ranks``: scan k takes the palette's colour ``ranks[k]``
        (default k)."""
        self._names = list(names)
        self._paths = [f"world/scans/{rr.escape_entity_path_part(name)}" for name in names]
        self._colours = scan_colours(len(names))[np.arange(len(names)) if ranks is None else np.asarray(ranks)]
        centres, self._boxes, self._moments = [], [], []
        for path, P, colour in zip(self._paths, points, self._colours):
            centres.append(P.mean(0) if len(P) else np.zeros(3))
            self._boxes.append((P.min(0), P.max(0)) if len(P) else (np.zeros(3), np.zeros(3)))
            Q = P - centres[-1]
            self._moments.append((len(P), centres[-1], Q.T @ Q / max(len(P), 1)))
            self.rec.log(
                path, rr.Points3D(P.astype(np.float32), colors=colour, radii=rr.Radius.ui_points(1.5)), static=True
            )
        self._centres = np.array(centres).reshape(-1, 3)
        sizes = [np.linalg.norm(hi - lo) for lo, hi in self._boxes]
        axes = rr.TransformAxes3D(0.1 * float(np.median(sizes)) or 1.0)  # sized by all the scans: logged after them
        for path in self._paths:
            self.rec.log(path, axes, static=True)
        self._log_nodes({})

    def reorder(self, order: np.ndarray, graph: PoseGraph) -> None:
        """From now on scan ``order[k]`` is scan k and ``graph`` (the logged graph's edges, relabelled so) is the
        graph, and the overlap scores are shown in that order: the pipeline hands its result back in the scans'
        listing order."""
        self._send_poses()  # held in the old order
        self._names, self._paths, self._boxes, self._moments = (
            [items[k] for k in order] for items in (self._names, self._paths, self._boxes, self._moments)
        )
        self._colours, self._centres = np.asarray(self._colours)[order], self._centres[order]
        if self._graph is not None:
            self._graph, self._scores = graph, self._scores[np.ix_(order, order)]
            self.rec.log("overlap_scores", rr.Tensor(self._scores.astype(np.float32)), static=True)

    def _log_nodes(self, marks: dict[str, str]) -> None:
        """The scans as graph nodes; a scan in ``marks`` gets its mark in the label and a larger node."""
        self.rec.log(
            "pose_graph",
            rr.GraphNodes(
                self._names,
                labels=[f"{n} ({marks[n]})" if n in marks else n for n in self._names],
                colors=self._colours,
                radii=[8.0 if n in marks else 5.0 for n in self._names],
            ),
        )

    def log_graph(self, graph: PoseGraph, scores: np.ndarray) -> None:
        """The pose graph of registered pairs before a synchronization (its edges only grow)."""
        self._graph, self._scores = graph, scores
        self.rec.log("overlap_scores", rr.Tensor(scores.astype(np.float32)), static=True)
        self._labels = [f"{self._names[a]}{_SEP}{self._names[b]}" for a, b in zip(graph.i, graph.j)]
        for entity in ("residuals", "weights"):
            self.rec.log(entity, rr.SeriesLines(names=self._labels), static=True)
        # Labels once, not with every step's lines: the edges only grow, so earlier steps keep theirs.
        self.rec.log("world/edges", rr.LineStrips3D.from_fields(labels=self._labels, show_labels=False), static=True)
        self._log_graph_edges(np.ones(graph.num_edges, dtype=bool))

    def _log_graph_edges(self, mask: np.ndarray) -> None:
        g = self._graph
        self.rec.log(
            "pose_graph", rr.GraphEdges([(self._names[a], self._names[b]) for a, b in zip(g.i[mask], g.j[mask])])
        )

    def on_iteration(self, record: IterationRecord) -> None:
        """One synchronization record (IRLS iteration, polish stage or LM iteration) on a step of its own."""
        self._next_step(f"sync {self._syncs + 1} · {record.stage}")
        self._log_state(record.poses, record.weights, record.residual_deg)
        if len(record.residual_deg):
            self.rec.log("metrics/median_residual_deg", rr.Scalars(float(np.median(record.residual_deg))))
        if np.isfinite(record.cost):
            self.rec.log("metrics/cost", rr.Scalars(float(record.cost)))

    def log_sync(self, result: SyncResult) -> None:
        """A synchronization's outcome on a step of its own: its poses and the edges it kept and rejected."""
        self._syncs += 1
        self._next_step(f"sync {self._syncs} · result")
        self._log_state(result.poses, result.weights, result.residual_deg)
        self._send_poses()
        if self._graph is not None:
            self._log_graph_edges(result.weights > 0)

    def _log_state(self, poses: np.ndarray, weights: np.ndarray, residual_deg: np.ndarray) -> None:
        self.log_poses(poses)
        if self._graph is not None and len(weights) == self._graph.num_edges:
            self._log_edges(poses, weights, residual_deg)

    def log_poses(self, poses: np.ndarray) -> None:
        """The scans' poses (N, 4, 4) at the current step; held until ``_send_poses`` sends them."""
        self._poses.append((self._step, np.array(poses[:, :3, :4], dtype=float)))

    def _send_poses(self) -> None:
        """The poses held by ``log_poses``, one column of steps a scan: one transform logged per scan and record
        took 3.9 CPU s for 66 scans and 522 records (0.5 s so), in the main process while workers wait."""
        if not self._poses:
            return
        steps = rr.TimeColumn(TIMELINE, sequence=[step for step, _ in self._poses])
        by_scan = np.stack([poses for _, poses in self._poses], axis=1)  # (N, steps, 3, 4)
        self._poses = []
        for path, P in zip(self._paths, by_scan):
            self.rec.send_columns(
                path, indexes=[steps], columns=rr.Transform3D.columns(translation=P[:, :, 3], mat3x3=P[:, :, :3])
            )

    def _log_edges(self, poses: np.ndarray, weights: np.ndarray, residual_deg: np.ndarray) -> None:
        g = self._graph
        kept = kept_edges(weights, self.min_weight, g.weight)
        centres = np.einsum("nij,nj->ni", poses[:, :3, :3], self._centres) + poses[:, :3, 3]
        strips = np.stack([centres[g.i], centres[g.j]], axis=1).astype(np.float32)
        colours = np.where(kept[:, None], np.array(KEPT, dtype=np.uint8), np.array(REJECTED, dtype=np.uint8))
        self.rec.log(
            "world/edges", rr.LineStrips3D(strips, colors=colours, radii=rr.Radius.ui_points(edge_radii(weights, kept)))
        )
        self.rec.log("metrics/kept_edges", rr.Scalars(float(kept.sum())))
        self.rec.log("residuals", rr.Scalars(np.asarray(residual_deg, dtype=float)))
        rel = weights / max(float(weights.max(initial=0.0)), 1e-300)
        with np.errstate(divide="ignore"):
            self.rec.log("weights", rr.Scalars(np.maximum(np.log10(rel), WEIGHT_FLOOR)))

    def log_final(self, poses: np.ndarray, flags: dict[str, list[str]]) -> None:
        """The final poses on a step of their own, and the flagged scans: ``flags`` maps a flag (``result.FLAGS``,
        e.g. ``"single registration"``) to the names of the scans it marks. Each flagged scan gets a box in its
        frame, in the colour of its first flag (``FLAG_COLOURS``) and labelled with all of them; its graph node
        too."""
        self._next_step("final")
        self.log_poses(poses)
        self._send_poses()
        self._log_view(poses, set(flags.get("unplaced", [])))
        by_scan: dict[str, list[str]] = {}
        for label, names in flags.items():
            for name in names:
                by_scan.setdefault(name, []).append(label)
            if names:
                self.rec.log("log", rr.TextLog(f"{label}: " + ", ".join(names), level=rr.TextLogLevel.WARN))
        colours = label_colours(first_flags(self._names, flags), other=FLAG_OTHER)
        for k, name in enumerate(self._names):
            if name not in by_scan:
                continue
            lo, hi = self._boxes[k]
            labels = by_scan[name]
            self.rec.log(
                f"{self._paths[k]}/flag",
                rr.Boxes3D(
                    centers=[(lo + hi) / 2],
                    half_sizes=[np.maximum((hi - lo) / 2, 1e-6)],
                    colors=[colours[k]],
                    labels=[f"{name}: {', '.join(labels)}"],
                    show_labels=True,
                    radii=rr.Radius.ui_points(2.0),
                ),
            )
        self._marks = {name: ", ".join(labels) for name, labels in by_scan.items()}
        self._log_nodes(self._marks)

    def log_parts(self, poses: np.ndarray, parts: Sequence[Part]) -> None:
        """At the current step: a box around each part's placed scans (``verify.Part``), in a categorical colour per
        part, labelled with its size and why its join failed; the graph nodes in their part's colour."""
        colours = scan_colours(max(len(parts), 1))
        part_of = {name: p.id for p in parts for name in p.scans}
        for p in parts:
            ks = [self._names.index(name) for name in p.scans]
            corners = np.concatenate([_corners(*self._boxes[k]) @ poses[k][:3, :3].T + poses[k][:3, 3] for k in ks])
            lo, hi = corners.min(axis=0), corners.max(axis=0)
            said = f"part {p.id}: {len(ks)} scan(s)" + (f", apart: {p.join.why}" if p.join else "")
            self.rec.log(
                f"world/parts/{p.id}",
                rr.Boxes3D(
                    centers=[(lo + hi) / 2],
                    half_sizes=[(hi - lo) / 2 + 1e-6],
                    colors=[colours[p.id]],
                    labels=[said],
                    radii=rr.Radius.ui_points(1.0),
                ),
            )
        self._colours = [colours[part_of[n]] if n in part_of else FLAG_OTHER for n in self._names]
        self._log_nodes(self._marks)

    def _log_view(self, poses: np.ndarray, unplaced: set[str]) -> None:
        """The world's ``ViewCoordinates``: ``up_axis`` of the placed scans' points under ``poses``."""
        placed = [
            k
            for k, name in enumerate(self._names)
            if name not in unplaced and self._moments[k][0] and np.isfinite(poses[k]).all()
        ]
        if not placed:
            return
        count = np.array([self._moments[k][0] for k in placed], dtype=float)
        R, t = poses[placed, :3, :3], poses[placed, :3, 3]
        means = np.einsum("nij,nj->ni", R, np.array([self._moments[k][1] for k in placed])) + t
        mean = count @ means / count.sum()
        spread = R @ np.array([self._moments[k][2] for k in placed]) @ np.swapaxes(R, 1, 2)
        d = means - mean
        scatter = np.einsum("n,nij->ij", count, spread + d[:, :, None] * d[:, None, :]) / count.sum()
        self.rec.log("world", _VIEWS[up_axis(scatter, mean, t)], static=True)

    def log_edge_status(self, poses: np.ndarray, status: Sequence[str]) -> None:
        """Every edge at the current step in the colour of its ``EDGE_STATUS`` key (``palette.EDGE_COLOURS``, kept
        in ``KEPT``), its class naming the status; kept ones as wide as their weight, the rest thin."""
        g = self._graph
        if g is None or len(status) != g.num_edges:
            return
        names = list(EDGE_STATUS)
        colours = {"kept": KEPT, **EDGE_COLOURS}
        self.rec.log(
            "world/edges", rr.AnnotationContext([(k, s, colours[s]) for k, s in enumerate(names)]), static=True
        )
        centres = np.einsum("nij,nj->ni", poses[:, :3, :3], self._centres) + poses[:, :3, 3]
        kept = np.array([s == "kept" for s in status], dtype=bool)
        weights = np.where(kept, g.weight, 0.0)
        self.rec.log(
            "world/edges",
            rr.LineStrips3D(
                np.stack([centres[g.i], centres[g.j]], axis=1).astype(np.float32),
                colors=np.array([colours[s] for s in status], dtype=np.uint8).reshape(-1, 3),
                class_ids=[names.index(s) for s in status],
                radii=rr.Radius.ui_points(edge_radii(weights, kept)),
            ),
        )

    def log_covariances(self, poses: np.ndarray, covariances: np.ndarray) -> None:
        """Per scan with a finite covariance (gtsam order, at the pose): its position ellipsoid in the world and
        its σ scalars (module doc), at the current step."""
        from sghr_gtsam.gtsam_api import sigmas

        rot, trans = sigmas(covariances)
        for name, T, C, r, t in zip(self._names, poses, covariances, rot, trans):
            if not np.isfinite(C).all():
                continue
            path = rr.escape_entity_path_part(name)
            # A translation ξ_t at the pose moves the scan by R ξ_t in the world.
            values, vectors = np.linalg.eigh(T[:3, :3] @ C[3:, 3:] @ T[:3, :3].T)
            vectors = vectors * np.sign(np.linalg.det(vectors))
            half = 3.0 * ELLIPSOID_GAIN * np.sqrt(np.maximum(values, 0.0))
            self.rec.log(
                f"{ELLIPSOIDS}/{path}",
                rr.Ellipsoids3D(
                    centers=[T[:3, 3]],
                    half_sizes=[half],
                    labels=[f"{name}: 3σ × {ELLIPSOID_GAIN:g}"],
                    show_labels=False,
                    quaternions=[rr.Quaternion(xyzw=_quaternion(vectors))],
                    fill_mode="majorwireframe",
                ),
            )
            self.rec.log(f"uncertainty/{path}/sigma_rotation_deg", rr.Scalars(float(r)))
            self.rec.log(f"uncertainty/{path}/sigma_translation", rr.Scalars(float(t)))

    def close(self) -> None:
        try:
            self._send_poses()  # those of a synchronization that failed or stopped
            self.rec.flush()
        finally:
            self.rec.disconnect()  # closes rerun's end of the pipe: the pump reaches its end
            self._pump.close()
