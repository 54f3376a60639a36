"""benchmarks.report: the benchmarks page from the JSON files the benchmarks write (benchmarks/_results.py)."""

import json
import re

import pytest

from benchmarks import report
from benchmarks._results import save


def test_report_renders_every_table_with_its_command_commit_and_machine(tmp_path):
    results = tmp_path / "results"
    save(
        "sync_optima",
        [["sphere2500", 1687.0059, 0.0], ["garage", 1.2626, None]],
        ["graph", "f", "gap"],
        "python benchmarks/bench_sync_optima.py",
        "Within 1e-5 of the published optimum.",
        section="Pose graphs",
        title="Published optima",
        folder=results,
    )
    path = save(
        "3dmatch",
        [["home_at", "60/60", 1.0]],
        ["scene", "placed", "RR"],
        "python benchmarks/bench_3dmatch.py",
        section="3DMatch end to end",
        folder=results,
    )
    record = json.loads(path.read_text())
    record.update(transcribed=True, commit="1258102")
    path.write_text(json.dumps(record))
    (results / "not_kept.json").write_text(json.dumps([{"what": "a third start for the polish", "commit": "abc1234"}]))

    out = tmp_path / "benchmarks.md"
    report.main(["--results", str(results), "--out", str(out)])
    text = out.read_text()

    # sections in the fixed order, whatever the file names
    assert text.index("## 3DMatch end to end") < text.index("## Pose graphs") < text.index("## Measured, not kept")
    assert "`python benchmarks/bench_sync_optima.py`" in text
    assert "| sphere2500 | 1687 | 0 |" in text and "| garage | 1.263 | – |" in text
    assert "transcribed from the journal, measured at 1258102" in text
    measured = re.search(r"^measured at (\S+) on \d{4}-\d\d-\d\d; (\d+) cores", text, re.M)
    assert measured and measured.group(1) != "unknown"
    assert "Within 1e-5 of the published optimum." in text
    assert "- a third start for the polish (abc1234)" in text


def test_save_refuses_a_row_that_does_not_fit_the_columns(tmp_path):
    with pytest.raises(ValueError, match="2 cells"):
        save("x", [[1, 2, 3]], ["a", "b"], "cmd", folder=tmp_path)
