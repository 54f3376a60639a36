"""How much code decides which scans and registrations to trust, at an earlier commit and now.

    python benchmarks/bench_code_size.py [--before COMMIT]

Per module of the verification and the stages that steer the graph by the same evidence (free space, loops,
disputes, groups), its lines and its statements (Python statements other than docstrings: a count that the formatter's
line wrapping does not change) at ``--before`` (default: the commit before ``verify.py`` was added) and in the
working tree.
"""

from __future__ import annotations

import argparse
import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks._results import save  # noqa: E402

MODULES = (
    "sghr_gtsam/verify.py",
    "sghr_gtsam/registration/overrule.py",
    "sghr_gtsam/registration/visibility.py",
    "sghr_gtsam/registration/groups.py",
    "sghr_gtsam/registration/densify.py",
    "sghr_gtsam/sync/disputes.py",
    "sghr_gtsam/sync/consensus.py",
    "sghr_gtsam/sync/cycles.py",
    "sghr_gtsam/sync/bridges.py",
)
FUNCTIONS = ("sghr_gtsam/pipeline.py", ("_doubts", "_underdetermined", "_verdict"))
"""The pipeline's own part of the verdict: the doubt rules before ``verify.py``, the call of it now."""


def _statements(source: str, functions: tuple[str, ...] = ()) -> int:
    """Statements of ``source`` other than docstrings; with ``functions``, of those functions alone."""
    docstrings = 0
    tree = ast.parse(source)
    if functions:
        tree = ast.Module([n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name in functions], [])
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr):
            docstrings += isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str)
    return sum(isinstance(node, ast.stmt) for node in ast.walk(tree)) - docstrings


def _lines(source: str, functions: tuple[str, ...] = ()) -> int:
    if not functions:
        return len(source.splitlines())
    nodes = [n for n in ast.parse(source).body if isinstance(n, ast.FunctionDef) and n.name in functions]
    return sum(n.end_lineno - n.lineno + 1 for n in nodes)


def _source(commit: str | None, path: str) -> str | None:
    if commit is None:
        file = ROOT / path
        return file.read_text() if file.exists() else None
    shown = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=ROOT, capture_output=True, text=True)
    return shown.stdout if shown.returncode == 0 else None


def _first_verify_commit() -> str:
    added = subprocess.run(
        ["git", "log", "--diff-filter=A", "--format=%h", "--", "sghr_gtsam/verify.py"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    return added[-1] + "~1"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", default=None, help="commit to compare against")
    args = parser.parse_args(argv)
    before = args.before or _first_verify_commit()
    rows, totals = [], [0, 0, 0, 0]
    pipeline, functions = FUNCTIONS
    for path, names in [*((m, ()) for m in MODULES), (pipeline, functions)]:
        cells = []
        for commit in (before, None):
            source = _source(commit, path)
            cells += [0, 0] if source is None else [_lines(source, names), _statements(source, names)]
        totals = [t + c for t, c in zip(totals, cells)]
        label = path.removeprefix("sghr_gtsam/") + (f" ({', '.join(names)})" if names else "")
        rows.append([label, *cells])
    rows.append(["all", *totals])
    save(
        "code_size",
        rows,
        ["module", f"lines at {before}", f"statements at {before}", "lines now", "statements now"],
        "python benchmarks/bench_code_size.py" + (f" --before {args.before}" if args.before else ""),
        "Statements: Python statements other than docstrings (the whole tree was reformatted by ruff format in "
        "between, which changed the line counts but not these).",
        section="Other",
        title="The code that decides what to trust",
    )
    for row in rows:
        print(*row, sep="\t")


if __name__ == "__main__":
    main()
