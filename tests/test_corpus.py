"""The hostile-input corpus: every case generated here, each asserting the one line the user gets
(never a traceback), the exit code and what is left in the output folder; hypothesis fuzzes the PLY, PCD and g2o
readers. docs/BENCHMARKS.md lists the cases and their outcomes.

Most cases fail before registration (a scene of one good scan and one bad file: the run stops with the bad file
named and why), so they take milliseconds; the cases that must register share a few runs (module fixtures)."""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from sghr_gtsam.cli import app
from sghr_gtsam.config import Config
from sghr_gtsam.gtsam_api import pose_covariances
from sghr_gtsam.io import atomic
from sghr_gtsam.io.atomic import staged_folder
from sghr_gtsam.io.g2o import read_g2o, write_g2o
from sghr_gtsam.io.results import CACHE, RESULT_FILES
from sghr_gtsam.io.scans import load_scan, write_scan
from sghr_gtsam.pipeline import Scan, register
from sghr_gtsam.se3 import inv_T, make_T, relative_errors
from sghr_gtsam.synthetic import make_scene, write_scene
from sghr_gtsam.types import InputError, PoseGraph

runner = CliRunner()
OLD = {"poses.txt": "old poses\n", "report.json": "{}\n", "recording.rrd": "old recording\n"}


def _cli(*args) -> tuple[int, list[str]]:
    r = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in r.output, r.output
    assert r.exception is None or isinstance(r.exception, SystemExit), repr(r.exception)
    return r.exit_code, r.output.strip().splitlines()


def _old_result(out: Path) -> Path:
    out.mkdir(parents=True)
    for name, text in OLD.items():
        (out / name).write_text(text)
    return out


def _untouched(out: Path) -> bool:
    """``out`` holds the earlier result exactly (beside the resume cache the run wrote in place), and no staging
    folder is left beside it."""
    left = {p.name: p.read_text() for p in out.iterdir() if p.name != CACHE}
    return left == OLD and not [p for p in out.parent.iterdir() if p.name.startswith(f".{out.name}.")]


def _good_scan(seed: int = 0) -> np.ndarray:
    """A small scan with extent (a noisy box surface of 600 points)."""
    rng = np.random.default_rng(seed)
    P = rng.uniform(-1, 1, (600, 3))
    P[np.arange(600), rng.integers(0, 3, 600)] = rng.choice([-1.0, 1.0], 600)
    return P


def _ply_header(n: int, fmt: str = "ascii", kind: str = "float") -> str:
    return (
        f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty {kind} x\nproperty {kind} y\n"
        f"property {kind} z\nend_header\n"
    )


def _ascii_ply(P: np.ndarray, declared: int | None = None) -> str:
    return _ply_header(len(P) if declared is None else declared) + "".join(f"{x} {y} {z}\n" for x, y, z in P)


def _binary_ply(P: np.ndarray, declared: int | None = None, kind: str = "float", data: str = "<f4") -> bytes:
    header = _ply_header(len(P) if declared is None else declared, "binary_little_endian", kind).encode()
    return header + P.astype(data).tobytes()


def _pcd(P: np.ndarray, points: int | None = None, width: int | None = None, rows: list[str] | None = None) -> str:
    n = len(P)
    body = rows if rows is not None else [f"{x} {y} {z}" for x, y, z in P]
    return (
        "VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {n if width is None else width}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {n if points is None else points}\nDATA ascii\n" + "\n".join(body) + "\n"
    )


def _corrupt_row(P: np.ndarray) -> str:
    lines = _ascii_ply(P).splitlines(keepends=True)
    lines[7 + 10] = "0.5 oops 0.25\n"  # header (7 lines), then row 10
    return "".join(lines)


def _stray(P: np.ndarray) -> np.ndarray:
    Q = P.copy()
    Q[5] = [1e9, 0.0, 0.0]
    return Q


G = _good_scan(1)
# name -> (file name, content: str | bytes | ndarray | callable(path), words the reason must contain)
BAD_FILES = {
    "binary garbage as ply": ("bad.ply", bytes(range(256)) * 4, "not a PLY file"),
    "truncated binary ply": ("bad.ply", _binary_ply(G)[:-100], "truncated PLY"),
    "non-number in an ascii ply row": ("bad.ply", _corrupt_row(G), "line 18: not a number"),
    "ascii ply header count too low": ("bad.ply", _ascii_ply(G, declared=500), "declares 500"),
    "binary ply header count too low": ("bad.ply", _binary_ply(G, declared=500), "declares 6000"),
    "float header over double data": ("bad.ply", _binary_ply(G, data="<f8"), "float written as double"),
    "ply header without end_header": ("bad.ply", _ply_header(5).replace("end_header\n", ""), "end_header"),
    "pcd points differ from width": ("bad.pcd", _pcd(G, width=10), "WIDTH x HEIGHT"),
    "truncated ascii pcd": ("bad.pcd", _pcd(G, rows=[f"{x} {y} {z}" for x, y, z in G[:300]]), "truncated PCD"),
    "non-number in a pcd row": (
        "bad.pcd",
        _pcd(G, rows=[f"{x} {y} {z}" for x, y, z in G[:-1]] + ["1 nan? 2"]),
        "not a number",
    ),
    "all nan": ("bad.npy", np.full((600, 3), np.nan), "0 finite points"),
    "all inf": ("bad.xyz", np.full((600, 3), np.inf), "0 finite points"),
    "all points identical": ("bad.npy", np.ones((600, 3)), "coincide"),
    "2d data (two columns)": ("bad.xyz", "1 2\n3 4\n" * 200, "expected x y z"),
    "npy of wrong shape": ("bad.npy", np.zeros((600, 2)), "shape (600, 2)"),
    "npy of three dimensions": ("bad.npy", np.zeros((10, 20, 3)), "shape (10, 20, 3)"),
    "empty file": ("bad.ply", b"", "empty file"),
    "symlink loop": ("bad.ply", lambda p: os.symlink(p.name, p), "leads nowhere"),
    "broken symlink": ("bad.ply", lambda p: os.symlink("nowhere.ply", p), "leads nowhere"),
    "one stray point at 1e9 m": ("bad.npy", _stray(_good_scan(2)), "stray point"),
    # nothing that is not a regular file is opened: a link to a FIFO hung the run for ever (the memory check opened
    # it), a plain FIFO was left out without a word, a link to /dev/zero "leads nowhere"
    "named pipe": ("bad.ply", os.mkfifo, "a named pipe (FIFO)"),
    "symlink to a named pipe": (
        "bad.ply",
        lambda p: os.mkfifo(p.with_name("pipe")) or os.symlink("pipe", p),
        "a symbolic link to a named pipe (FIFO)",
    ),
    "symlink to /dev/zero": (
        "bad.ply",
        lambda p: os.symlink("/dev/zero", p),
        "a symbolic link to a character device (/dev/zero)",
    ),
    # UTM-like coordinates stored as float32: rounded to steps of 1 m, they registered nothing, and the error asked
    # only whether the scans overlap
    "float32 at 1e7 m": ("bad.ply", _binary_ply(_good_scan(2) + [1e7, 2e6, 0]), "where float32 rounds to steps of 1,"),
}


def _write_bad(path: Path, content) -> None:
    if callable(content):
        content(path)
    elif isinstance(content, np.ndarray):
        if path.suffix == ".npy":
            np.save(path, content)
        else:
            np.savetxt(path, content)
    else:
        path.write_bytes(content if isinstance(content, bytes) else content.encode())


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_scan_is_named_with_its_reason(case, tmp_path):
    """A good scan and a bad file: the bad file is skipped with its reason, which leaves one scan, so the run
    ends in one line naming the file and why; the earlier result stays as it was."""
    name, content, reason = BAD_FILES[case]
    scene = tmp_path / "scene"
    scene.mkdir()
    np.save(scene / "good.npy", _good_scan(0))
    _write_bad(scene / name, content)
    out = _old_result(tmp_path / "out")
    with _at_most(60):  # a run that opens a pipe waits for ever
        code, lines = _cli("run", scene, "--out", out, "--workers", "1")
    assert code == 2
    assert lines[-1].startswith("error: ") and f"skipped {name}" in lines[-1] and reason in lines[-1], lines[-1]
    assert [line for line in lines if line.startswith("error:")] == lines[-1:]
    assert _untouched(out)


