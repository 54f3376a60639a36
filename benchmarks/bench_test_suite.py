"""The test suite on this machine: the README's test command, its result, wall time and CPU time.

    python benchmarks/bench_test_suite.py

Runs ``python -m pytest -q`` (two processes, a test file each: pyproject.toml's addopts) from the repository root
as CI does, and reads the result from pytest's last line. CPU time is that of every process the command started
(user + sys of the finished children). The real-data tests need ``../shared/data`` and are skipped without it.
"""

from __future__ import annotations

import re
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks._results import save  # noqa: E402

COMMAND = [sys.executable, "-m", "pytest", "-q"]


def main() -> int:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run(COMMAND, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    last = done.stdout.strip().splitlines()[-1] if done.stdout.strip() else "no output"
    result = re.sub(r"\s+in [\d.]+s.*$", "", last.strip("= "))  # the counts, without pytest's own timing
    print(f"{result}: {wall:.0f} s wall, {cpu:.0f} s CPU")
    save(
        "test_suite",
        [["`python -m pytest -q`", result, round(wall), round(cpu)]],
        ["command", "result", "wall s", "CPU s (user + sys)"],
        notes="Two processes, a test file each (pyproject.toml); CI runs the same command on a clean clone.",
        section="Scale and speed",
        title="The test suite on a 2-core machine",
    )
    return done.returncode


if __name__ == "__main__":
    sys.exit(main())
