"""Where a scene's run spends its time, stage by stage, for this checkout and an earlier one side by side, and
whether the two give the same answer.

    python benchmarks/bench_stages.py [--data ../shared/data] [--scenes home_at hotel_uc] [--runs 3]
        [--before DIR] [--profile SCENE]

Each run is ``python -m sghr_gtsam run SCENE --out OUT --no-cache --quiet`` in its own process, in the checkout's
folder (``--before``: another checkout, e.g. ``git worktree add ../before HEAD~3``), the runs of the two checkouts
alternating so that both see the same load. Per stage the median over ``--runs`` of the run's own timer
(report.json ``seconds``), and the median wall time with imports. The answers compared: the largest difference of a
pose matrix entry between the two checkouts' first runs, and each one's parts and doubts.
``--runs 0`` skips the timed runs. ``--profile SCENE``: one run of this checkout in one process (``workers=1``) under
cProfile, its CPU seconds split by component (the cumulative time of the functions named in ``COMPONENTS``).
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks._results import commit, save  # noqa: E402
from benchmarks.bench_3dmatch import SCENES as GT_SCENES  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402
from sghr_gtsam.io.poses import read_poses  # noqa: E402

SCENES = ("home_at", "hotel_uc", "kitchen")
"""Scenes of ``bench_3dmatch.SCENES`` run here."""
COMPONENTS = {
    "local features (FPFH)": ("local.py", "scan_features", None),
    "descriptor matching": ("pairwise.py", "mutual_matches", None),
    "robust estimate (SC²)": ("estimators.py", "sc2_estimate", None),
    "GICP of global registrations": ("icp.py", "gicp", "register_pair"),
    "GICP of refinements and loop closures": ("icp.py", "gicp", "multiscale_icp"),
    "scoring and information": ("pairwise.py", "scored", None),
    "information of refinements and loop closures": ("information.py", "registration_information", "refine_pair"),
    "synchronization": ("sync/__init__.py", "synchronize", None),
}
"""Component -> (file, function, calling function or None for every caller) whose cumulative time it is."""
COLUMNS = {
    "features": ("features",),
    "pairwise": ("pairwise",),
    "refine": ("refine",),
    "loops": ("loops",),
    "retry + groups": ("retry", "groups"),
    "other": ("load", "global_graph", "free_space", "sync", "pyramids", "covariances", "verify", "write"),
    "total": ("total",),
}
"""Table column -> the run's timed stages (report.json ``seconds``) it sums."""


def _run(checkout: Path, scene: Path, out: Path) -> tuple[float, dict]:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-m", "sghr_gtsam", "run", str(scene), "--out", str(out), "--no-cache", "--quiet"],
        cwd=checkout,
        env=env,
        check=True,
        capture_output=True,
    )
    wall = time.perf_counter() - start
    report = json.loads((out / "report.json").read_text())
    return wall, {"seconds": report["seconds"], "parts": len(report["parts"]), "doubts": report["doubts"]}


def _profile(scene: Path) -> list[list]:
    import sghr_gtsam as sg

    with tempfile.TemporaryDirectory() as tmp:
        profile = cProfile.Profile()
        profile.runcall(sg.run, str(scene), str(Path(tmp) / "out"), sg.Config(workers=1, record=False, cache=False))
    stats = pstats.Stats(profile)
    total = stats.total_tt
    rows = []
    for name, (file, function, caller) in COMPONENTS.items():
        seconds = 0.0
        for (path, _, fn), (_, _, _, cumulative, callers) in stats.stats.items():
            if path.endswith(file) and fn == function:
                seconds += cumulative if caller is None else sum(c[3] for f, c in callers.items() if f[2] == caller)
        rows.append([name, round(seconds, 1), round(100 * seconds / total)])
    return rows + [["whole run", round(total, 1), 100]]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=data_root())
    parser.add_argument("--scenes", nargs="+", default=["home_at", "hotel_uc"], choices=SCENES)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--before", type=Path, default=None, help="another checkout to compare against")
    parser.add_argument("--profile", choices=SCENES, default=None)
    args = parser.parse_args(argv)
    data = args.data
    checkouts = {"now": ROOT} | ({"before": args.before.resolve()} if args.before else {})
    labels = {c: commit(checkout) for c, checkout in checkouts.items()}
    rows, answers = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.scenes if args.runs > 0 else []:
            scene = data / GT_SCENES[name].folder
            runs: dict[str, list] = {c: [] for c in checkouts}
            for k in range(args.runs):
                for c, checkout in checkouts.items():
                    out = Path(tmp) / f"{name}-{c}-{k}"
                    wall, result = _run(checkout, scene, out)
                    result["T"] = read_poses(out / "poses.txt")[1]  # every placed scan's, in the scans' order
                    runs[c].append((wall, result))
                    shutil.rmtree(out)
                    print(f"{name} {c} run {k + 1}: {wall:.1f} s", flush=True)
            for c in checkouts:
                seconds = [r["seconds"] for _, r in runs[c]]
                cells = [
                    float(np.median([sum(t.get(s, 0.0) for s in group) for t in seconds])) for group in COLUMNS.values()
                ]
                wall = float(np.median([w for w, _ in runs[c]]))
                rows.append([name, labels[c], *(round(x, 1) for x in cells), round(wall, 1)])
            now = runs["now"][0][1]
            if "before" in runs:
                then = runs["before"][0][1]
                same = now["T"].shape == then["T"].shape
                diff = float(np.abs(now["T"] - then["T"]).max()) if same else None
                answers.append(
                    [
                        name,
                        diff,
                        then["parts"],
                        now["parts"],
                        ", ".join(sorted(then["doubts"])) or "–",
                        ", ".join(sorted(now["doubts"])) or "–",
                    ]
                )
    command = "python " + " ".join(["benchmarks/bench_stages.py", *(argv if argv is not None else sys.argv[1:])])
    if rows:
        save(
            "stages",
            rows,
            ["scene", "commit", *COLUMNS, "wall s (imports included)"],
            command,
            f"Seconds, medians of {args.runs} runs a checkout, alternating; each stage by the run's own timer "
            "(report.json), 'other' the sum of the rest (loading, global graph, free space, synchronization, pyramids, "
            "covariances, verification, writing).",
            section="Scale and speed",
            title="Where a run's time goes, stage by stage",
        )
    if answers:
        save(
            "stages_answers",
            answers,
            ["scene", "max |Δ| of a pose entry", "parts before", "parts now", "doubts before", "doubts now"],
            command,
            f"The first run of each checkout: {labels.get('before')} (before) and {labels['now']} (now).",
            section="Scale and speed",
            title="The same answers? (bench_stages)",
        )
    if args.profile:
        save(
            "stages_profile",
            _profile(data / GT_SCENES[args.profile].folder),
            ["component", "CPU s (one process)", "% of the run"],
            command,
            f"{args.profile}, workers=1, cProfile: each component's cumulative time (scoring and information includes"
            " the information of global registrations).",
            section="Scale and speed",
            title="Inside a run, by component",
        )
    for row in rows:
        print(*row, sep="\t")
    for row in answers:
        print(*row, sep="\t")


if __name__ == "__main__":
    main()