@contextlib.contextmanager
def _at_most(seconds: float):
    """The block, failed (not hung) when it takes longer than ``seconds``: SIGALRM, sent to the main thread itself
    (sent to the process, another thread may take it and a blocking open goes on waiting) every second from then on
    (code that swallows the error may open the pipe again)."""

    def hung(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    done = threading.Event()

    def alarm() -> None:
        if not done.wait(seconds):
            while not done.wait(1.0):
                signal.pthread_kill(threading.main_thread().ident, signal.SIGALRM)

    previous = signal.signal(signal.SIGALRM, hung)
    thread = threading.Thread(target=alarm, daemon=True)
    thread.start()
    try:
        yield
    finally:
        done.set()
        thread.join()
        signal.signal(signal.SIGALRM, previous)


def _scene_with_scan(tmp_path: Path) -> Path:
    scene = tmp_path / "scene"
    scene.mkdir()
    for k in range(2):
        np.save(scene / f"s{k}.npy", _good_scan(k))
    return scene


def _with_git(folder: Path) -> Path:
    """A folder whose only entry is hidden: the swap deleted it (hidden names were not counted as foreign)."""
    (folder / ".git").mkdir(parents=True)
    (folder / ".git" / "HEAD").write_text("ref: refs/heads/main\n")
    return folder


def _with_notes(folder: Path) -> Path:
    folder.mkdir()
    (folder / "notes.md").write_text("mine")
    return folder


def _config_file(tmp_path: Path, data: str) -> Path:
    path = tmp_path / "config.json"
    path.write_text(data)
    return path


# name -> (arguments after `run SCENE --out OUT`, or a callable(tmp_path, scene, out) giving all arguments;
#          words of the one line)
BAD_RUNS = {
    "empty folder": (lambda t, s, o: [(t / "empty").mkdir() or t / "empty", "--out", o], "no scans in"),
    "missing folder": (lambda t, s, o: [t / "nowhere", "--out", o], "does not exist"),
    "scene is a file": (lambda t, s, o: [s / "s0.npy", "--out", o], "is not a folder"),
    "--out an existing file": (
        lambda t, s, o: [s, "--out", (t / "f.txt").write_text("x") and t / "f.txt"],
        "is an existing file",
    ),
    "--out equal to the scene folder": (lambda t, s, o: [s, "--out", s], "is the scan folder"),
    "--out holding the scene folder": (lambda t, s, o: [s, "--out", t], "holds the scan folder"),
    "--out a folder of other files": (lambda t, s, o: [s, "--out", _with_notes(o)], "not a run's results (notes.md)"),
    "--out a folder holding a hidden .git": (lambda t, s, o: [s, "--out", _with_git(o)], "not a run's results (.git)"),
    "--voxel negative": (["--voxel", "-1"], "voxel must be a positive finite number"),
    "--voxel nan": (["--voxel", "nan"], "voxel must be a positive finite number"),
    "--k 0": (["--k", "0"], "k must be a positive integer"),
    "--method unknown": (["--method", "magic"], "method must be one of"),
    "--workers 0": (["--workers", "0"], "workers must be a positive integer"),
    "config voxel as a string": (
        lambda t, s, o: [s, "--out", o, "--config", _config_file(t, '{"voxel": "0.1"}')],
        "voxel must be float or null; got '0.1'",
    ),
    "config record as a string": (
        lambda t, s, o: [s, "--out", o, "--config", _config_file(t, '{"record": "no"}')],
        "record must be bool",
    ),
    "config negative icp_distance": (
        lambda t, s, o: [s, "--out", o, "--config", _config_file(t, '{"icp_distance": -5}')],
        "icp_distance must",
    ),
    "config negative min_inliers": (
        lambda t, s, o: [s, "--out", o, "--config", _config_file(t, '{"min_inliers": -1}')],
        "min_inliers must",
    ),
    "config negative min_weight": (
        lambda t, s, o: [s, "--out", o, "--config", _config_file(t, '{"min_weight": -0.5}')],
        "min_weight must",
    ),
    "config unknown key": (
        lambda t, s, o: [s, "--out", o, "--config", _config_file(t, '{"colour": 1}')],
        "unknown keys ['colour']",
    ),
    "config not an object": (
        lambda t, s, o: [s, "--out", o, "--config", _config_file(t, "[1, 2]")],
        "must hold a JSON object",
    ),
    "--features missing folder": (lambda t, s, o: [s, "--out", o, "--features", t / "nowhere"], "features"),
    "--features a file": (lambda t, s, o: [s, "--out", o, "--features", s / "s0.npy"], "features"),
    # crawled the current folder (from /, the whole tree)
    "--features empty": (["--features", ""], "features must name a folder; got an empty path"),
    # "unexpected MemoryError", "unexpected IndexError", or no bound at all
    "--iters 1e9": (["--iters", "1000000000"], "iters must be an integer from 1 to 10,000; got 1,000,000,000"),
    "--iters 2^63": (["--iters", str(2**63)], "iters must be an integer from 1 to 10,000; got 9,223,372,036,854,775,"),
    "--iters 1e6": (["--iters", "1000000"], "iters must be an integer from 1 to 10,000; got 1,000,000"),
    # "unexpected RuntimeError", and "File exists" for "Not a directory"
    "--out a symbolic link loop": (
        lambda t, s, o: [s, "--out", os.symlink("loop", t / "loop") or t / "loop"],
        "is, or lies through, a symbolic link loop",
    ),
    "--out below a file": (
        lambda t, s, o: [s, "--out", (t / "f").write_text("x") and t / "f" / "sub"],
        "cannot be made: ",
    ),
}


@pytest.mark.parametrize("case", list(BAD_RUNS))
def test_bad_folder_or_flag_is_one_line_error(case, tmp_path):
    scene = _scene_with_scan(tmp_path)
    out = tmp_path / "out"
    args, needle = BAD_RUNS[case]
    args = args(tmp_path, scene, out) if callable(args) else [scene, "--out", out, *args]
    code, lines = _cli("run", *args, "--workers", "1") if "--workers" not in args else _cli("run", *args)
    assert code == 2, lines
    assert lines[-1].startswith("error: ") and needle in lines[-1], lines[-1]
    assert [line for line in lines if line.startswith("error:")] == lines[-1:]
    assert list(scene.iterdir()) and {p.name for p in scene.iterdir()} == {"s0.npy", "s1.npy"}
    assert not (out / "report.json").exists() and not list(tmp_path.glob(".out.tmp-*"))


def test_scans_that_do_not_overlap_leave_the_earlier_result(tmp_path):
    rng = np.random.default_rng(3)
    scene = tmp_path / "scene"
    scene.mkdir()
    np.save(scene / "a.npy", rng.random((2000, 3)))
    np.save(scene / "b.npy", rng.random((2000, 3)) * [5, 0.1, 1] + 10)
    out = _old_result(tmp_path / "out")
    code, lines = _cli("run", scene, "--out", out, "--workers", "1")
    assert code == 2 and lines[-1] == "error: no pair of scans could be registered (do the scans overlap?)"
    assert _untouched(out)


@pytest.mark.parametrize("voxel, times", [(1e6, "1.36e+07x"), (1e-4, "0.00136x"), (1e308, "beyond any multiple of")])
def test_a_voxel_far_from_the_default_is_named_when_nothing_registers(small_room, tmp_path, voxel, times):
    """A voxel 10⁷× too coarse or 10³× too fine registers nothing; the error asked only whether the scans
    overlap, which they do. (1e308 read "infx the default".)"""
    code, lines = _cli("run", small_room, "--out", tmp_path / "out", "--voxel", voxel, "--workers", "1", "--no-record")
    assert code == 2 and lines[-1].startswith(
        "error: no pair of scans could be registered (do the scans overlap? "
        f"is the voxel {voxel:.3g} right? it is {times} the default "
    ), lines


def test_scan_too_large_for_the_memory_stops_before_reading_it(tmp_path):
    """A scan whose header declares more points than memory holds: one line naming it and the sizes, exit 2,
    before it is read (the machine would otherwise swap or kill the run); the earlier result stays."""
    scene = _scene_with_scan(tmp_path)
    (scene / "huge.ply").write_text(_ply_header(10**11))
    out = _old_result(tmp_path / "out")
    code, lines = _cli("run", scene, "--out", out, "--workers", "1")
    assert code == 2 and lines[-1].startswith(
        "error: scan huge.ply holds 100,000,000,000 points: reading it needs about "
    ), lines
    assert "GB are available" in lines[-1] and _untouched(out)


# --- runs that register: one scene holding every kind of bad scan among good ones ---------------------------------

GOOD_NAMES = ["scan 0 with spaces.ply", "skän_1.ply", "scan_2.ply", "scan_3.ply"]
SKIPPED = {
    "mm.ply": "another unit",  # scan_1 in millimetres
    "stray.npy": "stray point",
    "double.ply": "float written as double",
    "corrupt.ply": "not a number",
    "loop.ply": "leads nowhere",
}


@pytest.fixture(scope="module")
def mixed_bag(tmp_path_factory):
    """Four room scans (names with spaces and non-ASCII) and every kind of bad scan; run twice into a results
    folder inside the scene folder, the second time without recording."""
    root = tmp_path_factory.mktemp("bag")
    scene = make_scene(kind="room", n_scans=4, seed=0)
    d = root / "scene"
    d.mkdir()
    for name, P in zip(GOOD_NAMES, scene.scans):
        write_scan(d / name, P)
    write_scan(d / "mm.ply", scene.scans[1] * 1000.0)
    np.save(d / "stray.npy", _stray(scene.scans[2]))
    (d / "double.ply").write_bytes(_binary_ply(scene.scans[3], data="<f8"))
    (d / "corrupt.ply").write_text(_corrupt_row(scene.scans[0][:500]))
    os.symlink("loop.ply", d / "loop.ply")
    out = d / "results"
    first = _cli("run", d, "--out", out, "--workers", "1")
    report_1 = json.loads((out / "report.json").read_text())
    recorded = (out / "recording.rrd").exists()
    second = _cli("run", d, "--out", out, "--workers", "1", "--no-record")
    return scene, out, first, report_1, recorded, second


@pytest.mark.parametrize("name", list(SKIPPED))
def test_bad_scan_among_good_ones_is_skipped_and_named(mixed_bag, name):
    _, out, (code, lines), report, _, _ = mixed_bag
    assert code == 0, lines
    assert SKIPPED[name] in report["skipped"][name]
    assert any(line.startswith(f"skipped {name}") for line in lines)


def test_good_scans_with_spaces_and_non_ascii_names_register(mixed_bag):
    scene, out, (code, _), report, recorded, _ = mixed_bag
    assert code == 0 and recorded
    assert sorted(report["registered"]) == sorted(GOOD_NAMES) and set(report["skipped"]) == set(SKIPPED)
    from sghr_gtsam.io.poses import read_poses

    names, poses = read_poses(out / "poses.txt")
    gt = scene.poses[[GOOD_NAMES.index(n) for n in names]]
    rot, trans = relative_errors(poses, inv_T(gt[0]) @ gt)
    assert rot.max() < 1.0 and trans.max() < 2 * report["voxel"]


def test_second_run_into_the_scene_folder_reads_no_output_and_keeps_no_old_file(mixed_bag):
    """--out inside the scene folder, twice: the same scans (merged.ply is not read), and the run without
    recording leaves no recording of the first run."""
    _, out, _, first, _, (code, lines) = mixed_bag
    second = json.loads((out / "report.json").read_text())
    assert code == 0, lines
    assert second["scans"] == first["scans"] and sorted(second["registered"]) == sorted(GOOD_NAMES)
    assert {p.name for p in out.iterdir()} == set(RESULT_FILES) - {"recording.rrd"} | {CACHE}
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".results.")]


