"""The notebooks run as they are shipped: every code cell in order, and what they show is what they claim."""

import json
from pathlib import Path

import numpy as np

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"


def run_notebook(path: Path) -> dict:
    """Execute the code cells of ``path`` in one namespace (as a kernel would, top to bottom)."""
    namespace: dict = {}
    for cell in json.loads(path.read_text())["cells"]:
        if cell["cell_type"] == "code":
            exec(compile("".join(cell["source"]), str(path), "exec"), namespace)  # noqa: S102 - our own file
    return namespace


def test_tour_registers_the_room_and_finds_the_wrong_edges(capsys):
    ns = run_notebook(NOTEBOOKS / "tour.ipynb")
    assert ns["errors"].rotation_deg.max() < 1.0 and ns["result"].verdict.doubts == {}
    np.testing.assert_array_equal(np.flatnonzero(ns["synced"].weights == 0), ns["wrong"])
    assert ns["rot"].max() < 3.0
    cached = ns["again"].cache  # the second run read every result back from OUT/cache and computed none
    assert all(cached[stage]["computed"] == 0 < cached[stage]["cached"] for stage in ("features", "pairs", "refined"))
    np.testing.assert_array_equal(ns["again"].poses, ns["result"].poses)
    assert ns["score"].within == ns["score"].scans == 8 and ns["score"].unflagged_wrong == []
    learned = ns["learned_score"]  # the same room matched on the learned descriptor
    assert learned.within == learned.scans == 8 and learned.unflagged_wrong == []
    assert ns["learned_config"].inlier_bar > ns["config"].inlier_bar
    assert 0 < ns["moved"] < 0.05  # the odometry factor moved scan 1, weighed against the far stiffer registrations
    assert len(ns["session"].names) == 3 and ns["session_rot"].max() < 0.5
    assert "unregistered: [] | parts: 1 | doubts: {}" in capsys.readouterr().out
    assert not ns["work"].exists()  # the notebook removes its temporary folder


def test_tour_is_stored_executed_with_its_figures():
    """Stored as a kernel ran it (data_tools/screenshots.py): every code cell executed in order, no errors, and
    the two figures inline."""
    cells = [c for c in json.loads((NOTEBOOKS / "tour.ipynb").read_text())["cells"] if c["cell_type"] == "code"]
    assert [c["execution_count"] for c in cells] == list(range(1, len(cells) + 1))
    assert not [o for c in cells for o in c["outputs"] if o["output_type"] == "error"]
    figures = [c["id"] for c in cells for o in c["outputs"] if "image/png" in o.get("data", {})]
    assert figures == ["summary-figure", "weights-figure"]
