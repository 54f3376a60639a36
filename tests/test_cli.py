"""The command line on good and bad input: one line and a non-zero exit, never a traceback."""

import os
import subprocess
import sys

import numpy as np
import pytest
from typer.testing import CliRunner

from sghr_gtsam.cli import app
from sghr_gtsam.synthetic import make_scene, write_scene

runner = CliRunner()


def _run(*args):
    result = runner.invoke(app, [str(a) for a in args])
    assert "Traceback" not in result.output
    return result


def test_empty_folder_is_one_line_error(tmp_path):
    (tmp_path / "scene").mkdir()
    r = _run("run", tmp_path / "scene", "--out", tmp_path / "out")
    assert r.exit_code == 2
    assert r.output.strip().startswith("error:") and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "out" / "report.json").exists()


def test_missing_folder_is_one_line_error(tmp_path):
    r = _run("run", tmp_path / "nowhere", "--out", tmp_path / "out")
    assert r.exit_code == 2 and "error:" in r.output


def test_single_scan_is_an_error(tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    np.save(scene / "a.npy", np.random.default_rng(0).random((500, 3)))
    r = _run("run", scene, "--out", tmp_path / "out")
    assert r.exit_code == 2 and "at least 2" in r.output


def test_bad_scans_are_skipped_and_reported(tmp_path):
    """A corrupt file, a NaN-only scan and a tiny scan are skipped; the rest is registered."""
    scene = make_scene(kind="room", n_scans=3, seed=1)
    d = tmp_path / "scene"
    write_scene(scene, d)
    (d / "zz_corrupt.ply").write_text("ply\nformat binary_little_endian 1.0\nelement vertex 1000\n")
    np.save(d / "zz_nan.npy", np.full((500, 3), np.nan))
    np.save(d / "zz_tiny.npy", np.random.default_rng(0).random((20, 3)))
    out = tmp_path / "out"
    r = _run("run", d, "--out", out, "--no-record")
    assert r.exit_code == 0, r.output
    import json

    report = json.loads((out / "report.json").read_text())
    assert set(report["skipped"]) == {"zz_corrupt.ply", "zz_nan.npy", "zz_tiny.npy"}
    assert len(report["registered"]) == 3


def test_module_entry_point_prints_no_traceback(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "sghr_gtsam", "run", str(tmp_path / "none")], capture_output=True, text=True
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error:") and "Traceback" not in proc.stderr


def test_sync_command_reaches_the_published_optimum(data_dir, tmp_path):
    """`sync --noise isotropic` on parking-garage: SE-Sync objective at f* = 1.263 (4 digits published)."""
    from sghr_gtsam.io.g2o import read_g2o, sesync_objective

    out = tmp_path / "pg.g2o"
    r = _run("sync", data_dir / "posegraph" / "parking-garage.g2o", "--out", out, "--noise", "isotropic")
    assert r.exit_code == 0, r.output
    ids, poses, graph = read_g2o(out)
    _, _, original = read_g2o(data_dir / "posegraph" / "parking-garage.g2o")
    assert len(ids) == 1661 and graph.num_edges == 6275
    np.testing.assert_allclose(graph.T, original.T, atol=1e-6)
    f = sesync_objective(poses, original)
    assert abs(f - 1.263) <= 0.0005 + 1e-4 * 1.263


def test_sync_command_rejects_a_bad_file(tmp_path):
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 oops\n")
    r = _run("sync", bad, "--out", tmp_path / "o.g2o")
    assert r.exit_code == 2 and "error:" in r.output
    assert not (tmp_path / "o.g2o").exists()


def test_bad_options_and_config_files_are_one_line_errors(tmp_path):
    scene = tmp_path / "scene"
    write_scene(make_scene(kind="room", n_scans=3, seed=0), scene)
    bad_json = tmp_path / "bad.json"
    bad_json.write_text("{not json")
    unknown = tmp_path / "unknown.json"
    unknown.write_text('{"k": 4, "colour": "red"}')
    for args in (
        ["--polish", "sometimes"],
        ["--method", "magic"],
        ["--k", "0"],
        ["--max-sigma", "-1"],
        ["--config", bad_json],
        ["--config", unknown],
        ["--config", tmp_path / "missing.json"],
    ):
        r = _run("run", scene, "--out", tmp_path / "out", *args)
        assert r.exit_code == 2, args
        assert r.output.strip().startswith("error:") and len(r.output.strip().splitlines()) == 1, args
    assert not (tmp_path / "out").exists()


def test_config_file_values_hold_unless_an_option_overrides_them(tmp_path):
    from sghr_gtsam.cli import _config

    path = tmp_path / "config.json"
    path.write_text('{"k": 4, "polish": "lm", "record": false}')
    cfg = _config(path, k=None, polish=None, record=None, iters=7, max_sigma=0.1)
    assert (cfg.k, cfg.polish, cfg.record, cfg.iters, cfg.max_sigma) == (4, "lm", False, 7, 0.1)
    assert _config(path, k=6).k == 6


def test_sync_command_runs_every_method_and_baseline(tmp_path):
    """`sync --method X` for the project's methods and every baseline: a noise-free g2o graph comes back
    exact (same vertex ids, poses equal to the truth up to the gauge)."""
    from scipy.spatial.transform import Rotation

    from sghr_gtsam.cli import _BASELINE_NAMES, _METHOD_NAMES
    from sghr_gtsam.io.g2o import read_g2o, write_g2o
    from sghr_gtsam.se3 import inv_T, make_T, relative_errors
    from sghr_gtsam.types import PoseGraph

    rng = np.random.default_rng(4)
    n = 12
    truth = make_T(Rotation.random(n, random_state=rng).as_matrix(), rng.uniform(-3, 3, (n, 3)))
    i, j = np.array([(a, b) for a in range(n) for b in range(a + 1, n) if b - a <= 3]).T
    graph = PoseGraph(
        n=n,
        i=i,
        j=j,
        T=inv_T(truth[i]) @ truth[j],
        weight=np.ones(len(i)),
        information=np.tile(np.diag([400.0] * 3 + [100.0] * 3), (len(i), 1, 1)),
    )
    ids = list(range(100, 100 + n))
    write_g2o(tmp_path / "in.g2o", ids, np.tile(np.eye(4), (n, 1, 1)), graph)
    for method in _METHOD_NAMES + _BASELINE_NAMES:
        out = tmp_path / f"{method}.g2o"
        r = _run("sync", tmp_path / "in.g2o", "--out", out, "--method", method)
        assert r.exit_code == 0, (method, r.output)
        got_ids, poses, _ = read_g2o(out)
        assert got_ids == ids
        rot, trans = relative_errors(inv_T(poses[0]) @ poses, inv_T(truth[0]) @ truth)
        assert rot.max() < 1e-3 and trans.max() < 1e-4, method
        assert "unverified" not in r.output, method  # every edge of this band graph lies on a loop

    # Without the edges that close loops the graph is a chain: every pose but the first rests on one edge.
    chain = j - i == 1
    write_g2o(
        tmp_path / "chain.g2o",
        ids,
        np.tile(np.eye(4), (n, 1, 1)),
        PoseGraph(
            n=n, i=i[chain], j=j[chain], T=graph.T[chain], weight=np.ones(n - 1), information=graph.information[chain]
        ),
    )
    r = _run("sync", tmp_path / "chain.g2o", "--out", tmp_path / "chain_out.g2o")
    assert r.exit_code == 0 and f"{n - 1} pose(s) of the largest part unverified" in r.output, r.output


def test_the_console_script_is_the_module_entry():
    """``sghr-gtsam`` and ``python -m sghr_gtsam`` share one entry, which turns a stop while the command line
    loads into the same one line as later (``tests/test_corpus.py``, signals)."""
    from importlib.metadata import entry_points

    from sghr_gtsam.__main__ import main

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "sghr-gtsam"]
    assert script.load() is main
    done = subprocess.run([sys.executable, "-m", "sghr_gtsam", "sync", "--help"], capture_output=True, text=True)
    assert done.returncode == 0 and "python -m sghr_gtsam sync" in done.stdout