# --- georeferenced coordinates -----------------------------------------------------------------------------------


def test_georeferenced_scans_register_exactly_as_near_the_origin():
    """The same 4 scans near the origin and at 1e3, 1e6 and 1e9 m (UTM-like offsets): scans that far out are
    centred, and the poses handed back in the input frame are the origin run's once the offset is taken out, with the
    same edges, to 1e-4. Not to float64's resolution: the coordinates' rounding differs with the offset (1e-10 m at
    1e6 m), and a normal nearly at right angles to the direction it is oriented towards flips with it, which moves
    that point's FPFH (seen on one CPU and not on another)."""
    scene = make_scene(kind="room", n_scans=4, seed=2)
    runs = {}
    for offset in (0.0, 1e3, 1e6, 1e9):
        shift = np.array([offset, -0.7 * offset, 0.01 * offset])
        res = register(
            [Scan(n, P + shift) for n, P in zip(scene.names, scene.scans)],
            Config(record=False, workers=1),
            log=lambda m: None,
        )
        S = make_T(np.eye(3), shift)
        assert res.unregistered == []
        np.testing.assert_array_equal(res.poses[0], np.eye(4))
        if offset == 1e3:  # centred: the information and covariances mapped back agree with gtsam's on the result
            C = pose_covariances(res)
            np.testing.assert_allclose(C, res.covariances, rtol=0, atol=1e-3 * np.abs(C).max())
        runs[offset] = inv_T(S) @ res.poses @ S, res.graph.num_edges
    gt = inv_T(scene.poses[0]) @ scene.poses
    rot, trans = relative_errors(runs[0.0][0], gt)
    assert rot.max() < 0.1 and trans.max() < 0.01
    for offset in (1e3, 1e6, 1e9):
        assert runs[offset][1] == runs[0.0][1]
        np.testing.assert_allclose(runs[offset][0], runs[0.0][0], atol=1e-4)


def test_a_scan_in_another_unit_is_named_by_the_api():
    scans = [Scan(f"s{k}", _good_scan(k)) for k in range(3)] + [Scan("mm", _good_scan(3) * 1000)]
    log: list[str] = []
    try:  # whether the three boxes register does not matter here: what was skipped before does
        register(scans, Config(record=False, workers=1), log=log.append)
    except InputError:
        pass
    assert any(line.startswith("skipped mm: its extent") and "1e+03x" in line for line in log), log


# --- signals: a run stopped at any point leaves the earlier result -----------------------------------------------


@pytest.fixture(scope="module")
def small_room(tmp_path_factory):
    d = tmp_path_factory.mktemp("signals") / "scene"
    write_scene(make_scene(kind="room", n_scans=4, seed=1), d)
    return d


def _stop_mid_run(scene: Path, out: Path, signum: int) -> tuple[int, str, list[int]]:
    """Start a run, send ``signum`` to it alone once it is registering pairs; ``_stopped_run``'s answer."""

    def when(proc: subprocess.Popen) -> None:
        for line in proc.stdout:
            if line.startswith("features:"):  # the pairwise stage is starting
                break
        time.sleep(0.5)

    return _stopped_run(scene, out, signum, when, group=False)


