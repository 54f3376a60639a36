"""The Rerun recording read back from its .rrd file: the layout it opens on, the entities a reviewer looks at
(scans in a categorical palette with their axes, kept and rejected edges apart, flagged scans marked, series
named by scan files) and the named steps of the timeline. Generated data only."""

from collections import defaultdict

import numpy as np
import pytest
import rerun as rr
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from sghr_gtsam.config import Config
from sghr_gtsam.palette import FLAG_COLOURS, REJECTED, scan_colours
from sghr_gtsam.pipeline import run
from sghr_gtsam.recording import KEPT, TIMELINE, Recorder, edge_radii
from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.sync import synchronize
from sghr_gtsam.synthetic import make_scene, write_scene
from sghr_gtsam.types import PoseGraph
from sghr_gtsam.verify import Verification, verify


def _rows(path) -> dict[str, list[dict]]:
    """Every logged row of the recording by entity path: its components and, if temporal, its step."""
    rows: dict[str, list[dict]] = defaultdict(list)
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        columns = chunk.to_record_batch().to_pydict()
        for k in range(chunk.num_rows):
            rows[chunk.entity_path].append({name: values[k] for name, values in columns.items()})
    for entity in rows.values():
        entity.sort(key=lambda row: row.get(TIMELINE, -1))
    return rows


def _latest(rows: dict[str, list[dict]], entity: str, component: str, step: int | None = None):
    """The value of ``component`` on ``entity`` at ``step`` (default: the last), as the viewer shows it."""
    found = [
        r[component]
        for r in rows[entity]
        if r.get(component) is not None and (step is None or r.get(TIMELINE, -1) <= step)
    ]
    assert found, f"{entity} has no {component}"
    return found[-1]


def _rgb(packed: int) -> tuple[int, int, int]:
    return packed >> 24 & 255, packed >> 16 & 255, packed >> 8 & 255


def _stages(rows) -> dict[int, str]:
    """Step -> the stage name in force there."""
    changes = [(r[TIMELINE], r["StateChange:state"][0]) for r in rows["/stage"]]
    last = max(r[TIMELINE] for entity in rows.values() for r in entity if TIMELINE in r)
    named, current = {}, None
    for step in range(last + 1):
        current = next((s for t, s in changes if t == step), current)
        named[step] = current
    return named


# --- a synchronization with rejected edges and every kind of flagged scan --------------------------------


@pytest.fixture(scope="module")
def flagged(tmp_path_factory):
    """Nine scans: a 6-clique with two wrong edges; scan 6 hangs on one edge (single registration); scan 7 on an
    edge too weak to use (unplaced); scan 8 on three weak right edges against one strong wrong one (verified: one
    dropped registration is no competing placement)."""
    rng = np.random.default_rng(1)
    n = 9
    poses = make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.uniform(-3, 3, (n, 3)))
    pairs = [(a, b) for a in range(6) for b in range(a + 1, 6)] + [(5, 6), (0, 7), (0, 8), (1, 8), (2, 8), (3, 8)]
    i, j = np.array(pairs).T
    T = inv_T(poses[i]) @ poses[j]
    weight = rng.uniform(20, 100, len(i))
    wrong = [pairs.index(p) for p in ((0, 3), (1, 4), (3, 8))]
    T[wrong] = make_T(Rotation.random(3, random_state=rng).as_matrix(), rng.uniform(-3, 3, (3, 3)))
    weight[pairs.index((0, 7))] = 1e-14  # below irls.NEGLIGIBLE of the largest: never used
    weight[[pairs.index(p) for p in ((0, 8), (1, 8), (2, 8))]] = 5.0
    weight[pairs.index((3, 8))] = 60.0
    graph = PoseGraph(n=n, i=i, j=j, T=T, weight=weight)
    names = [f"s{k}.ply" for k in range(n)]
    points = [rng.uniform(-1, 1, (200, 3)) * (1 + k % 3) for k in range(n)]

    path = tmp_path_factory.mktemp("rec") / "flagged.rrd"
    recorder = Recorder(path)
    recorder.log_scans(names, points)
    recorder.log_graph(graph, np.eye(n))
    result = synchronize(graph, on_iteration=recorder.on_iteration)
    recorder.log_sync(result)
    verdict = verify(names, graph, result.weights > 0, result.poses, result.component == 0, Verification())
    flags = {
        "unplaced": [names[k] for k in np.flatnonzero(result.component != 0)],
        **{reason: [n for n, r in verdict.doubts.items() if r == reason] for reason in set(verdict.doubts.values())},
    }
    recorder.log_final(result.poses, flags)
    recorder.log_parts(result.poses, verdict.parts)
    recorder.close()
    return graph, result, names, points, flags, _rows(path), path