def test_a_console_that_cannot_print_unicode_gets_question_marks(tmp_path):
    """The summary's °, – and × in a latin-1 console ended a complete run with a UnicodeEncodeError traceback."""
    scene = tmp_path / "scene"
    write_scene(make_scene(kind="room", n_scans=3, seed=1), scene)
    env = {**os.environ, "PYTHONIOENCODING": "latin-1"}
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
        env=env,
        errors="replace",
    )
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert "worst residual" in done.stdout


def test_a_stop_after_the_results_are_in_says_so(tmp_path, capsys):
    """A stop that lands after the swap (while the summary prints) said "nothing written" of complete results."""
    import signal
    import time

    import typer

    from sghr_gtsam.cli import _guarded, _Stopped

    started = time.time()
    out = tmp_path / "out"
    with pytest.raises(typer.Exit) as stop:
        with _guarded(out, started):
            raise _Stopped(signal.SIGTERM)
    assert stop.value.exit_code == 143 and "nothing written" in capsys.readouterr().err
    out.mkdir()
    (out / "report.json").write_text("{}")
    with pytest.raises(typer.Exit) as stop:
        with _guarded(out, started):
            raise _Stopped(signal.SIGTERM)
    assert capsys.readouterr().err.strip() == (
        f"error: stopped by SIGTERM after the results were written: {out} is complete"
    )