def _stopped_run(scene: Path, out: Path, signum: int, when, group: bool) -> tuple[int, str, list[int]]:
    """A run started with 2 workers, ``signum`` sent once ``when(proc)`` returns: its exit code, its stderr, and
    the processes it started that are still running 10 s after it ended (workers, fork server)."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1]), "OPENBLAS_NUM_THREADS": "1"}
    with tempfile.TemporaryFile("w+") as err:  # not a pipe: a killed run's orphaned workers would hold it open
        proc = subprocess.Popen(
            [sys.executable, "-m", "sghr_gtsam", "run", str(scene), "--out", str(out), "--workers", "2"],
            stdout=subprocess.PIPE,
            stderr=err,
            text=True,
            env=env,
            start_new_session=True,
        )
        try:
            when(proc)
            if group:
                os.killpg(proc.pid, signum)
            else:
                proc.send_signal(signum)
            code = proc.wait(timeout=120)
            deadline = time.monotonic() + 10
            while (left := _running(session=proc.pid)) and time.monotonic() < deadline:
                time.sleep(0.1)
        finally:  # whatever is left, as a job scheduler would
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.stdout.close()
        err.seek(0)
        return code, err.read(), left


def _running(session: int | None = None, parent: int | None = None, command: bytes = b"") -> list[int]:
    """The processes running (not ended) in ``session`` or with the ``parent``, whose command line holds
    ``command``."""
    found = []
    for proc in Path("/proc").iterdir():
        try:
            state, ppid, _, sid = (proc / "stat").read_text().rsplit(")", 1)[1].split()[:4]
            if (
                state != "Z"
                and (session is None or int(sid) == session)
                and (parent is None or int(ppid) == parent)
                and command in (proc / "cmdline").read_bytes()
            ):
                found.append(int(proc.name))
        except (OSError, ValueError):  # not a process, or one that ended meanwhile
            continue
    return found


def test_ctrl_c_while_the_run_loads_ends_in_one_line(small_room, tmp_path):
    """A terminal's Ctrl-C reaches the run's whole process group. Sent while the run imports the pipeline and its
    fork server imports the workers' modules, it printed the server's KeyboardInterrupt traceback, and open3d,
    interrupted in its initialisation, ended the run with an ImportError traceback (exit 1)."""

    def when(proc: subprocess.Popen) -> None:
        deadline = time.monotonic() + 60
        while not _running(parent=proc.pid, command=b"forkserver") and time.monotonic() < deadline:
            time.sleep(0.01)

    out = _old_result(tmp_path / "out")
    code, err, left = _stopped_run(small_room, out, signal.SIGINT, when, group=True)
    assert code == 130 and not left, (err, left)
    assert err.strip().splitlines() == [
        "error: stopped by SIGINT: nothing written, earlier results left as they were"
    ], err
    assert {p.name: p.read_text() for p in out.iterdir() if p.name != CACHE} == OLD


@pytest.mark.parametrize("signum, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143), (signal.SIGKILL, -9)])
def test_stopped_run_leaves_the_earlier_result(small_room, tmp_path, signum, code):
    out = _old_result(tmp_path / "out")
    got, err, left = _stop_mid_run(small_room, out, signum)
    assert got == code, err
    assert not left, left  # a run killed outright takes its workers with it (``executor._end_with``)
    assert {p.name: p.read_text() for p in out.iterdir() if p.name != CACHE} == OLD
    if signum == signal.SIGKILL:  # nothing could clean up: the next run removes the staging folder
        stale = [p for p in tmp_path.iterdir() if p.name.startswith(".out.tmp-")]
        assert len(stale) == 1
        with staged_folder(out, carry=CACHE) as stage:
            assert not stale[0].exists()
            (stage / "poses.txt").write_text("new\n")
        assert [p.name for p in out.iterdir() if p.name != CACHE] == ["poses.txt"]
    else:
        name = signal.Signals(signum).name
        assert err.strip().splitlines() == [
            f"error: stopped by {name}: nothing written, earlier results left as they were"
        ], err
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.")]


_STOP_LATE = """
import atexit, os, signal, sys, time
import sghr_gtsam.__main__ as command
from sghr_gtsam import cli

app, when = cli.app, sys.argv[1]

def stopped_late(*args, **kwargs):  # the stop as the command returns, or as Python shuts down
    try:
        app(*args, **kwargs)
    finally:
        if when == "returning":
            signal.raise_signal(signal.{signal})
        else:
            atexit.register(lambda: (os.kill(os.getpid(), signal.{signal}), time.sleep(5)))

cli.app = stopped_late
sys.argv = [sys.argv[0], "run", *sys.argv[2:]]
command.main("sghr-gtsam")
"""


@pytest.mark.parametrize("when", ["returning", "shutting down"])
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_stop_after_the_results_are_swapped_in_says_they_are_complete(small_room, tmp_path, when, signum):
    """A Ctrl-C right after the summary: as the command returned it said "nothing written" of complete results, and
    while Python shut down it printed "Exception ignored in: <module 'threading'> ... _Stopped: 2" and exited 0 (or
    ended with 130/143 and no line once Python had put the default handlers back)."""
    name = signal.Signals(signum).name
    out = tmp_path / "out"
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            _STOP_LATE.replace("{signal}", name),
            when,
            str(small_room),
            "--out",
            str(out),
            "--workers",
            "1",
            "--no-record",
            "--quiet",
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert done.returncode == 128 + signum, done.stderr
    assert done.stderr.splitlines() == [
        f"error: stopped by {name} after the results were written: {out} is complete"
    ], done.stderr
    assert (out / "report.json").is_file()


def test_a_scan_given_twice_gets_finite_covariances_and_strict_json(small_room, tmp_path):
    """Two identical scans fit with residuals of rounding alone: their information overflowed, gtsam's marginals
    gave NaN, report.json held 190 NaN (which strict JSON readers refuse) and every scan was reported loose."""
    scene = tmp_path / "scene"
    shutil.copytree(small_room, scene)
    first = sorted(p for p in scene.iterdir() if p.suffix == ".ply")[1]
    shutil.copy(first, scene / "scan_99.ply")
    code, lines = _cli("run", scene, "--out", tmp_path / "out", "--workers", "1", "--no-record", "--quiet")
    assert code == 0, lines
    report = json.loads(
        (tmp_path / "out" / "report.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in report.json")
    )
    assert report["loose"] == {} and len(report["registered"]) == 5
    covariances = [np.array(c["covariance"]) for c in report["pose_covariances"].values()]
    assert all(np.all(np.isfinite(c)) for c in covariances)


def test_swap_keeps_the_resume_cache(tmp_path):
    """OUT/cache, written in place during a run, survives a completed swap and a failed run."""
    out = _old_result(tmp_path / "out")
    (out / "cache").mkdir()
    (out / "cache" / "scan.npz").write_text("cached")
    with pytest.raises(RuntimeError):
        with staged_folder(out, carry=CACHE) as stage:
            (stage / "poses.txt").write_text("half")
            raise RuntimeError
    assert (out / "cache" / "scan.npz").read_text() == "cached" and (out / "poses.txt").read_text() == OLD["poses.txt"]
    with staged_folder(out, carry=CACHE) as stage:
        (stage / "poses.txt").write_text("new\n")
    assert sorted(p.name for p in out.iterdir()) == ["cache", "poses.txt"]
    assert (out / "cache" / "scan.npz").read_text() == "cached"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]


@pytest.mark.parametrize("failing", [1, 2, 3], ids=["the cache", "the old results", "the new results"])
def test_a_swap_the_file_system_refuses_leaves_the_earlier_results_and_their_cache(tmp_path, monkeypatch, failing):
    """An OUT or OUT/cache that cannot be renamed (immutable, a read-only bind mount) ended the run as "unexpected
    PermissionError" after all its work; the ``failing``-th rename of the swap (no one-step exchange) now gives one
    line, and every rename that went before it is undone: the earlier results in place, with their cache."""
    out = _old_result(tmp_path / "out")
    (out / "cache").mkdir()
    (out / "cache" / "scan.npz").write_text("cached")
    renames, rename = [], os.rename

    def refusing(a, b):
        renames.append(a)
        if len(renames) == failing:
            raise PermissionError(1, "Operation not permitted", str(a))
        rename(a, b)

    monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)
    monkeypatch.setattr(atomic.os, "rename", refusing)
    with pytest.raises(
        InputError,
        match=f"cannot swap the results into {out}: Operation not permitted .*; the "
        "earlier results are left as they were",
    ):
        with staged_folder(out, carry=CACHE) as stage:
            (stage / "poses.txt").write_text("new\n")
    monkeypatch.undo()
    assert _untouched(out) and (out / "cache" / "scan.npz").read_text() == "cached"


def test_an_output_name_that_leaves_no_room_for_its_staging_folder_is_named(small_room, tmp_path):
    """An OUT name of 240 bytes is legal, its staging sibling is not: "File name too long" blamed the name given."""
    code, lines = _cli("run", small_room, "--out", tmp_path / ("L" * 240))
    assert code == 2 and lines[-1] == (
        "error: output folder name LLLLLLLLLLLLLLLLLLLL... is 240 bytes: the results "
        "are staged beside it as .LLLLLLLL...tmp-PID-XXXXXXXX, a name up to 22 bytes "
        "longer, which the file system refuses; choose a shorter name"
    ), lines


def test_a_failed_first_run_leaves_no_empty_cache_folder(tmp_path):
    """A first run that failed before its cache held an entry left an empty OUT/cache/features; an entry it stored
    stays for the next run to resume from, and an earlier result keeps its folder."""
    out = tmp_path / "out"
    with pytest.raises(OSError):
        with staged_folder(out, carry=CACHE):
            (out / "cache" / "features").mkdir(parents=True)  # as the cache makes its folder before a write fails
            raise OSError(28, "No space left on device")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(OSError):
        with staged_folder(out, carry=CACHE):
            (out / "cache" / "features").mkdir(parents=True)
            (out / "cache" / "pairs").mkdir()
            (out / "cache" / "features" / "a.npz").write_text("entry")
            raise OSError(28, "No space left on device")
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*")) == [
        "cache",
        "cache/features",
        "cache/features/a.npz",
    ]
    shutil.rmtree(out)
    _old_result(out)
    with pytest.raises(OSError):
        with staged_folder(out, carry=CACHE):
            (out / "cache" / "features").mkdir(parents=True)
            raise OSError(28, "No space left on device")
    assert _untouched(out) and not (out / "cache").exists()


def _poses(out: Path) -> np.ndarray:
    from sghr_gtsam.io.poses import read_poses

    return read_poses(out / "poses.txt")[1]


def test_cache_entries_that_are_no_files_or_no_rigid_transforms_are_recomputed(small_room, tmp_path):
    """Entries that are a folder, a pipe, a link to /dev/zero or a cached pair whose rotation is scaled or
    reflected each ended the run with exit 2 (the message not saying it was the cache); an entry linked to a user's
    file got that file overwritten. Each is now recomputed to the same poses and the user's file left alone; an
    OUT/cache, or its features folder, that is a file: the run keeps no cache, says so, and the file stays."""
    out = tmp_path / "out"
    args = ("run", small_room, "--out", out, "--workers", "1", "--no-record", "--quiet")
    assert _cli(*args)[0] == 0
    first = _poses(out)
    features, pairs = (sorted((out / CACHE / kind).glob("*.npz")) for kind in ("features", "pairs"))
    features[0].unlink()
    features[0].mkdir()
    features[1].unlink()
    os.mkfifo(features[1])
    features[2].unlink()
    os.symlink("/dev/zero", features[2])
    mine = tmp_path / "thesis.tex"
    mine.write_text("mine")
    pairs[0].unlink()
    os.symlink(mine, pairs[0])
    for path, change in zip(pairs[1:3], (np.diag([2.0, 2.0, 2.0, 1.0]), np.diag([1.0, 1.0, -1.0, 1.0]))):
        with np.load(path) as archive:
            arrays = dict(archive)
        arrays["T"] = arrays["T"] @ change
        with open(path, "wb") as f:
            np.savez(f, **arrays)
    with _at_most(120):
        code, lines = _cli(*args)
    assert code == 0, lines
    assert json.loads((out / "report.json").read_text())["cache"]["unreadable"] == 6
    np.testing.assert_allclose(_poses(out), first, atol=1e-9)
    assert mine.read_text() == "mine" and all(p.is_file() and not p.is_symlink() for p in features[:3] + pairs[:3])

    shutil.rmtree(out / CACHE / "features")
    (out / CACHE / "features").write_text("not a folder")
    code, lines = _cli(*args[:-1])
    assert (
        code == 0
        and f"the cache {out / CACHE} cannot be used ({out / CACHE / 'features'} is not a folder): this run keeps none"
        in lines
    ), lines
    shutil.rmtree(out / CACHE)
    (out / CACHE).write_text("a file")
    code, lines = _cli(*args[:-1])
    assert code == 0 and any(line.startswith(f"the cache {out / CACHE} cannot be used") for line in lines), lines
    assert (out / CACHE).read_text() == "a file"
    np.testing.assert_allclose(_poses(out), first, atol=1e-9)


def test_a_second_run_into_an_output_folder_being_written_refuses(small_room, tmp_path):
    """Two runs into one OUT both exited 0, the later silently replacing the other's results."""
    out = _old_result(tmp_path / "out")
    with staged_folder(out, carry=CACHE) as stage:  # a run writing OUT
        code, lines = _cli("run", small_room, "--out", out, "--workers", "1", "--no-record", "--quiet")
        assert code == 2 and lines == [
            f"error: {out} is being written by another run (pid {os.getpid()}): wait for "
            f"it to end, or choose another output folder"
        ], lines
        (stage / "poses.txt").write_text("new\n")
    assert [p.name for p in out.iterdir()] == ["poses.txt"] and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_a_linked_cache_keeps_the_users_empty_folders_after_a_failure(tmp_path):
    """OUT/cache linked to a user's folder: a failed run removed every empty folder in it."""
    mine = tmp_path / "mine"
    (mine / "empty" / "deeper").mkdir(parents=True)
    out = _old_result(tmp_path / "out")
    os.symlink(mine, out / CACHE)
    with pytest.raises(OSError):
        with staged_folder(out, carry=CACHE):
            (out / CACHE / "features").mkdir()  # the cache's own: removed
            raise OSError(28, "No space left on device")
    assert sorted(str(p.relative_to(mine)) for p in mine.rglob("*")) == ["empty", "empty/deeper"]


