"""What summary.png costs a run: the write stage of a kitchen run with and without it, the drawing alone (warm),
and matplotlib's import in a fresh process.

    python benchmarks/bench_summary_png.py [--data ../shared/data] [--repeat 3]

One worker, no recording (the stages before writing do not change).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # data_tools
from data_tools.scene_gt import data_root  # noqa: E402

IMPORT = (
    "import time; t = time.perf_counter(); import matplotlib.figure, matplotlib.collections; "
    "from matplotlib.backends import backend_agg; print(time.perf_counter() - t)"
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=data_root())
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()

    import sghr_gtsam.io.results as results
    from sghr_gtsam.config import Config
    from sghr_gtsam.pipeline import run
    from sghr_gtsam.plots import write_summary
    from sghr_gtsam.registration.edges import edge_status

    imports = [
        float(subprocess.run([sys.executable, "-c", IMPORT], capture_output=True, text=True, check=True).stdout)
        for _ in range(args.repeat)
    ]
    config = Config(workers=1, record=False)
    with tempfile.TemporaryDirectory() as tmp:
        results.write_summary = lambda *a, **k: None
        without = run(args.data / "kitchen", Path(tmp) / "without", config, log=lambda m: None)
        results.write_summary = write_summary
        result = run(args.data / "kitchen", Path(tmp) / "with", config, log=lambda m: None)
        status = edge_status(result)
        warm = []
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            write_summary(Path(tmp) / "summary.png", result, status)
            warm.append(time.perf_counter() - t0)
        size = (Path(tmp) / "with" / "summary.png").stat().st_size
    points = sum(len(result.features[k].points) for k in result.registered)
    print("| kitchen (9 scans) | value |\n|---|---:|")
    print(f"| points in the top view | {points:,} |")
    print(f"| write stage without summary.png (s) | {without.timings['write']:.2f} |")
    print(f"| write stage with summary.png, first drawing of the process (s) | {result.timings['write']:.2f} |")
    print(f"| summary.png drawn again, warm, median of {args.repeat} (s) | {sorted(warm)[len(warm) // 2]:.2f} |")
    print(
        f"| matplotlib import in a fresh process, median of {args.repeat} (s) | "
        f"{sorted(imports)[len(imports) // 2]:.2f} |"
    )
    print(f"| whole run with summary.png (s) | {result.timings['total']:.1f} |")
    print(f"| summary.png size (kB) | {size // 1024} |")


if __name__ == "__main__":
    main()
