"""docs/gtsam.md's Python snippets run as written, in order, in one namespace, so the page cannot rot: a folder with a
small generated scene (``scene/``) and a small g2o graph (``posegraph.g2o``, from the shared data)."""

import re
import shutil
from pathlib import Path

import pytest

from sghr_gtsam.synthetic import make_scene, write_scene

DOCS = Path(__file__).resolve().parents[1] / "docs"


def python_blocks(page: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", page.read_text(), flags=re.S | re.M)


def test_the_gtsam_page_has_snippets():
    assert len(python_blocks(DOCS / "gtsam.md")) >= 5


def test_the_gtsam_page_runs(data_dir, tmp_path, monkeypatch):
    graph = data_dir / "posegraph" / "gtsam" / "pose3example.txt"
    if not graph.is_file():
        pytest.skip(f"{graph} not found")
    shutil.copy(graph, tmp_path / "posegraph.g2o")
    write_scene(make_scene("room", 5, seed=0), tmp_path / "scene")
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for k, block in enumerate(python_blocks(DOCS / "gtsam.md")):
        exec(compile(block, f"docs/gtsam.md, python block {k}", "exec"), namespace)
    assert (tmp_path / "out" / "graph.g2o").is_file()
