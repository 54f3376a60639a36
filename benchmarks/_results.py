"""One JSON file a benchmark table, in ``benchmarks/results/``: the rows, the command that made them, the commit and
the machine. ``python -m benchmarks.report`` turns the folder into docs/benchmarks.md.

A file holds: ``name``, ``section`` and ``title`` (where the table goes on the page), ``columns``, ``rows`` (one list
of cells a row, in the columns' order), ``command``, ``commit`` (short hash, ``+dirty`` when the tracked files had
changes), ``date`` (UTC), ``machine`` (CPUs, memory, load average at the end of the run, OS, Python), ``notes``
(a few lines shown under the table) and ``transcribed`` (true when the rows were copied from an older document
rather than written by the run itself).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def commit(root: Path = ROOT) -> str:
    """The short hash of HEAD, ``+dirty`` when tracked files other than results differ from it; ``unknown`` outside a
    git checkout."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            [
                "git",
                "status",
                "--porcelain",
                "--untracked-files=no",
                "--",
                ".",
                ":!benchmarks/results",
                ":!docs/benchmarks.md",
            ],  # results are not code
            cwd=root,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("+dirty" if dirty else "")


STARTED_AT = commit()
"""The commit when the benchmark started (it imports this module first): the code that ran, whatever is committed
before it ends."""


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory_gb() -> float | None:
    try:
        return round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):
        return None


def machine() -> dict[str, Any]:
    """What made the timings: CPU model and count, memory, load average (other jobs share the cores), OS, Python."""
    try:
        load = round(os.getloadavg()[0], 1)
    except OSError:
        load = None
    return {
        "cpu": _cpu_model(),
        "cores": os.cpu_count(),
        "memory_gb": _memory_gb(),
        "load": load,
        "os": f"{platform.system()} {platform.release()}",
        "python": platform.python_version(),
    }


def save(
    name: str,
    rows: Sequence[Sequence[Any]],
    columns: Sequence[str],
    command: str | None = None,
    notes: str = "",
    *,
    section: str = "Other",
    title: str | None = None,
    folder: Path = RESULTS,
) -> Path:
    """Write ``folder/<name>.json`` (atomically) and return its path. ``command`` defaults to this process's own
    command line; cells are JSON values (numbers, strings, None) in the order of ``columns``."""
    if any(len(row) != len(columns) for row in rows):
        raise ValueError(f"{name}: every row needs {len(columns)} cells ({', '.join(columns)})")
    record = {
        "name": name,
        "section": section,
        "title": title or name,
        "columns": list(columns),
        "rows": [list(row) for row in rows],
        "command": command or "python " + " ".join([_relative(sys.argv[0]), *sys.argv[1:]]),
        "commit": STARTED_AT,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d"),
        "machine": machine(),
        "notes": notes,
        "transcribed": False,
    }
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.json"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(json.dumps(record, indent=1, ensure_ascii=False) + "\n")
    os.replace(tmp, path)
    return path


def _relative(script: str) -> str:
    try:
        return str(Path(script).resolve().relative_to(ROOT))
    except ValueError:
        return script
