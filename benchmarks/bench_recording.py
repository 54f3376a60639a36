"""What the Rerun recording costs: the recorder calls of one run, replayed into this Recorder and a former one.

    python benchmarks/bench_recording.py SCENE_DIR [SCENE_DIR ...] [--baseline COMMIT] [--repeat 3]

Each scene runs once through ``pipeline.register`` (``workers=1``) with a stand-in recorder that keeps every
call and its arguments; the calls are then replayed into ``sghr_gtsam.recording.Recorder`` and, with
``--baseline``, into the ``Recorder`` of that commit (calls it does not have are skipped; ``log_final``'s
flags are passed as it takes them), each in a fresh process. Reported: process CPU (every thread, rerun's
encoder included) and wall time from the Recorder's creation to its ``close``, medians over ``--repeat``
replays, and the .rrd size; a row a scene, written for the benchmarks page.
"""

from __future__ import annotations

import argparse
import copy
import inspect
import json
import os
import pickle
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks._results import save  # noqa: E402


class _Trace:
    def __init__(self) -> None:
        self.calls: list[tuple[str, tuple]] = []

    def __getattr__(self, name: str):
        def call(*args) -> None:
            if name == "log_scans":  # the points are read from the run's store, removed once the run ends
                args = (args[0], [P.copy() for P in args[1]])
            self.calls.append((name, copy.deepcopy(args)))

        return call


def _capture(scene: str, path: Path) -> tuple[int, list[int]]:
    from sghr_gtsam.config import Config
    from sghr_gtsam.pipeline import load_scene, register

    config = Config(workers=1, record=False)
    scans, skipped = load_scene(scene, config, log=lambda m: None)
    trace = _Trace()
    register(scans, config, recorder=trace, log=lambda m: None, skipped=skipped)
    path.write_bytes(pickle.dumps(trace.calls))
    edges = [args[0].num_edges for name, args in trace.calls if name == "log_graph"]
    return len(scans), list(dict.fromkeys(edges))  # each graph size once, in the order synchronized


def _replay(module_dir: str, trace: str, out: str) -> None:
    """In a fresh process: replay ``trace`` into the Recorder found first on ``module_dir``; print JSON."""
    sys.path.insert(0, module_dir)
    import rerun  # noqa: F401  (imports outside the timing)
    from recording import Recorder  # the module under test, copied beside its package

    calls = pickle.loads(Path(trace).read_bytes())
    final_params = list(inspect.signature(Recorder.log_final).parameters)[2:]

    def cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    wall, c0 = time.perf_counter(), cpu()
    recorder = Recorder(out)
    for name, args in calls:
        if not hasattr(recorder, name):
            continue
        if name == "log_final" and final_params != ["flags"]:
            poses, flags = args
            args = (poses, *[flags.get(p, []) for p in final_params])
        getattr(recorder, name)(*args)
    recorder.close()
    print(
        json.dumps(
            {
                "cpu": cpu() - c0,
                "wall": time.perf_counter() - wall,
                "records": sum(name == "on_iteration" for name, _ in calls),
                "mb": os.path.getsize(out) / 1e6,
            }
        )
    )


def _module_dir(commit: str | None, tmp: Path) -> str:
    """A folder holding ``recording.py`` (of ``commit``, else of this tree) importing the installed package."""
    source = (
        subprocess.run(
            ["git", "show", f"{commit}:sghr_gtsam/recording.py"], cwd=ROOT, check=True, capture_output=True, text=True
        ).stdout
        if commit
        else (ROOT / "sghr_gtsam" / "recording.py").read_text()
    )
    folder = tmp / (commit or "current")
    folder.mkdir()
    (folder / "recording.py").write_text(source.replace("from .", "from sghr_gtsam."))
    return str(folder)


COLUMNS = [
    "scene",
    "scans",
    "edges",
    "records",
    "CPU new",
    "CPU before",
    "wall new",
    "wall before",
    ".rrd new",
    ".rrd before",
]


def _replays(scene: str, folder: str, tmp: Path, repeat: int) -> dict:
    """Medians of ``repeat`` replays of the captured trace into the Recorder in ``folder``, each in a fresh process."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OPENBLAS_NUM_THREADS": "1"}
    runs = [
        json.loads(
            subprocess.run(
                [sys.executable, __file__, scene, "--replay", folder, str(tmp / "trace.pkl"), str(tmp / "r.rrd")],
                env=env,
                check=True,
                capture_output=True,
                text=True,
            ).stdout.splitlines()[-1]
        )
        for _ in range(repeat)
    ]
    return {
        "cpu": statistics.median(r["cpu"] for r in runs),
        "wall": statistics.median(r["wall"] for r in runs),
        "records": runs[0]["records"],
        "mb": runs[0]["mb"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--baseline", help="commit whose Recorder to compare with")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--replay", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.replay:
        return _replay(*args.replay)
    rows, shares = [], []  # shares: the recorder's wall time over its scene's run, a phrase a scene
    for scene in args.scenes:
        with tempfile.TemporaryDirectory() as tmp_name:
            tmp = Path(tmp_name)
            t0 = time.perf_counter()
            n, edges = _capture(scene, tmp / "trace.pkl")
            run = time.perf_counter() - t0
            print(f"{scene}: {n} scans, run {run:.1f} s")
            new = _replays(scene, _module_dir(None, tmp), tmp, args.repeat)
            old = _replays(scene, _module_dir(args.baseline, tmp), tmp, args.repeat) if args.baseline else None
        shares.append(f"{100 * new['wall'] / run:.1f} % of {Path(scene).name}'s run ({run:.1f} s)")
        per_record = f"{new['cpu']:.2f} s ({1000 * new['cpu'] / new['records']:.1f} ms a record)"
        rows.append(
            [
                Path(scene).name,
                n,
                ", then ".join(map(str, edges)),
                new["records"],
                per_record,
                "-" if old is None else f"{old['cpu']:.2f} s ({1000 * old['cpu'] / old['records']:.1f} ms)",
                f"{new['wall']:.2f} s",
                "-" if old is None else f"{old['wall']:.2f} s",
                f"{new['mb']:.1f} MB",
                "-" if old is None else f"{old['mb']:.1f} MB",
            ]
        )
        print(" | ".join(map(str, rows[-1])), flush=True)
    save(
        "recording",
        rows,
        COLUMNS,
        notes=f"The recorder's own wall time, replayed: {', '.join(shares)}; each run in one process.",
        section="Scale and speed",
        title="What the Rerun recording costs",
    )


if __name__ == "__main__":
    main()
