"""Regenerate the README's pictures and the stored outputs of notebooks/tour.ipynb.

    pip install -e '.[docs]' && python -m data_tools.screenshots

1. runs `python -m sghr_gtsam demo` (a generated room, `--scans`, `--seed`) in a temporary folder and keeps
   its `summary.png` as docs/images/summary.png and its terminal output as docs/images/terminal.txt;
2. executes notebooks/tour.ipynb with a Jupyter kernel (nbclient) and stores it with its outputs, figures
   included; its weight-history figure becomes docs/images/tour_weights.png.

The PNGs are quantized to a 128-colour palette to keep the repository small. Nothing is drawn by hand.
"""

from __future__ import annotations

import argparse
import base64
import io
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
IMAGES = ROOT / "docs" / "images"
NOTEBOOK = ROOT / "notebooks" / "tour.ipynb"


def _save_small_png(data: bytes, path: Path) -> None:
    from PIL import Image

    image = Image.open(io.BytesIO(data)).convert("RGB").quantize(colors=128, method=Image.Quantize.MEDIANCUT)
    path.parent.mkdir(parents=True, exist_ok=True)
    image.save(path, optimize=True)
    print(f"{path.relative_to(ROOT)}: {image.size[0]}x{image.size[1]}, {path.stat().st_size // 1024} kB")


def demo_pictures(scans: int, seed: int) -> None:
    """The summary picture and the terminal output of a demo run."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "100"}
    with tempfile.TemporaryDirectory(prefix="sghr_screens_") as tmp:
        proc = subprocess.run(
            [sys.executable, "-m", "sghr_gtsam", "demo", "--out", tmp, "--scans", str(scans), "--seed", str(seed)],
            capture_output=True,
            text=True,
            env=env,
            cwd=ROOT,
        )
        if proc.returncode:
            raise SystemExit(f"demo failed:\n{proc.stderr}")
        _save_small_png((Path(tmp) / "results" / "summary.png").read_bytes(), IMAGES / "summary.png")
        terminal = (proc.stdout + proc.stderr).replace(tmp, "results/demo")
    (IMAGES / "terminal.txt").write_text(terminal)


def notebook_pictures() -> None:
    """Execute the tour in a kernel, store it with its outputs, keep its weight-history figure."""
    import nbformat
    from nbclient import NotebookClient

    nb = nbformat.read(NOTEBOOK, as_version=4)
    os.environ["PYTHONPATH"] = str(ROOT)  # the kernel imports this checkout's package
    NotebookClient(nb, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(ROOT)}}).execute()
    for cell in nb.cells:  # run-dependent metadata (timings) would make every regeneration a diff
        cell.metadata.pop("execution", None)
    nbformat.write(nb, NOTEBOOK)
    figures = {
        cell.id: base64.b64decode(out["data"]["image/png"])
        for cell in nb.cells
        if cell.cell_type == "code"
        for out in cell.outputs
        if "image/png" in out.get("data", {})
    }
    if set(figures) != {"summary-figure", "weights-figure"}:
        raise SystemExit(f"expected the notebook's two figures, found {sorted(figures)}")
    _save_small_png(figures["weights-figure"], IMAGES / "tour_weights.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scans", type=int, default=10, help="scans of the demo room")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--skip-notebook", action="store_true")
    args = parser.parse_args()
    demo_pictures(args.scans, args.seed)
    if not args.skip_notebook:
        notebook_pictures()


if __name__ == "__main__":
    main()