def test_the_recording_opens_on_its_layout(flagged):
    path = flagged[-1]
    reader = rr.chunk.RrdReader(path)
    (store,) = reader.blueprints()
    views, timeline = {}, None
    for chunk in reader.stream(store=store).to_chunks():
        columns = chunk.to_record_batch().to_pydict()
        if "ViewBlueprint:class_identifier" in columns:
            views[columns["ViewBlueprint:space_origin"][0][0]] = columns["ViewBlueprint:class_identifier"][0][0]
        timeline = columns.get("TimePanelBlueprint:timeline", [[timeline]])[0][0]
    assert timeline == TIMELINE  # the viewer opens on the run's steps, not on log_time
    assert views["/world"] == "3D" and views["/pose_graph"] == "Graph" and views["/log"] == "TextLog"
    assert views["/residuals"] == views["/weights"] == "TimeSeries"
    assert views["/stage"] == "StateTimeline"


def test_kept_and_rejected_edges_differ_in_colour_and_width(flagged):
    graph, result, names, *_, rows, _ = flagged
    kept = result.weights > 0
    assert kept.any() and (~kept).any()
    colours = np.array([_rgb(c) for c in _latest(rows, "/world/edges", "LineStrips3D:colors")])
    np.testing.assert_array_equal(colours[kept], np.tile(KEPT, (kept.sum(), 1)))
    np.testing.assert_array_equal(colours[~kept], np.tile(REJECTED, ((~kept).sum(), 1)))
    assert np.linalg.norm(np.subtract(KEPT, REJECTED)) > 150
    # Width grows with the log of the weight: the final weights span 5 to 100 here, and an IRLS weight 1e-3 of
    # the largest is still visibly thicker than a rejected edge.
    radii = -np.array(_latest(rows, "/world/edges", "LineStrips3D:radii"))  # negative: UI points
    w = result.weights
    order = np.argsort(w[kept])
    assert np.all(np.diff(radii[kept][order]) >= 0) and radii[kept].max() > 2 * radii[~kept].max()
    r = edge_radii(np.array([1.0, 1e-2, 1e-3, 1e-9, 0.0]), np.array([True, True, True, False, False]))
    assert r[0] > r[1] > r[2] and r[3] == r[4] == r[2]
    labels = _latest(rows, "/world/edges", "LineStrips3D:labels")
    assert labels == [f"{names[a]}–{names[b]}" for a, b in zip(graph.i, graph.j)]


def test_series_are_named_by_scan_files(flagged):
    graph, result, names, *_, rows, _ = flagged
    expected = [f"{names[a]}–{names[b]}" for a, b in zip(graph.i, graph.j)]
    for entity in ("/residuals", "/weights"):
        assert _latest(rows, entity, "SeriesLines:names") == expected
    np.testing.assert_allclose(_latest(rows, "/residuals", "Scalars:scalars"), result.residual_deg, atol=1e-9)
    weights = np.array(_latest(rows, "/weights", "Scalars:scalars"))
    kept = result.weights > 0
    np.testing.assert_allclose(10 ** weights[kept], result.weights[kept] / result.weights.max(), rtol=1e-9)
    assert np.all(weights[~kept] == weights.min())


def test_parts_are_boxed_in_their_colours_and_colour_the_graph_nodes(flagged):
    """Every part of the verification gets a box holding its scans under their final poses, labelled with its size
    (and why its join failed), in a colour of its own that its scans' graph nodes share."""
    graph, result, names, points, flags, rows, _ = flagged
    verdict = verify(names, graph, result.weights > 0, result.poses, result.component == 0, Verification())
    assert len(verdict.parts) >= 2  # the scan on one edge is a part of its own
    colours = {}
    for p in verdict.parts:
        box = f"/world/parts/{p.id}"
        assert _latest(rows, box, "Boxes3D:labels")[0].startswith(f"part {p.id}: {len(p.scans)} scan(s)")
        centre = np.array(_latest(rows, box, "Boxes3D:centers")[0])
        half = np.array(_latest(rows, box, "Boxes3D:half_sizes")[0])
        for name in p.scans:
            T = result.poses[names.index(name)]
            world = points[names.index(name)] @ T[:3, :3].T + T[:3, 3]
            assert np.all(np.abs(world - centre) <= half + 1e-5)
        colours[p.id] = _rgb(_latest(rows, box, "Boxes3D:colors")[0])
    assert len(set(colours.values())) == len(verdict.parts)
    nodes = _latest(rows, "/pose_graph", "GraphNodes:colors")
    part_of = verdict.part_of()
    assert all(_rgb(c) == colours[part_of[n]] for n, c in zip(names, nodes) if n in part_of)


