"""What importing the package costs: open3d's ``ml`` and ``visualization`` subpackages wait until used."""

import subprocess
import sys
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]


def _python(code: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=_ROOT,
        env={**__import__("os").environ, "PYTHONPATH": "."},
    )
    assert out.returncode == 0, out.stderr[-800:]
    return out.stdout.split()


def test_open3d_extras_are_deferred_until_used():
    seen = _python(
        "import sys\n"
        "import sghr_gtsam.pipeline\n"
        "print('open3d._ml3d' in sys.modules, 'open3d.visualization.draw_plotly' in sys.modules)\n"
        "import open3d\n"
        "print(callable(open3d.visualization.draw_geometries), 'open3d.visualization.draw_plotly' in sys.modules)\n"
        "from open3d.ml import datasets\n"
        "print('open3d._ml3d' in sys.modules, callable(open3d.geometry.PointCloud))\n"
    )
    assert seen == ["False", "False", "True", "True", "True", "True"]


def test_open3d_imported_first_is_left_alone():
    seen = _python("import open3d, sys\nimport sghr_gtsam.features.local\nprint('open3d._ml3d' in sys.modules)\n")
    assert seen == ["True"]


def test_default_overlap_scoring_runs_without_torch():
    """torch (seconds to import) is for a learned head's checkpoint and for training only."""
    seen = _python(
        "import sys\n"
        "import numpy as np\n"
        "import sghr_gtsam.cli, sghr_gtsam.pipeline\n"
        "from sghr_gtsam.features.netvlad import codebook_features\n"
        "from sghr_gtsam.graph import top_k_graph\n"
        "rng = np.random.default_rng(0)\n"
        "F, _ = codebook_features([rng.random((300, 33)) for _ in range(6)])\n"
        "print(len(top_k_graph(F, 3)[0]) > 0, 'torch' in sys.modules)\n"
        "from sghr_gtsam.features.netvlad import load_default_head\n"
        "load_default_head()\n"
        "print('torch' in sys.modules)\n"
    )
    assert seen == ["True", "False", "True"]


def test_a_run_without_recording_imports_neither_rerun_nor_scipy_stats():
    """rerun is for a run that records, scipy.stats for nothing a run does; together ~0.6 s of every run's start."""
    seen = _python(
        "import sys, tempfile\n"
        "import numpy as np\n"
        "import sghr_gtsam as sg\n"
        "from sghr_gtsam.synthetic import make_scene, write_scene\n"
        "folder = tempfile.mkdtemp()\n"
        "write_scene(make_scene('room', 4, 0), folder + '/scans')\n"
        "sg.run(folder + '/scans', folder + '/out', sg.Config(record=False, workers=1))\n"
        "print('rerun' in sys.modules, 'scipy.stats' in sys.modules)\n"
        "sg.run(folder + '/scans', folder + '/out2', sg.Config(workers=1))\n"
        "print('rerun' in sys.modules)\n"
    )
    assert seen == ["False", "False", "True"]


def test_every_benchmark_script_imports():
    """A benchmark whose imports fall behind the package fails here, not when its numbers are next needed
    (bench_overlap.py imported a class renamed months before anyone ran it again)."""
    scripts = sorted((_ROOT / "benchmarks").glob("bench_*.py"))
    seen = _python(
        "import importlib.util, sys\n"
        f"for path in {[str(p) for p in scripts]!r}:\n"
        "    spec = importlib.util.spec_from_file_location(path.rsplit('/', 1)[1][:-3], path)\n"
        "    sys.modules[spec.name] = module = importlib.util.module_from_spec(spec)\n"
        "    spec.loader.exec_module(module)\n"
        "    print(spec.name)\n"
    )
    assert seen == [p.stem for p in scripts] and len(seen) > 10


def test_the_everyday_names_are_at_the_top_level_and_imported_when_first_used():
    """``import sghr_gtsam as sg; sg.run(...)``: each name is the one its module defines, and importing the package
    imports none of them (the pipeline, gtsam: seconds)."""
    seen = _python(
        "import sys\n"
        "import sghr_gtsam as sg\n"
        "print('sghr_gtsam.pipeline' in sys.modules, 'gtsam' in sys.modules)\n"
        "from sghr_gtsam.config import Config\n"
        "from sghr_gtsam.gtsam_api import to_gtsam\n"
        "from sghr_gtsam.incremental import Session\n"
        "from sghr_gtsam.io.results import load_results\n"
        "from sghr_gtsam.pipeline import register, run\n"
        "from sghr_gtsam.sync import synchronize\n"
        "print(sg.run is run, sg.register is register, sg.Config is Config, sg.synchronize is synchronize,\n"
        "      sg.load_results is load_results, sg.to_gtsam is to_gtsam, sg.Session is Session)\n"
        "print(set(sg.__all__) <= set(dir(sg)), hasattr(sg, 'nothing'))\n"
        "from sghr_gtsam import local_frame, Config as C\n"
        "print(local_frame.__name__, C is Config)\n"
    )
    assert seen == ["False", "False"] + ["True"] * 7 + ["True", "False", "sghr_gtsam.local_frame", "True"]
