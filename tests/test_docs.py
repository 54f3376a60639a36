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
    blocks = python_blocks(DOCS / "gtsam.md")
    assert len(blocks) >= 5
    code = "\n".join(blocks)  # the public API a SLAM stack uses is shown running, not only described
    for call in (
        "sg.run(",
        "sg.to_gtsam(",
        "sg.load_results(",
        "sg.synchronize(",
        "sg.Session(",
        ".add_scan(",
        ".add_node(",
        ".add_between(",
        ".add_prior(",
        ".add_position(",
        ".add_factor(",
        ".key(",
    ):
        assert call in code, call


def test_the_pages_name_only_top_level_names_that_exist():
    import sghr_gtsam

    pages = [DOCS.parent / "README.md", *sorted(DOCS.glob("*.md"))]
    used = {name for page in pages for name in re.findall(r"\bsg\.(\w+)", page.read_text())}
    assert used and used <= set(sghr_gtsam.__all__), used - set(sghr_gtsam.__all__)


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