def test_flagged_scans_are_marked_in_3d_and_in_the_graph(flagged):
    graph, result, names, points, flags, rows, _ = flagged
    assert all(flags.values()), flags  # the graph makes one scan of each kind
    marked = set()
    for label, flagged_names in flags.items():
        for name in flagged_names:
            box = f"/world/scans/{name}/flag"
            assert label in _latest(rows, box, "Boxes3D:labels")[0]
            assert _rgb(_latest(rows, box, "Boxes3D:colors")[0]) == FLAG_COLOURS[label]
            # the box holds the scan (in its own frame, under its transform)
            centre = np.array(_latest(rows, box, "Boxes3D:centers")[0])
            half = np.array(_latest(rows, box, "Boxes3D:half_sizes")[0])
            P = points[names.index(name)]
            assert np.all(np.abs(P - centre) <= half + 1e-5)
            marked.add(name)
    unmarked = [n for n in names if n not in marked]
    assert unmarked and not any(f"/world/scans/{n}/flag" in rows for n in unmarked)
    assert len({FLAG_COLOURS[label] for label in flags}) == len(flags)
    labels = _latest(rows, "/pose_graph", "GraphNodes:labels")
    for name, label in zip(names, labels):
        assert (name in marked) == (label != name) and label.startswith(name)
    kept = result.weights > 0
    edges = _latest(rows, "/pose_graph", "GraphEdges:edges")
    assert {(e["first"], e["second"]) for e in edges} == {
        (names[a], names[b]) for a, b in zip(graph.i[kept], graph.j[kept])
    }


def test_steps_of_a_synchronization_carry_their_stage(flagged):
    *_, rows, _ = flagged
    named = _stages(rows)
    stages = list(dict.fromkeys(named.values()))
    assert stages[:3] == ["start", "sync 1 · irls", "sync 1 · loops/irls"]
    assert stages[-3:] == ["sync 1 · lm", "sync 1 · result", "final"]
    assert sum(s == "sync 1 · irls" for s in named.values()) == Config().iters
    # per synchronization record: a transform per scan and a handful of entities, never one per edge
    irls_step = next(step for step, s in named.items() if s == "sync 1 · irls")
    at_step = {entity for entity, entity_rows in rows.items() for r in entity_rows if r.get(TIMELINE) == irls_step}
    assert len(at_step) <= len(flagged[2]) + 6, sorted(at_step)


def _pose(rows, entity: str, step: int | None) -> np.ndarray:
    """The transform of ``entity`` in force at ``step`` (None: the last), as the viewer reads it."""
    T = np.eye(4)
    T[:3, :3] = np.array(_latest(rows, entity, "Transform3D:mat3x3", step)[0]).reshape(3, 3).T  # column-major
    T[:3, 3] = _latest(rows, entity, "Transform3D:translation", step)[0]
    return T


def test_every_record_s_poses_are_at_its_step_also_when_a_synchronization_stops(flagged, tmp_path):
    """Poses are held and sent a column a scan (``Recorder._send_poses``): each record's still land on its own step,
    those of a synchronization that stops mid-way too (sent by ``close``)."""
    graph, _, names, points, *_ = flagged
    path = tmp_path / "stopped.rrd"
    recorder = Recorder(path)
    recorder.log_scans(names, points)
    recorder.log_graph(graph, np.eye(graph.n))
    seen = []

    def observe(record):
        recorder.on_iteration(record)
        seen.append(record.poses.copy())
        if len(seen) == 3:
            raise KeyboardInterrupt  # a stop in the first synchronization's third record

    with pytest.raises(KeyboardInterrupt):
        synchronize(graph, on_iteration=observe)
    recorder.close()
    rows = _rows(path)
    for step, poses in enumerate(seen, start=1):  # step 0 is "start"
        for name, T in zip(names, poses):
            np.testing.assert_allclose(_pose(rows, f"/world/scans/{name}", step), T, atol=1e-6)


