"""docs/benchmarks.md from the JSON files the benchmarks write (``benchmarks/_results.py``):

    python -m benchmarks.report [--results benchmarks/results] [--out docs/benchmarks.md]

Tables go by section (the order of ``SECTIONS``, then any other), each with its command, commit, date and machine;
``not_kept.json`` (a list of ``{"what", "commit"}``) becomes the closing list of what was measured and not kept.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from benchmarks._results import RESULTS, ROOT

SECTIONS = [
    "3DMatch end to end",
    "Objects",
    "Synchronization",
    "Pose graphs",
    "Covariances",
    "Scale and speed",
    "Other",
]
NOT_KEPT = "not_kept.json"
HEADER = """# Benchmarks

Current results, one table a benchmark. Made by `python -m benchmarks.report` from `benchmarks/results/*.json`,
which each benchmark in `benchmarks/` writes (`benchmarks/_results.py`); do not edit by hand. Rows marked
*transcribed* were copied from the journal this page replaced (git keeps it: `git log -- docs/BENCHMARKS.md`) at
the commit they were measured at, not re-run since. Timings on a shared machine read up to 2–3× a quiet one's.
"""


def _cell(value: Any) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value).replace("|", "\\|").replace("\n", " ")


def _machine(m: dict) -> str:
    memory = f", {m['memory_gb']:g} GB" if m.get("memory_gb") else ""
    load = f", load {m['load']:g}" if m.get("load") is not None else ""
    return f"{m.get('cores', '?')} cores ({m.get('cpu', '?')}){memory}{load}"


def table(record: dict) -> list[str]:
    """One result as markdown: its title, provenance, the table and its notes."""
    origin = "transcribed from the journal, measured" if record.get("transcribed") else "measured"
    lines = [
        f"### {record['title']}",
        "",
        f"`{record['command']}`",
        "",
        f"{origin} at {record['commit']} on {record.get('date', '?')}; {_machine(record.get('machine', {}))}",
        "",
        "| " + " | ".join(record["columns"]) + " |",
        "|" + "---|" * len(record["columns"]),
    ]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in record["rows"]]
    if record.get("notes"):
        lines += ["", record["notes"].strip()]
    return [*lines, ""]


def render(folder: Path) -> str:
    records = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json")) if p.name != NOT_KEPT]
    order = {s: k for k, s in enumerate(SECTIONS)}
    records.sort(key=lambda r: (order.get(r.get("section", "Other"), len(SECTIONS)), r.get("order", 0), r["name"]))
    lines = [HEADER]
    section = None
    for record in records:
        if record.get("section", "Other") != section:
            section = record.get("section", "Other")
            lines += [f"## {section}", ""]
        lines += table(record)
    not_kept = folder / NOT_KEPT
    if not_kept.exists():
        lines += [
            "## Measured, not kept",
            "",
            "Ideas measured and left out, one line each with the commit it was measured at (the journal at "
            "that commit has the tables).",
            "",
        ]
        lines += [f"- {item['what']} ({item['commit']})" for item in json.loads(not_kept.read_text())]
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=RESULTS)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "benchmarks.md")
    args = parser.parse_args(argv)
    text = render(args.results)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_name(f".{args.out.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, args.out)
    print(f"{args.out}: {text.count(chr(10))} lines from {len(list(args.results.glob('*.json')))} files")


if __name__ == "__main__":
    main()