def test_a_full_disk_is_named_not_unexpected(tmp_path, capsys):
    """A full disk ended in "unexpected OSError: [Errno 28] No space left on device", naming no folder."""
    import errno

    import typer

    from sghr_gtsam.cli import _guarded

    with pytest.raises(typer.Exit) as stop:
        with _guarded(tmp_path / "out"):
            raise OSError(errno.ENOSPC, "No space left on device")
    assert stop.value.exit_code == 1
    assert capsys.readouterr().err.strip() == f"error: cannot write {tmp_path / 'out'}: No space left on device"


_RECORD_SCRIPT = """
import errno, resource, signal, sys
import numpy as np
from sghr_gtsam.recording import Recorder
if sys.argv[2] != "0":  # a file limit: EFBIG once rerun's writer is past it, mid-recording
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
try:
    recorder = Recorder(sys.argv[1])
    recorder.log_scans(["a.ply", "b.ply"], [np.random.default_rng(k).random((20000, 3)) for k in range(2)])
    recorder.close()
except OSError as e:
    print("OSError", errno.errorcode[e.errno])
"""


@pytest.mark.parametrize("path, limit, code", [("/dev/full", 0, "ENOSPC"), ("rec.rrd", 65536, "EFBIG")])
def test_a_recording_that_cannot_be_written_raises_its_oserror(tmp_path, path, limit, code):
    """Rerun's file writer kept the OS's error to its log on stderr and raised a RuntimeError ("Failed to encode
    LogMsg", "File-writer thread shut down prematurely", which the command line called unexpected) or hung in
    ``flush`` for ever; the recording is written through a pipe now, and ``close`` raises the write's OSError."""
    if not os.path.exists(path) and path.startswith("/dev"):
        pytest.skip(f"no {path}")
    done = subprocess.run(
        [sys.executable, "-c", _RECORD_SCRIPT, str(tmp_path / path), str(limit)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.stdout.split() == ["OSError", code] and done.stderr == "", (done.stdout, done.stderr[-2000:])


def test_merged_ply_cut_short_by_the_disk_is_an_error_not_an_output(tmp_path, capfd):
    """open3d wrote merged.ply through RPly, which printed a line per failed row on a full disk and returned
    success with the file cut short: the results were written with a truncated merged.ply. Under a file-size
    limit (EFBIG, as ENOSPC without a full disk) the write raises and leaves no merged.ply."""
    import resource
    import signal

    from sghr_gtsam.config import Config
    from sghr_gtsam.io.results import write_results
    from sghr_gtsam.merged import merged_cloud
    from sghr_gtsam.pipeline import Scan, register

    scene = make_scene(kind="room", n_scans=3, seed=1)
    config = Config(workers=1, record=False, cache=False)
    result = register([Scan(n, P) for n, P in zip(scene.names, scene.scans)], config, log=lambda m: None)
    merged = merged_cloud(result)
    assert 24 * len(merged) > 100_000  # larger than the limit, while every other output is smaller
    capfd.readouterr()
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    limits = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (100_000, limits[1]))
    try:
        with pytest.raises(OSError):
            write_results(tmp_path, result, config, 0.0, merged)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limits)
        signal.signal(signal.SIGXFSZ, previous)
    assert not (tmp_path / "merged.ply").exists() and "RPly" not in capfd.readouterr().err
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary left