@contextlib.contextmanager
def _tmpfs(folder: Path, size: str):
    """A tmpfs of ``size`` mounted at ``folder`` for the block; skips the test where mounting is not allowed."""
    folder.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)], capture_output=True, text=True
    )
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {mounted.stderr.strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


def test_a_first_run_on_a_full_disk_says_so_and_leaves_nothing(small_room, tmp_path):
    """A full disk under --out: one line and exit 1; the failed first run left an empty OUT/cache/features."""
    with _tmpfs(tmp_path / "disk", "64k") as disk:
        code, lines = _cli("run", small_room, "--out", disk / "out", "--workers", "1", "--quiet")
        assert (code, lines) == (1, [f"error: cannot write {disk / 'out'}: No space left on device"])
        assert list(disk.iterdir()) == []


def test_a_cache_or_output_folder_that_is_a_mount_point_is_named(tmp_path):
    """OUT/cache as a mount point failed the final swap ("unexpected OSError: [Errno 16] Device or resource busy"),
    OUT as one too (EBUSY, or EXDEV when OUT/cache had to move across): a run says so before its work, and the
    swap itself names the mount point, the earlier result and the cache left as they were."""
    from sghr_gtsam.io.results import check_output_folder

    out = _old_result(tmp_path / "out")
    with _tmpfs(out / "cache", "1m") as cache:
        (cache / "entry.npz").write_text("cached")
        with pytest.raises(InputError, match=f"^{cache} is a mount point: "):
            check_output_folder(out, tmp_path / "scene")
        with pytest.raises(InputError, match=f"^{cache} is a mount point: "):
            with staged_folder(out, carry=CACHE) as stage:
                (stage / "poses.txt").write_text("new\n")
        assert _untouched(out) and (cache / "entry.npz").read_text() == "cached"
        assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    shutil.rmtree(out)
    with _tmpfs(out, "1m"):
        (out / "poses.txt").write_text(OLD["poses.txt"])
        with pytest.raises(InputError, match=f"^{out} is a mount point: "):
            check_output_folder(out, tmp_path / "scene")
        with pytest.raises(InputError, match=f"^{out} is a mount point: "):
            with staged_folder(out, carry=CACHE) as stage:
                (stage / "poses.txt").write_text("new\n")
        assert (out / "poses.txt").read_text() == OLD["poses.txt"]


# --- demo and train -------------------------------------------------------------------------------------------------


def test_demo_with_one_scan_or_a_file_as_out_is_one_line_error(tmp_path):
    code, lines = _cli("demo", "--scans", "1", "--out", tmp_path / "d")
    assert code == 2 and lines == ["error: --scans must be at least 2 (a registration needs two scans); got 1"]
    (tmp_path / "file").write_text("x")
    code, lines = _cli("demo", "--out", tmp_path / "file")
    assert code == 2 and lines == [f"error: --out {tmp_path / 'file'} is an existing file, not a folder"]
    assert not (tmp_path / "d").exists() and (tmp_path / "file").read_text() == "x"


def _tree(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): p.read_text() if p.is_file() else "/" for p in sorted(folder.rglob("*"))}


