"""Does the answer about trust survive changes that should not matter?

    python benchmarks/bench_stability.py [--data ../shared/data] [--scenes home_at hotel_uc studyroom kitchen]

Each scene runs with defaults as given, then three times more with a change that no scan or registration should
notice: its scans listed in reverse order (links named so that they sort the other way: the run numbers them anew),
and the ICP correspondence distance 0.1 % longer and 0.1 % shorter (``Config.icp_distance`` 1.5 -> 1.5015 and 1.4985
voxels, well below any registration's noise; ``ICP_VARIANTS``). Per variant: the parts' sizes, the scans doubted,
and how far the scans' poses relative to the first scan moved against the run as given (largest rotation and
translation over the scans the two runs placed), and the registration recall of the placed scans on the scene's
3DMatch and 3DLoMatch pairs.
A verdict that changes here changes on any scene for reasons that have nothing to do with the scans.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks._results import save  # noqa: E402
from benchmarks.bench_3dmatch import SCENES as GT_SCENES  # noqa: E402
from benchmarks.bench_3dmatch import lo_gt, scene_gt  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402
from sghr_gtsam.evaluate import fragment_id, registration_recall_counting_unplaced  # noqa: E402
from sghr_gtsam.io.poses import read_poses  # noqa: E402
from sghr_gtsam.io.scans import list_scans  # noqa: E402
from sghr_gtsam.se3 import inv_T, rotation_angle  # noqa: E402

SCENES = ("home_at", "hotel_uc", "studyroom", "kitchen")
"""Scenes of ``bench_3dmatch.SCENES`` run here."""
ICP_VARIANTS = {"+0.1 %": 1.5015, "−0.1 %": 1.4985}
"""The ICP correspondence distances (voxels; the default is 1.5) of the variants that change it: both ways, so that
the table shows how far the answers spread by chance, not one draw of it."""


def _recalls(data: Path, name: str, poses: dict[str, np.ndarray]) -> tuple[float | None, float | None]:
    """Registration recall of the placed scans by the paper's protocol on the scene's 3DMatch and 3DLoMatch pairs
    (``evaluate.registration_recall_counting_unplaced``; a pair with an unplaced scan fails)."""
    scene = GT_SCENES[name]
    gt = scene_gt(data, scene)
    if "gt_log" not in gt:
        return None, None
    names = list(poses)
    ids, T = [fragment_id(n) for n in names], np.stack([poses[n] for n in names])
    every = [fragment_id(n) for n in gt["gt_names"]]
    out = []
    for log, info in [(gt["gt_log"], gt["gt_info"]), lo_gt(data, scene) or (None, None)]:
        out.append(None if log is None else registration_recall_counting_unplaced(ids, T, log, info, every).recall)
    return out[0], out[1]


def _reversed(scene: Path, folder: Path) -> dict[str, str]:
    """Links to the scene's scans (``io.scans.list_scans``) in ``folder`` that sort in reverse order; the link name ->
    the scan's name."""
    folder.mkdir()
    names = {}
    for k, path in enumerate(reversed(list_scans(scene))):
        link = folder / f"s{k:05d}_{path.name}"
        link.symlink_to(path.resolve())
        names[link.name] = path.name
    return names


def _run(scene: Path, out: Path, config: dict | None = None) -> None:
    command = [sys.executable, "-m", "sghr_gtsam", "run", str(scene), "--out", str(out), "--no-cache", "--quiet"]
    if config:
        path = out.with_suffix(".json")
        path.write_text(json.dumps(config))
        command += ["--config", str(path)]
    subprocess.run(command, cwd=ROOT, check=True, capture_output=True)


def _read(out: Path, names: dict[str, str] | None = None) -> dict:
    """Parts' sizes, doubts and poses (in the run's order) by the scans' own names."""
    rename = (lambda n: names.get(n, n)) if names else (lambda n: n)
    report = json.loads((out / "report.json").read_text())
    placed, T = read_poses(out / "poses.txt")
    return {
        "parts": sorted((len(p["scans"]) for p in report["parts"]), reverse=True),
        "doubts": sorted(rename(n) for n in report["doubts"]),
        "poses": {rename(n): pose for n, pose in zip(placed, T)},
    }


def _moved(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> tuple[float, float]:
    """Largest rotation (degrees) and translation between the runs' poses relative to the first scan of ``a`` that
    ``b`` placed too."""
    common = [n for n in a if n in b]
    ref = common[0]
    worst = (0.0, 0.0)
    for n in common:
        D = inv_T(inv_T(a[ref]) @ a[n]) @ inv_T(b[ref]) @ b[n]
        worst = (
            max(worst[0], float(np.degrees(rotation_angle(D[:3, :3])))),
            max(worst[1], float(np.linalg.norm(D[:3, 3]))),
        )
    return worst


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=data_root())
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes:
            scene = args.data / GT_SCENES[name].folder
            given = Path(tmp) / f"{name}-given"
            _run(scene, given)
            base = _read(given)
            variants = {"as given": base}
            names = _reversed(scene, Path(tmp) / f"{name}-reversed-scans")
            _run(Path(tmp) / f"{name}-reversed-scans", Path(tmp) / f"{name}-reversed")
            variants["scans in reverse order"] = _read(Path(tmp) / f"{name}-reversed", names)
            for label, distance in ICP_VARIANTS.items():
                _run(scene, Path(tmp) / f"{name}-icp{distance}", {"icp_distance": distance})
                variants[f"ICP distance {label}"] = _read(Path(tmp) / f"{name}-icp{distance}")
            for variant, result in variants.items():
                degrees, metres = _moved(base["poses"], result["poses"])
                rr, lo = _recalls(args.data, name, result["poses"])
                rows.append(
                    [
                        name,
                        variant,
                        None if rr is None else round(rr, 3),
                        None if lo is None else round(lo, 3),
                        "+".join(str(s) for s in result["parts"]),
                        len(result["doubts"]),
                        ", ".join(n.rsplit(".", 1)[0] for n in result["doubts"]) or "–",
                        round(degrees, 3),
                        round(metres, 4),
                    ]
                )
                print(*rows[-1], sep="\t", flush=True)
    save(
        "stability",
        rows,
        [
            "scene",
            "variant",
            "RR",
            "3DLoMatch RR",
            "parts",
            "doubted",
            "doubted scans",
            "max Δ rotation °",
            "max Δ translation",
        ],
        notes="Poses compared relative to the first scan both runs placed; one run a variant, 2 cores.",
        section="3DMatch end to end",
        title="The verdict under changes that should not matter",
    )


if __name__ == "__main__":
    main()