@settings(max_examples=50, deadline=None)
@given(log_w=st.lists(st.floats(-12, 6), min_size=2, max_size=30), min_weight=st.sampled_from([0.0, 1e-6, 1e-3, 0.1]))
def test_edge_width_grows_with_log_weight_within_bounds(log_w, min_weight):
    """Any ``min_weight`` the config allows, 0 included (its log once made every radius NaN)."""
    w = 10.0 ** np.array(log_w)
    kept = w >= min_weight * w.max()
    r = edge_radii(w, kept)
    order = np.argsort(w[kept])
    assert np.all(np.isfinite(r)) and np.all(np.diff(r[kept][order]) >= -1e-6)
    assert r[np.argmax(w)] == pytest.approx(3.5) and np.all(r >= 0.75 - 1e-6) and np.all(r[~kept] == r.min())
    # scale-free: only weight ÷ the largest matters
    np.testing.assert_allclose(edge_radii(w * 1e3, kept), r, atol=1e-5)


# --- a run: the pipeline's stages on the timeline ------------------------------------------------------


@pytest.fixture(scope="module")
def object_run(tmp_path_factory):
    scene = make_scene(kind="object", n_scans=4, seed=3)
    folder = tmp_path_factory.mktemp("object")
    write_scene(scene, folder / "scene")
    messages = []
    result = run(folder / "scene", folder / "out", Config(voxel=scene.voxel, workers=1), log=messages.append)
    return result, _rows(folder / "out" / "recording.rrd")


def test_a_run_names_its_stages_and_messages_land_on_them(object_run):
    result, rows = object_run
    named = _stages(rows)
    stages = set(named.values())
    assert {"start", "features", "pairwise", "sync 1 · irls", "sync 1 · lm", "sync 1 · result", "final"} <= stages
    if result.densify["rounds"]:
        assert {"refine", "sync 2 · result"} <= stages
    messages = {r["TextLog:text"][0]: r[TIMELINE] for r in rows["/log"]}
    (sync_step,) = [step for text, step in messages.items() if text.startswith("sync (")]
    assert named[sync_step] == "sync 1 · result"
    assert named[next(step for text, step in messages.items() if text.startswith("pairwise:"))] == "pairwise"
    assert named[next(step for text, step in messages.items() if text.startswith("features:"))] == "global_graph"


def test_a_run_draws_every_scan_with_its_axes_and_colour(object_run):
    result, rows = object_run
    colours = scan_colours(len(result.names))
    for name, colour in zip(result.names, colours):
        entity = f"/world/scans/{name}"
        assert _latest(rows, entity, "TransformAxes3D:axis_length")[0] > 0
        assert _rgb(_latest(rows, entity, "Points3D:colors")[0]) == tuple(colour)
        np.testing.assert_allclose(_pose(rows, entity, None), result.poses[result.names.index(name)], atol=1e-5)


# --- what a reviewer reads off the recording: up axis, name, seconds, edge statuses, ellipsoid scale ------------


def _view(axis: int, sign: int) -> list:
    name = f"RIGHT_HAND_{'XYZ'[axis]}_{'UP' if sign > 0 else 'DOWN'}"
    return getattr(rr.ViewCoordinates, name).as_arrow_array().to_pylist()[0]


def _floors(axis: int, sign: int, rng: np.random.Generator, n: int = 3) -> list[np.ndarray]:
    """``n`` scans of a floor 1.5 m below their sensor (the frame origin) along ``sign`` × ``axis``, 8 m across, with
    a wall patch above it: what a scanner on a tripod or a camera in a room sees."""
    scans = []
    for _ in range(n):
        P = rng.uniform(-4, 4, (600, 3))
        P[:, axis] = -1.5 * sign + rng.normal(0, 0.02, 600)
        wall = rng.uniform(-0.5, 0.5, (100, 3)) + 3.0
        wall[:, axis] = sign * rng.uniform(-1.5, 1.0, 100)
        scans.append(np.vstack([P, wall]))
    return scans