def test_demo_replaces_nothing_it_did_not_write(tmp_path):
    """`demo --out d` replaced d/scene with the user's scan and folder in it, without a word; with d/results
    holding the user's file it refused, but only after d/scene was replaced. Now it refuses before touching
    anything; its own earlier scene (gt_poses.txt and the scans it names) and results beside it it replaces."""
    d = tmp_path / "d"
    (d / "scene" / "sub").mkdir(parents=True)
    (d / "scene" / "my_scan.xyz").write_text("1 2 3\n")
    (d / "scene" / "sub" / "notes.md").write_text("n")
    before = _tree(d)
    code, lines = _cli("demo", "--out", d, "--scans", "3", "--workers", "1")
    assert code == 2 and lines == [
        f"error: --out {d}: {d / 'scene'} holds files the demo did not write (it writes "
        f"generated scans and gt_poses.txt, and replaces that folder as a whole); choose a "
        f"new or empty --out"
    ], lines
    assert _tree(d) == before

    e = tmp_path / "e"
    (e / "results").mkdir(parents=True)
    (e / "results" / "thesis.tex").write_text("mine")
    code, lines = _cli("demo", "--out", e, "--scans", "3", "--workers", "1")
    assert code == 2 and lines[-1].startswith(f"error: --out {e}: {e / 'results'} is not the demo's"), lines
    assert _tree(e) == {"results": "/", "results/thesis.tex": "mine"}

    from sghr_gtsam.cli import _check_demo_folders

    write_scene(make_scene(kind="room", n_scans=3, seed=0), d / "ours" / "scene")
    _old_result(d / "ours" / "results")
    _check_demo_folders(d / "ours")  # its own earlier output: replaced
    (d / "ours" / "scene" / "extra.ply").write_text("a user's scan")
    with pytest.raises(InputError, match="holds files the demo did not write"):
        _check_demo_folders(d / "ours")


def test_demo_with_an_absurd_scan_count_is_refused_before_any_work(tmp_path):
    """`demo --scans 100000000` ran until stopped (generating a building of 1e8 scans)."""
    done = subprocess.run(
        [sys.executable, "-m", "sghr_gtsam", "demo", "--scans", "100000000", "--out", str(tmp_path / "d")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2 and done.stderr.splitlines() == [
        "error: --scans must be at most 10,000 (the run's memory grows with the scans and their pairs: ~13 GB at "
        "10,000); got 100,000,000"
    ], done.stderr
    assert not (tmp_path / "d").exists()


def test_demo_with_an_unknown_kind_or_too_small_a_building_is_one_line_error(tmp_path):
    code, lines = _cli("demo", "--kind", "garden", "--out", tmp_path / "d")
    kinds = "room, object, fragments, building, hotel"
    assert code == 2 and lines == [f"error: --kind must be auto or one of {kinds}; got 'garden'"]
    code, lines = _cli("demo", "--kind", "hotel", "--scans", "5", "--out", tmp_path / "d")
    assert code == 2 and lines == ["error: --scans 5: a building needs at least 9 scans, got 5"]
    assert not (tmp_path / "d").exists()


@pytest.mark.parametrize(
    "case, needle",
    [
        ("corrupt", "cannot read cached scene"),
        ("incomplete", "no overlap array"),
        ("inconsistent", "is inconsistent"),
        ("empty folder", "no cached scenes"),
    ],
)
def test_train_on_a_bad_cache_is_one_line_error(tmp_path, case, needle):
    cache = tmp_path / "cache"
    cache.mkdir()
    if case == "corrupt":
        (cache / "scene_00000.npz").write_bytes(b"PK\x03\x04 not a zip at all")
    elif case == "incomplete":
        np.savez(cache / "scene_00000.npz", desc=np.zeros((4, 33)), offsets=np.array([0, 2, 4]))
    elif case == "inconsistent":
        np.savez(cache / "scene_00000.npz", desc=np.zeros((4, 33)), offsets=np.array([0, 2, 9]), overlap=np.eye(2))
    code, lines = _cli("train", cache, "--out", tmp_path / "runs", "--epochs", "1")
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], lines
    assert not (tmp_path / "runs").exists()


# --- sync ------------------------------------------------------------------------------------------------------------

_V = "VERTEX_SE3:QUAT {} 0 0 0 0 0 0 1\n"
_INFO = " ".join("1" if r == c else "0" for r in range(6) for c in range(r, 6))


def _edge(a, b, pose="1 0 0 0 0 0 1", info=_INFO) -> str:
    return f"EDGE_SE3:QUAT {a} {b} {pose} {info}\n"


SYNC_ERRORS = {
    "malformed number": (_V.format(0) + _V.format(1) + _edge(0, 1, "1 0 x 0 0 0 1"), "line 3: malformed number"),
    "not an SE3 line": (_V.format(0) + "EDGE_SE2 0 1 1 0 0 1 0 1 0 1\n", "line 2: not a VERTEX_SE3:QUAT"),
    "nan in a pose": (_V.format(0) + _V.format(1) + _edge(0, 1, "nan 0 0 0 0 0 1"), "line 3: pose is not finite"),
    "zero quaternion": (_V.format(0) + _V.format(1) + _edge(0, 1, "1 0 0 0 0 0 0"), "quaternion is zero"),
    "information not positive definite": (
        _V.format(0) + _V.format(1) + _edge(0, 1, info=_INFO.replace("1", "-1", 1)),
        "line 3: information matrix is not positive definite",
    ),
    "zero information": (_V.format(0) + _V.format(1) + _edge(0, 1, info=" ".join(["0"] * 21)), "not positive definite"),
    "information of 1e-300": (
        _V.format(0) + _V.format(1) + _edge(0, 1, info=_INFO.replace("1", "1e-300")),
        "line 3: information's eigenvalues 1e-300 to 1e-300 leave the range double precision",
    ),
    "self-loop": (_V.format(0) + _V.format(1) + _edge(1, 1), "line 3: edge 1-1 joins a vertex to itself"),
    "edge to an undefined vertex": (_V.format(0) + _edge(0, 5), "refers to a vertex that is not defined"),
    "duplicate vertex": (_V.format(0) + _V.format(0) + _edge(0, 0), "line 2: vertex 0 is defined a second time"),
    "empty file": ("", "no VERTEX_SE3:QUAT lines"),
}


@pytest.mark.parametrize("case", list(SYNC_ERRORS))
def test_bad_g2o_is_one_line_error_with_its_line(tmp_path, case):
    text, needle = SYNC_ERRORS[case]
    (tmp_path / "in.g2o").write_text(text)
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o")
    assert code == 2 and len(lines) == 1 and needle in lines[0], lines
    assert not (tmp_path / "out.g2o").exists() and [p.name for p in tmp_path.iterdir()] == ["in.g2o"]


def test_sync_out_a_folder_names_the_folder(tmp_path):
    (tmp_path / "in.g2o").write_text(_V.format(0) + _V.format(1) + _edge(0, 1))
    (tmp_path / "o").mkdir()
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "o")
    assert code == 2 and lines == [f"error: cannot write {tmp_path / 'o'}: it is a folder"]
    assert not any((tmp_path / "o").iterdir())


def test_sync_out_a_pipe_is_refused_and_a_link_followed(tmp_path):
    """A rename onto ``--out`` put a regular file in place of a pipe or a device (``/dev/null``, as root) and of a
    symbolic link: a pipe is refused, a link's file is replaced and the link stays."""
    (tmp_path / "in.g2o").write_text(_V.format(0) + _V.format(1) + _edge(0, 1))
    os.mkfifo(tmp_path / "out.fifo")
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.fifo")
    assert code == 2 and lines == [
        f"error: cannot write {tmp_path / 'out.fifo'}: it is not a regular file (a device, pipe or socket)"
    ], lines
    assert (tmp_path / "out.fifo").is_fifo()
    (tmp_path / "real.g2o").write_text("old\n")
    (tmp_path / "link.g2o").symlink_to("real.g2o")
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "link.g2o")
    assert code == 0, lines
    assert (tmp_path / "link.g2o").is_symlink() and read_g2o(tmp_path / "real.g2o")[0] == [0, 1]


def test_run_out_a_link_to_a_folder_fills_the_folder(small_room, tmp_path):
    """``--out`` a symbolic link to a folder: the folder gets the results (with the umask's permissions, not
    mkdtemp's 0700), the link stays, nothing is left beside them."""
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to("real")
    code, lines = _cli("run", small_room, "--out", tmp_path / "link", "--workers", "1", "--no-record", "--quiet")
    assert code == 0, lines
    assert (tmp_path / "link").is_symlink() and (tmp_path / "real" / "poses.txt").is_file()
    assert (tmp_path / "real").stat().st_mode & 0o777 == 0o777 & ~atomic._UMASK
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "real"]


