"""The hostile-input corpus of tests/test_corpus.py as a table: each case run through the command line as the test
runs it, with the exit code, the one line the user gets and what is left in the output folder.

    python benchmarks/bench_corpus.py > corpus.md

The cases that must register (a scene mixing good and bad scans, georeferenced offsets, signals mid-run) take
minutes and are not repeated here: their outcomes are the tests' assertions (docs/BENCHMARKS.md).
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import test_corpus as corpus  # noqa: E402  (the cases are defined once, in the test)


def _state(out: Path) -> str:
    if not out.exists():
        return "absent"
    if out.is_dir() and out.name == "out" and {p.name for p in out.iterdir()} == set(corpus.OLD):
        same = all((out / n).read_text() == t for n, t in corpus.OLD.items())
        return "earlier result untouched" if same else "earlier result CHANGED"
    return "present"


def _row(case: str, code: int, lines: list[str], state: str, folder: str) -> str:
    line = (lines[-1] if lines else "").replace(folder, "…").replace("|", "\\|")
    return f"| {case} | {line[:160]} | {code} | {state} |"


def main() -> None:
    print("| case | one line on stderr (paths shortened) | exit | output folder |")
    print("|---|---|---|---|")
    for case, (name, content, _) in corpus.BAD_FILES.items():
        with tempfile.TemporaryDirectory() as d:
            scene, out = Path(d) / "scene", Path(d) / "out"
            scene.mkdir()
            np.save(scene / "good.npy", corpus._good_scan(0))
            corpus._write_bad(scene / name, content)
            corpus._old_result(out)
            code, lines = corpus._cli("run", scene, "--out", out, "--workers", "1")
            print(_row(f"scan: {case}", code, lines, _state(out), d))
    for case, (args, _) in corpus.BAD_RUNS.items():
        with tempfile.TemporaryDirectory() as d:
            t = Path(d)
            scene, out = corpus._scene_with_scan(t), t / "out"
            args = args(t, scene, out) if callable(args) else [scene, "--out", out, *args]
            extra = [] if "--workers" in args else ["--workers", "1"]
            code, lines = corpus._cli("run", *args, *extra)
            print(
                _row(
                    f"run: {case}",
                    code,
                    lines,
                    "no report.json written" if not (out / "report.json").exists() else "report.json written",
                    d,
                )
            )
    for case, (text, _) in corpus.SYNC_ERRORS.items():
        with tempfile.TemporaryDirectory() as d:
            (Path(d) / "in.g2o").write_text(text)
            code, lines = corpus._cli("sync", Path(d) / "in.g2o", "--out", Path(d) / "out.g2o")
            print(_row(f"sync: {case}", code, lines, "out.g2o " + _state(Path(d) / "out.g2o"), d))


if __name__ == "__main__":
    main()