@settings(max_examples=12, deadline=None)
@given(axis=st.integers(0, 2), sign=st.sampled_from([1, -1]), seed=st.integers(0, 2**16))
def test_the_world_is_viewed_with_the_scans_up_axis(tmp_path_factory, axis, sign, seed):
    """Scans that look down on a floor along any axis: the recording's view coordinates put that axis up (a
    3DMatch fragment's camera frame is y down), read back from the file."""
    rng = np.random.default_rng(seed)
    scans = _floors(axis, sign, rng)
    path = tmp_path_factory.mktemp("up") / "up.rrd"
    recorder = Recorder(path)
    names = [f"s{k}" for k in range(len(scans))]
    recorder.log_scans(names, scans)
    shift = np.eye(4)[None].repeat(len(scans), 0)
    shift[:, :3, 3] = rng.uniform(-1, 1, (len(scans), 3)) * np.where(np.arange(3) == axis, 0.05, 1.0)
    recorder.log_final(shift, {})
    recorder.close()
    assert _latest(_rows(path), "/world", "ViewCoordinates:xyz")[0] == _view(axis, sign)


def test_every_edge_status_has_a_colour_of_its_own_and_a_class_naming_it(flagged, tmp_path):
    from sghr_gtsam.palette import EDGE_COLOURS
    from sghr_gtsam.registration.edges import EDGE_STATUS

    colours = {"kept": KEPT, **EDGE_COLOURS}
    assert set(colours) == set(EDGE_STATUS)
    rgb = np.array(list(colours.values()), dtype=float)
    distance = np.linalg.norm(rgb[:, None] - rgb[None], axis=2)
    assert distance[np.triu_indices(len(rgb), 1)].min() > 60  # contradicted and failed are not rejected's
    graph, result, names, points, *_ = flagged
    path = tmp_path / "status.rrd"
    recorder = Recorder(path)
    recorder.log_scans(names, points)
    recorder.log_graph(graph, np.eye(graph.n))
    statuses = list(EDGE_STATUS)
    status = [statuses[e % len(statuses)] for e in range(graph.num_edges)]  # every status, several times
    recorder.log_final(result.poses, {})
    recorder.log_edge_status(result.poses, status)
    recorder.close()
    rows = _rows(path)
    drawn = [_rgb(c) for c in _latest(rows, "/world/edges", "LineStrips3D:colors")]
    assert drawn == [tuple(colours[s]) for s in status]
    assert _latest(rows, "/world/edges", "LineStrips3D:class_ids") == [statuses.index(s) for s in status]
    (context,) = _latest(rows, "/world/edges", "AnnotationContext:context")
    assert {c["class_description"]["info"]["label"] for c in context} == set(EDGE_STATUS)


def test_a_run_s_recording_is_named_after_it_with_its_stage_seconds_and_scaled_ellipsoids(object_run):
    result, rows = object_run
    (name,) = _latest(rows, "/__properties", "RecordingInfo:name")
    assert name.startswith("scene → out · ")  # the scene's folder, the results folder, then the start time
    for stage in ("features", "pairwise", "sync"):
        logged = [r["Scalars:scalars"][0] for r in rows[f"/seconds/{stage}"]]
        assert sum(logged) == pytest.approx(result.timings[stage], rel=1e-9, abs=1e-9)
    assert [r["Scalars:scalars"][0] for r in rows["/seconds/load"]] == [pytest.approx(result.timings["load"])]
    ellipsoids = [e for e in rows if e.startswith("/world/uncertainty_3sigma_x10/")]
    assert len(ellipsoids) == len(result.registered)
    assert "3σ × 10" in _latest(rows, ellipsoids[0], "Ellipsoids3D:labels")[0]


def test_two_runs_of_one_scene_are_told_apart(tmp_path):
    ids = []
    for k in range(2):
        path = tmp_path / f"{k}.rrd"
        Recorder(path, name="scene → out").close()
        ids.append(rr.chunk.RrdReader(path).recordings()[0].recording_id)
    assert ids[0] != ids[1] and all(i.startswith("scene → out · ") for i in ids)


def test_the_overlap_scores_are_shown_in_the_order_the_scans_were_listed(object_run):
    """The stages take the scans in an order of their content; the matrix the viewer shows is the result's, as
    listed."""
    result, rows = object_run
    (shown,) = _latest(rows, "/overlap_scores", "Tensor:data")
    matrix = np.asarray(shown["buffer"]).reshape(shown["shape"])
    np.testing.assert_allclose(matrix, result.scores, atol=1e-6)
