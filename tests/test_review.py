"""Reviewing a run at a glance: progress bars on a terminal (captured here), the command line's help,
closing summary and quiet mode, summary.png and its palette, TUM poses beside KITTI."""

import io
import re

import numpy as np
import pytest
from rich.console import Console
from scipy.spatial.distance import pdist
from typer.testing import CliRunner

from sghr_gtsam.cli import app
from sghr_gtsam.config import Config
from sghr_gtsam.io.poses import read_kitti, read_tum
from sghr_gtsam.palette import FLAG_COLOURS, REJECTED, scan_colours
from sghr_gtsam.pipeline import run
from sghr_gtsam.plots import summary_figure
from sghr_gtsam.progress import TerminalProgress
from sghr_gtsam.synthetic import make_scene, write_scene

ANSI = re.compile(r"\x1b\[[0-9;?]*[A-Za-z]")


@pytest.fixture(scope="module")
def watched_run(tmp_path_factory):
    """A 4-scan room registered with the terminal's progress drawn on a captured 'terminal'."""
    tmp = tmp_path_factory.mktemp("review")
    write_scene(make_scene(kind="room", n_scans=4, seed=0), tmp / "scene")
    screen = io.StringIO()
    progress = TerminalProgress(Console(file=screen, force_terminal=True, width=140))
    try:
        result = run(tmp / "scene", tmp / "out", Config(workers=1, record=False), log=progress.log, progress=progress)
    finally:
        progress.close()
    return result, tmp / "out", ANSI.sub("", screen.getvalue()).replace("\r", "\n")


def _final_line(text, label):
    """The last drawn state of the bar ``label`` (rich redraws every bar on each refresh)."""
    lines = [line for line in text.splitlines() if line.startswith(label + " ")]
    assert lines, f"no bar {label!r} in:\n{text[-2000:]}"
    return lines[-1]


def test_progress_bars_count_every_task_of_each_stage(watched_run):
    result, _, text = watched_run
    top_k = result.edge_origin.count("top-k")
    refined = result.densify["refine_tried"]
    assert re.search(r"\b4/4\b", _final_line(text, "features"))
    assert re.search(rf"\b{top_k}/{top_k}\b", _final_line(text, "pairwise registration"))
    assert re.search(rf"\b{refined}/{refined}\b", _final_line(text, "refinement"))
    assert re.search(r"\b50/50\b", _final_line(text, "synchronization"))  # the IRLS iterations (Config.iters)
    assert "ETA" in _final_line(text, "pairwise registration")


def test_stage_messages_print_above_the_bars(watched_run):
    _, _, text = watched_run
    assert re.search(r"^pairwise: \d+ pairs in [\d.]+ s$", text, re.MULTILINE)
    assert re.search(r"^4 scans, voxel ", text, re.MULTILINE)


def test_progress_only_observes(watched_run, tmp_path):
    result, out, _ = watched_run
    unwatched = run(out.parent / "scene", tmp_path, Config(workers=1, record=False), log=lambda m: None)
    np.testing.assert_array_equal(unwatched.poses, result.poses)


def test_tum_poses_are_written_beside_kitti(watched_run):
    result, out, _ = watched_run
    stamps, tum = read_tum(out / "poses_tum.txt")
    assert stamps.tolist() == result.registered  # timestamp = scan index
    np.testing.assert_allclose(tum, result.poses[result.registered], atol=1e-12)
    np.testing.assert_allclose(read_kitti(out / "poses_kitti.txt"), tum, atol=1e-12)