def test_sync_odd_but_valid_graphs(tmp_path):
    """A 1e300 quaternion (a direction), a duplicate edge, two disconnected parts: synchronized, the truth kept."""
    big = "1 0 0 0 0 0 1e300"
    text = (
        _V.format(0)
        + _V.format(1)
        + _V.format(2)
        + _V.format(3)
        + _edge(0, 1, big)
        + _edge(0, 1)
        + _edge(2, 3, "0 2 0 0 0 0 1")
    )
    (tmp_path / "in.g2o").write_text(text)
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o")
    assert code == 0 and "2 connected part(s)" in lines[0], lines
    ids, poses, _ = read_g2o(tmp_path / "out.g2o")
    assert ids == [0, 1, 2, 3]
    np.testing.assert_allclose((inv_T(poses[0]) @ poses[1])[:3, 3], [1, 0, 0], atol=1e-6)
    np.testing.assert_allclose((inv_T(poses[2]) @ poses[3])[:3, 3], [0, 2, 0], atol=1e-6)


@pytest.mark.parametrize("method", ["history", "lm", "eigse3", "l1_irls", "rotavg", "gnc_tls", "shonan", "open3d"])
def test_sync_a_vertex_without_edges(tmp_path, method):
    """A vertex on no edge is a part of its own for every method (Shonan failed: "Attempting to at the key")."""
    (tmp_path / "in.g2o").write_text(
        _V.format(0)
        + _V.format(1)
        + _V.format(2)
        + _V.format(9)
        + _edge(0, 1)
        + _edge(1, 2, "0 1 0 0 0 0 1")
        + _edge(0, 2, "1 1 0 0 0 0 1")
    )
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--method", method)
    assert code == 0 and "2 connected part(s)" in lines[0], lines
    ids, poses, _ = read_g2o(tmp_path / "out.g2o")
    assert ids == [0, 1, 2, 9]
    np.testing.assert_allclose((inv_T(poses[0]) @ poses[2])[:3, 3], [1, 1, 0], atol=1e-6)


@pytest.mark.parametrize(
    "method, n, words",
    [
        (
            "eigse3",
            251,
            "eigse3 solves a dense eigenproblem of 4N x 4N: at most 250 poses in a connected part, got 251",
        ),
        (
            "open3d",
            100_000,
            "open3d's global optimization holds a dense system of 6N x 6N: 100,000 poses need about 5364.4 GB",
        ),
    ],
)
def test_sync_dense_baselines_refuse_graphs_too_large_for_them(tmp_path, method, n, words):
    """A chain of 2,000 poses kept eigse3 in LAPACK for minutes, deaf to SIGTERM; of 10,000 it asked for 24 GB
    ("unexpected MemoryError"), and open3d said only "std::bad_alloc"."""
    (tmp_path / "in.g2o").write_text(
        "".join(_V.format(k) for k in range(n)) + "".join(_edge(k, k + 1) for k in range(n - 1))
    )
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--method", method)
    assert code == 2 and len(lines) == 1 and words in lines[0], lines
    assert not (tmp_path / "out.g2o").exists()


@pytest.mark.parametrize("method", ["history", "lm", "gnc_tls", "shonan"])
def test_sync_keeps_the_input_frame_and_does_not_stack_parts(tmp_path, method):
    """Every part used to be written with its first vertex at the identity: two parts 100 m apart were stacked on one
    another (exit 0, nothing said), a vertex on no edge sat on vertex 0, and an input shifted by 10 m came back at
    the origin. Each part is now placed by its first vertex's input pose, and the parts apart are named."""
    shifted = "VERTEX_SE3:QUAT {} 10 0 0 0 0 0 1\n"
    far = "VERTEX_SE3:QUAT {} 100 5 0 0 0 0 1\n"
    (tmp_path / "in.g2o").write_text(
        shifted.format(0)
        + shifted.format(1)
        + shifted.format(2)
        + far.format(7)
        + far.format(8)
        + _edge(0, 1)
        + _edge(1, 2, "0 1 0 0 0 0 1")
        + _edge(0, 2, "1 1 0 0 0 0 1")
        + _edge(7, 8, "0 0 1 0 0 0 1")
    )
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--method", method)
    assert code == 0 and "2 connected part(s)" in lines[0], lines
    assert lines[1] == (
        "2 pose(s) outside the largest part, joined to it by no kept edge: each part is placed by "
        "its first vertex's input pose, not by the graph: 7 8"
    ), lines
    ids, poses, _ = read_g2o(tmp_path / "out.g2o")
    np.testing.assert_allclose(poses[[0, 3], :3, 3], [[10, 0, 0], [100, 5, 0]], atol=1e-9)
    np.testing.assert_allclose(poses[[2, 4], :3, 3], [[11, 1, 0], [100, 5, 1]], atol=1e-6)


def test_sync_holds_a_part_at_its_fix_vertex(tmp_path):
    """``FIX`` lines were skipped: the part was held at its first vertex, so the FIX vertex moved. A part now keeps
    its first FIX vertex at its input pose; a second FIX vertex in the same part is named as placed by the graph."""
    (tmp_path / "in.g2o").write_text(
        "FIX 2 1\n"
        + _V.format(0)
        + _V.format(1)
        + "VERTEX_SE3:QUAT 2 5 5 0 0 0 0 1\n"
        + _edge(0, 1)
        + _edge(1, 2, "0 1 0 0 0 0 1")
        + _edge(0, 2, "1 1 0 0 0 0 1")
    )
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o")
    assert code == 0 and lines[1:] == ["FIX vertices placed by the graph (a part is held at its first FIX vertex): 1"]
    _, poses, _ = read_g2o(tmp_path / "out.g2o")
    np.testing.assert_allclose(poses[:, :3, 3], [[4, 4, 0], [5, 4, 0], [5, 5, 0]], atol=1e-6)


def test_sync_names_every_method_and_refuses_absurd_translations(tmp_path):
    """``--method bogus`` listed five of the twelve methods; an edge translation of 1e200 printed numpy's overflow
    warnings and wrote poses of 1e199 (lm, l1_irls, rotavg, shonan, open3d)."""
    (tmp_path / "in.g2o").write_text(_V.format(0) + _V.format(1) + _edge(0, 1))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--method", "bogus")
    assert code == 2 and len(lines) == 1 and "gnc_tls" in lines[0] and "open3d_all_uncertain" in lines[0], lines
    (tmp_path / "in.g2o").write_text(
        _V.format(0)
        + _V.format(1)
        + _V.format(2)
        + _edge(0, 1, "1e200 0 0 0 0 0 1")
        + _edge(1, 2)
        + _edge(0, 2, "2 0 0 0 0 0 1")
    )
    for method in ("history", "lm"):
        code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--method", method)
        assert code == 2 and lines == [
            f"error: {tmp_path / 'in.g2o'}: line 4: translation 1e+200 beyond what double "
            "precision can square (1.3e+154)"
        ], lines
    assert not (tmp_path / "out.g2o").exists()


def test_scan_files_whose_names_are_not_utf8_are_skipped_and_shown_escaped(tmp_path):
    """File names of bytes that are not UTF-8 (Python keeps them as surrogates) passed, and the whole run was lost
    when poses.txt was written ("unexpected UnicodeEncodeError: … surrogates not allowed"). They are skipped like
    names with a line break, and every message shows such a name escaped, on one line."""
    scene = tmp_path / "scene"
    write_scene(make_scene(kind="room", n_scans=4, seed=1), scene)
    (scene / "scan_00.ply").rename(scene / os.fsdecode(b"caf\xe9.ply"))
    (scene / "scan_01.ply").rename(scene / "a\nb.ply")
    (scene / os.fsdecode(b"gt_pose\xe9s.txt")).write_text("not a scan")
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "sghr_gtsam",
            "run",
            str(scene),
            "--out",
            str(tmp_path / "out"),
            "--workers",
            "1",
            "--no-record",
        ],
        capture_output=True,
        text=True,
        errors="strict",
    )
    assert done.returncode == 0, done.stderr
    assert re.search(r"skipped files +2: 'a\\nb\.ply', 'caf\\udce9\.ply'", done.stdout), done.stdout
    assert "not a scan, by its name: 'gt_pose\\udce9s.txt'" in done.stdout + done.stderr
    assert (tmp_path / "out" / "poses.txt").read_text().count(".ply") == 2
    (scene / "scan_02.ply").rename(scene / os.fsdecode(b"scan_\xff.ply"))
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "sghr_gtsam",
            "run",
            str(scene),
            "--out",
            str(tmp_path / "out"),
            "--workers",
            "1",
            "--no-record",
        ],
        capture_output=True,
        text=True,
        errors="strict",
    )
    assert done.returncode == 2 and done.stderr.count("\n") == 1, done.stderr
    assert (
        "need at least 2 usable scans, 1 left; skipped 'a\\nb.ply': its name 'a\\nb.ply' cannot be written on "
        "its own line in the pose files: rename it (and 2 more)" in done.stderr
    ), done.stderr


