"""What importing the package costs: open3d's ``ml`` and ``visualization`` subpackages wait until used."""

import subprocess
import sys
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]


def _python(code: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=_ROOT,
                         env={**__import__("os").environ, "PYTHONPATH": "."})
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