def test_summary_png_is_written(watched_run):
    _, out, _ = watched_run
    data = (out / "summary.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
    assert (width, height) == (990, 450)


def test_summary_figure_draws_kept_and_rejected_edges_apart(watched_run):
    """One kept edge marked rejected: one dashed red segment between its scans' centres, the rest solid, the
    heaviest kept edge widest; the top view holds exactly the scans' palette colours."""
    from matplotlib.collections import LineCollection

    result, _, _ = watched_run
    from sghr_gtsam.registration.edges import edge_status

    status = edge_status(result)
    kept = [e for e, s in enumerate(status) if s == "kept"]
    assert len(kept) >= 3
    status[kept[0]] = "rejected"
    fig = summary_figure(result, status)
    top = fig.axes[0]
    rejected, solid = (
        next(c for c in top.collections if isinstance(c, LineCollection) and c.get_label() == label)
        for label in ("rejected", "kept")
    )
    assert len(rejected.get_segments()) == 1 and len(solid.get_segments()) == len(kept) - 1
    assert rejected.get_linestyle()[0][1] is not None  # dashed
    np.testing.assert_allclose(rejected.get_edgecolor()[0][:3], np.divide(REJECTED, 255), atol=1e-6)
    widths = solid.get_linewidths()
    heaviest = int(np.argmax(result.sync.weights[kept[1:]]))
    assert widths[heaviest] == pytest.approx(3.0) and min(widths) >= 0.6
    image = top.images[0].get_array()
    drawn = np.unique(image[image[..., 3] > 0][:, :3], axis=0)
    np.testing.assert_allclose(np.sort(drawn, axis=0), np.sort(scan_colours(4) / 255.0, axis=0))


def test_summary_figure_rings_each_doubtful_scan_in_its_reasons_colour(watched_run):
    """Every doubt shows: a ring in the palette's colour of the scan's reason, a legend entry and a count in the
    title for each reason."""
    from dataclasses import replace

    from matplotlib.collections import PathCollection

    result, _, _ = watched_run
    a, b, c = result.names[1:4]
    flagged = replace(result, verdict=replace(result.verdict, doubts={a: "free space", b: "free space", c: "loose"}))
    top = summary_figure(flagged).axes[0]
    dots = next(col for col in top.collections if isinstance(col, PathCollection))
    rings = [tuple(np.round(rgba[:3] * 255).astype(int)) for rgba in dots.get_edgecolor()]
    assert rings[1:] == [FLAG_COLOURS["free space"]] * 2 + [FLAG_COLOURS["loose"]]
    assert [t.get_text() for t in top.get_legend().get_texts() if " edge (" not in t.get_text()] == [
        "free space",
        "loose",
    ]
    assert "2 free space · 1 loose" in top.get_title()


def test_summary_legend_counts_every_edge_status_and_its_title_stays_in_the_picture(watched_run):
    """summary.png said "rejected edge (0)" while 11 edges were contradicted or failed and not drawn, and a title
    listing many flags ran past the picture's left edge."""
    from dataclasses import replace

    from matplotlib.collections import LineCollection

    from sghr_gtsam.palette import EDGE_COLOURS
    from sghr_gtsam.registration.edges import edge_status

    result, _, _ = watched_run
    status = edge_status(result)
    assert len(status) >= 6
    status[:5] = ["contradicted", "contradicted", "failed", "overruled", "unplaced"]
    names = result.names
    from sghr_gtsam.verify import REASONS

    reasons = list(REASONS)
    doubts = {name: reasons[k % len(reasons)] for k, name in enumerate(names[1:])}
    flagged = replace(result, verdict=replace(result.verdict, doubts=doubts))
    fig = summary_figure(flagged, status)
    top = fig.axes[0]
    legend = [t.get_text() for t in top.get_legend().get_texts()]
    counts = {key: status.count(key) for key in dict.fromkeys(status)}
    for key, count in counts.items():
        (entry,) = [t for t in legend if t.startswith(f"{key} edge ({count}")]
        assert entry.endswith("not drawn)") == (key in ("failed", "unplaced"))
    for key in ("contradicted", "overruled"):  # drawn dashed, in their own colours
        lines = next(c for c in top.collections if isinstance(c, LineCollection) and c.get_label() == key)
        assert len(lines.get_segments()) == counts[key]
        np.testing.assert_allclose(lines.get_edgecolor()[0][:3], np.divide(EDGE_COLOURS[key], 255), atol=1e-6)
    fig.canvas.draw()
    box = top.title.get_window_extent()
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width and box.y1 <= fig.bbox.height, box
    assert all(f"{list(doubts.values()).count(reason)} {reason}" in top.get_title() for reason in set(doubts.values()))


@pytest.mark.parametrize("n", [8, 30, 60])
def test_scan_colours_are_categorical(n):
    """The issue's case: random colours put two beiges 24 RGB units apart at 8 scans, 13 near pairs at 30.
    The recording and the picture share the palette, and it is the same on every run."""
    c = scan_colours(n).astype(float)
    assert c.shape == (n, 3) and pdist(c).min() > 55
    np.testing.assert_array_equal(scan_colours(n), c)
    np.testing.assert_array_equal(scan_colours(n + 700)[:n], c)  # a scan keeps its colour as scans are added


# --- the command line ------------------------------------------------------------------------------------------

runner = CliRunner()


def _help(command):
    """The help text of ``command`` as one line of words (rich wraps it inside a box)."""
    r = runner.invoke(app, [command, "--help"], env={"COLUMNS": "250"})
    assert r.exit_code == 0, r.output
    return " ".join(r.output.replace("│", " ").split())


def test_run_help_shows_defaults_and_choices():
    text = _help("run")
    for default in (
        "[default: results/<scene name>]",
        "[default: 1/100 of the median scan's bounding-box diagonal]",
        "[default: 10]",
        "[default: 50]",
        "[default: history]",
        "[default: loops]",
        "[default: vlad]",
        "[default: 0]",
        "[default: every core]",
        "[default: --record]",
    ):
        assert default in text, default
    for choice in ("history", "constant", "current", "spectral", "lm", "loops", "robust", "none", "learned"):
        assert re.search(rf"\b{choice}\b", text), choice
    assert "--quiet" in text and "Synchronization method ." not in text
    text = _help("sync")
    for default in (
        "[default: history]",
        "[default: 50]",
        "[default: loops]",
        "[default: information]",
        "[default: none]",
    ):
        assert default in text, default
    assert "huber, cauchy or tls" in text and "shonan" in text


def test_help_lists_every_choice_of_the_modules():
    from sghr_gtsam import cli
    from sghr_gtsam.gtsam_api import KERNELS, NOISE_MODELS
    from sghr_gtsam.sync import METHODS, POLISHES
    from sghr_gtsam.sync.baselines import BASELINES

    for name in METHODS:
        assert re.search(rf"\b{name}\b", cli._METHOD_HELP), name
    for name in POLISHES:
        assert re.search(rf"\b{name}\b", cli._POLISH_HELP), name
    text = _help("sync")
    for name in (*KERNELS, *NOISE_MODELS, *BASELINES):
        assert re.search(rf"\b{name}\b", text), name
    assert cli._METHOD_NAMES == tuple(METHODS) and set(cli._BASELINE_NAMES) == set(BASELINES)
    from sghr_gtsam.synthetic import SCENE_KINDS

    assert cli._SCENE_KINDS == SCENE_KINDS
    text = _help("demo")
    for name in ("auto", *SCENE_KINDS):
        assert re.search(rf"\b{name}\b", text), name
    assert f"room up to {cli._ONE_ROOM} scans, building above" in text


@pytest.fixture(scope="module")
def small_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli") / "scene"
    write_scene(make_scene(kind="room", n_scans=3, seed=1), d)
    return d


def test_run_off_a_terminal_prints_messages_and_summary_but_no_bars(small_scene, tmp_path):
    r = runner.invoke(app, ["run", str(small_scene), "--out", str(tmp_path / "out"), "--no-record", "--workers", "1"])
    assert r.exit_code == 0, r.output
    assert "━" not in r.output and "ETA" not in r.output
    assert re.search(r"^pairwise: \d+ pairs", r.output, re.MULTILINE)
    assert re.search(r"^scans placed\s+3/3$", r.output, re.MULTILINE)
    assert re.search(r"^worst residual\s+\d+\.\d+° \(", r.output, re.MULTILINE)
    assert re.search(r"^seconds\s+[\d.]+ total: load [\d.]+ · features", r.output, re.MULTILINE)
    assert "rerun" not in r.output  # nothing recorded


def test_quiet_run_prints_the_summary_and_how_to_open_the_recording(small_scene, tmp_path):
    out = tmp_path / "out"
    r = runner.invoke(app, ["run", str(small_scene), "--out", str(out), "--quiet", "--workers", "1"])
    assert r.exit_code == 0, r.output
    assert "pairwise:" not in r.output and "voxel" not in r.output
    assert re.search(r"^scans placed\s+3/3$", r.output, re.MULTILINE)
    assert r.output.rstrip().splitlines()[-1] == f"review the run: rerun {out / 'recording.rrd'}"
    assert (out / "recording.rrd").is_file() and (out / "summary.png").is_file()


def test_summary_figure_places_georeferenced_scans_where_local_ones_are():
    """The same room in local and in georeferenced coordinates (5,000 km off the origin: the pipeline registers
    centred scans and hands the poses back in the input frames): its top view puts the scans' centres as far apart."""
    from matplotlib.collections import PathCollection

    from sghr_gtsam.pipeline import register
    from sghr_gtsam.types import Scan

    scene = make_scene(kind="room", n_scans=4, seed=0)
    offset = np.array([4.1e5, 5.3e6, 120.0])
    spreads = []
    for shift in (np.zeros(3), offset):
        scans = [Scan(n, P + shift) for n, P in zip(scene.names, scene.scans)]
        result = register(scans, Config(workers=1, record=False), log=lambda m: None)
        assert result.unregistered == []
        dots = next(c for c in summary_figure(result).axes[0].collections if isinstance(c, PathCollection))
        spreads.append(pdist(dots.get_offsets()))
    np.testing.assert_allclose(spreads[1], spreads[0], atol=0.05)


def test_every_flag_has_a_colour_of_its_own():
    """A run whose doubts included a reason without a colour failed at its end (KeyError in the recording)."""
    from sghr_gtsam.result import FLAGS

    assert set(FLAGS) == set(FLAG_COLOURS)
    assert len(set(FLAG_COLOURS.values())) == len(FLAG_COLOURS)