@pytest.mark.parametrize("method", ["history", "lm", "shonan", "gnc_tls"])
def test_sync_information_beyond_double_precision_is_refused_by_every_method(tmp_path, method):
    """Information of 1e-300 on every edge of a loop: Shonan failed ("TridiagEigen: eigen decomposition failed"),
    the other methods wrote a graph; every method refuses it, naming the edge's line."""
    tiny = _INFO.replace("1", "1e-300")
    (tmp_path / "in.g2o").write_text(
        _V.format(0)
        + _V.format(1)
        + _V.format(2)
        + _edge(0, 1, info=tiny)
        + _edge(1, 2, "0 1 0 0 0 0 1", tiny)
        + _edge(0, 2, "1 1 0 0 0 0 1", tiny)
    )
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--method", method)
    assert code == 2 and len(lines) == 1 and "in.g2o: line 4: information's eigenvalues" in lines[0], lines
    assert not (tmp_path / "out.g2o").exists()


def test_sync_shonan_on_precisions_far_apart_says_so_in_one_line(tmp_path):
    """A 5-scan loop and one edge of 1e140 × its information: gtsam's Shonan eigensolver fails ("unexpected
    RuntimeError: TridiagEigen: …" before); the line names the method and the precisions' range."""
    ring = "1 0 0 0 0 0.309017 0.9510565"  # 36° about z a step
    (tmp_path / "in.g2o").write_text(
        "".join(_V.format(k) for k in range(5))
        + "".join(_edge(k, (k + 1) % 5, ring) for k in range(5))
        + _edge(0, 2, "0 1 0 0.7071068 0 0 0.7071068", _INFO.replace("1", "1e140"))
    )
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o", "--method", "shonan")
    assert code == 2 and lines == [
        "error: Shonan averaging failed (TridiagEigen: eigen decomposition failed) on "
        "rotation precisions from 1 to 1e+140: try another method"
    ], lines
    assert not (tmp_path / "out.g2o").exists()


def test_sync_single_vertex_graph(tmp_path):
    (tmp_path / "in.g2o").write_text(_V.format(7))
    code, lines = _cli("sync", tmp_path / "in.g2o", "--out", tmp_path / "out.g2o")
    assert code == 2 and len(lines) == 1 and lines[0].startswith("error: "), lines
    assert not (tmp_path / "out.g2o").exists()


# --- fuzzing the readers: an InputError or the right array, never anything else ------------------------------------

_FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
_coords = st.floats(-1e6, 1e6, allow_nan=False, width=32)


def _load(path: Path) -> np.ndarray | None:
    """``load_scan`` must either raise ``InputError`` or return a finite-shaped (N, 3) float64 array."""
    try:
        P = load_scan(path)
    except InputError as e:
        assert "\n" not in str(e)
        return None
    assert P.ndim == 2 and P.shape[1] == 3 and P.dtype == np.float64 and len(P) >= 1
    return P


@_FUZZ
@given(
    st.lists(st.tuples(_coords, _coords, _coords), min_size=1, max_size=30),
    st.sampled_from(["ascii", "binary"]),
    st.data(),
)
def test_fuzzed_ply_is_read_exactly_or_refused(rows, fmt, data):
    """A valid PLY comes back exactly; the same file with one byte changed, truncated or with its vertex count
    altered is refused or read as exactly the values its bytes hold (no padding, no uninitialised memory)."""
    P = np.array(rows, dtype=np.float32).astype(np.float64)
    blob = _ascii_ply(P).encode() if fmt == "ascii" else _binary_ply(P)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "f.ply"
        path.write_bytes(blob)
        np.testing.assert_array_equal(_load(path), P)
        mutation = data.draw(st.sampled_from(["byte", "cut", "count"]))
        if mutation == "byte":
            at = data.draw(st.integers(0, len(blob) - 1))
            blob = blob[:at] + bytes([data.draw(st.integers(0, 255))]) + blob[at + 1 :]
        elif mutation == "cut":
            blob = blob[: data.draw(st.integers(0, len(blob) - 1))]
        else:
            blob = blob.replace(f"vertex {len(P)}".encode(), f"vertex {data.draw(st.integers(0, 40))}".encode(), 1)
        path.write_bytes(blob)
        Q = _load(path)
    if Q is not None and mutation == "count":  # a changed count is refused unless it changed nothing
        np.testing.assert_array_equal(Q, P)
    if Q is not None and mutation == "cut":  # ... and a cut too, but inside an ASCII file's last number (undetectable)
        np.testing.assert_array_equal(Q[:-1], P[:-1])
        assert len(Q) == len(P) and fmt == "ascii" or np.array_equal(Q, P)
    if Q is not None and mutation == "byte":
        assert len(Q) == len(P)  # the header's count is the count read, whichever byte changed


@_FUZZ
@given(st.binary(max_size=400), st.sampled_from([".ply", ".pcd"]))
def test_fuzzed_bytes_never_escape_as_another_error(blob, suffix):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"f{suffix}"
        for prefix in (b"", b"ply\nformat ascii 1.0\n", b"VERSION .7\nFIELDS x y z\n"):
            path.write_bytes(prefix + blob)
            _load(path)


@_FUZZ
@given(st.lists(st.tuples(_coords, _coords, _coords), min_size=1, max_size=30), st.data())
def test_fuzzed_pcd_is_read_exactly_or_refused(rows, data):
    P = np.array(rows, dtype=np.float32).astype(np.float64)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "f.pcd"
        write_scan(path, P)  # binary float32
        np.testing.assert_array_equal(_load(path), P)
        blob = path.read_bytes()
        cut = data.draw(st.integers(0, len(blob) - 1))
        path.write_bytes(blob[:cut])
        assert _load(path) is None
        n = data.draw(st.integers(0, 40).filter(lambda n: n != len(P)))
        path.write_bytes(blob.replace(f"POINTS {len(P)}".encode(), f"POINTS {n}".encode(), 1))
        assert _load(path) is None


@_FUZZ
@given(st.lists(st.text(st.sampled_from(list("0123456789 .-eE+naifVERTEX_SE3:QUAT\n#")), max_size=80), max_size=8))
def test_fuzzed_g2o_is_read_or_refused_with_a_line(lines):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "f.g2o"
        path.write_text(_V.format(0) + "".join(lines) + "\n" + _V.format(1) + _edge(0, 1))
        try:
            ids, poses, graph = read_g2o(path, positive_definite=True)
        except InputError as e:
            assert "\n" not in str(e) and ("line" in str(e) or "vertex" in str(e)), str(e)
            return
    assert ids[0] == 0 and np.isfinite(poses).all() and np.isfinite(graph.T).all()
    assert (np.linalg.eigvalsh(graph.information) > 0).all()


def test_g2o_written_and_read_back_keeps_a_large_quaternion_exactly(tmp_path):
    graph = PoseGraph(
        n=2,
        i=np.array([0]),
        j=np.array([1]),
        T=make_T(np.eye(3), np.ones(3))[None],
        weight=np.ones(1),
        information=np.eye(6)[None],
    )
    write_g2o(tmp_path / "g.g2o", [0, 1], np.tile(np.eye(4), (2, 1, 1)), graph)
    text = (tmp_path / "g.g2o").read_text().replace(" 0.0 0.0 0.0 1.0\n", " 0.0 0.0 0.0 1e300\n", 1)
    (tmp_path / "g.g2o").write_text(text)
    _, poses, back = read_g2o(tmp_path / "g.g2o")
    np.testing.assert_array_equal(poses, np.tile(np.eye(4), (2, 1, 1)))
