"""Stop runs at random moments, as a terminal's Ctrl-C (the signal to the run's whole process group), `kill` (the
run alone) or a scheduler would, and count how each ended: the exit code, how many lines stderr got, and whether
the earlier result in the output folder was left byte for byte.

    python benchmarks/bench_signals.py --trials 14 --signal SIGINT --group --between 0.2 4
    python benchmarks/bench_signals.py --trials 10 --signal SIGTERM --group --between 0.2 12

Each run is `python -m sghr_gtsam run SCENE --workers 2 --no-cache --no-record` (default SCENE: the kitchen of the
shared data; `--record` keeps the recording on); the moments are drawn uniformly in --between (seconds after the
start), with --seed.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from data_tools.scene_gt import data_root  # noqa: E402


def _digest(out: Path) -> str:
    h = hashlib.sha1()
    for p in sorted(out.iterdir()):
        if p.is_file():
            h.update(p.name.encode() + p.read_bytes())
    return h.hexdigest()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", type=Path, default=data_root() / "kitchen")
    ap.add_argument("--trials", type=int, default=10)
    ap.add_argument("--signal", default="SIGINT", choices=["SIGINT", "SIGTERM"])
    ap.add_argument("--group", action="store_true", help="to the run's process group (a terminal's Ctrl-C)")
    ap.add_argument("--between", type=float, nargs=2, default=(0.2, 4.0), metavar=("FROM", "TO"))
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument(
        "--record", action="store_true", help="with the recording (rerun writes through the recorder's pipe)"
    )
    args = ap.parse_args()
    signum = signal.Signals[args.signal]
    command = [
        sys.executable,
        "-m",
        "sghr_gtsam",
        "run",
        str(args.scene),
        "--workers",
        "2",
        "--no-cache",
        *([] if args.record else ["--no-record"]),
        "--quiet",
    ]
    draw = random.Random(args.seed)
    with tempfile.TemporaryDirectory() as d:
        out = Path(d) / "out"
        subprocess.run([*command, "--out", str(out)], check=True, capture_output=True)
        before = _digest(out)
        print("| stop at s | exit | stderr lines | last line | earlier result |")
        print("|---|---|---|---|---|")
        outcomes = Counter()
        for _ in range(args.trials):
            at = draw.uniform(*args.between)
            with tempfile.TemporaryFile() as err:
                proc = subprocess.Popen(
                    [*command, "--out", str(out)], stdout=subprocess.DEVNULL, stderr=err, start_new_session=True
                )
                time.sleep(at)
                if args.group:
                    os.killpg(proc.pid, signum)
                else:
                    proc.send_signal(signum)
                code = proc.wait(timeout=120)
                try:
                    os.killpg(proc.pid, signal.SIGKILL)  # what a scheduler would end: workers left behind
                except ProcessLookupError:
                    pass
                err.seek(0)
                lines = err.read().decode(errors="replace").strip().splitlines()
            same = _digest(out) == before
            if not same:  # the run finished before the stop: its result is the new earlier one
                before = _digest(out)
            last = (lines[-1] if lines else "").replace("|", "\\|")[:90]
            print(f"| {at:.1f} | {code} | {len(lines)} | {last} | {'untouched' if same else 'replaced'} |")
            clean = code == 128 + signum and len(lines) == 1 and same
            outcomes[f"one line, exit {code}, untouched" if clean else f"exit {code}, {len(lines)} lines"] += 1
        for outcome, n in outcomes.most_common():
            print(f"\n{n} of {args.trials}: {outcome}", end="")
        print()


if __name__ == "__main__":
    main()
