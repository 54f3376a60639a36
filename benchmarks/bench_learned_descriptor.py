"""The learned local descriptor (``sghr_gtsam.features.learned``, ``Config.descriptor = "learned"``): its training
data and training on simulated rooms, its inlier bar, and FPFH against it on the gt.log pairs of real 3DMatch scenes
(a learned local descriptor trained here on simulated scans).

    python benchmarks/bench_learned_descriptor.py data DIR [--scenes 160]       # ~10 min on 2 cores
    python benchmarks/bench_learned_descriptor.py train DIR WEIGHTS.npz [--minutes 22]
    python benchmarks/bench_learned_descriptor.py calibrate [--weights W] [--scenes 60]   # config.MIN_INLIERS
    python benchmarks/bench_learned_descriptor.py bars [--weights W]            # what it admits on real scans
    python benchmarks/bench_learned_descriptor.py eval [--weights W] [--scenes studyroom home_at ...] [--data ROOT]

Without ``--weights`` the shipped network (``sghr_gtsam/weights/patch_rooms.npz``) is used.

**Patch and network**: ``sghr_gtsam.features.learned`` (``encode_patches``, ``torch_network``).

**Data.** Rooms of ``data_tools.simulate.make_training_scene`` (dataset seed ``DATA_SEED``, which no benchmark
scores: ``bench_sparse_graph`` uses 2), 12–19 scans each; per scene up to ``PAIRS_A_SCENE`` pairs of GT overlap
> 0.25, per pair ``PER_PAIR`` grid points with a grid point of the other scan within 0.6 voxel under GT. Every
tenth scene is held out.

**Training.** InfoNCE (temperature 0.07) over the correspondences of one pair (the other points of the pair are
the negatives, as in matching), 8 pairs a step, Adam 1e-3, for a fixed number of minutes; the weights kept are the
best on the held-out pairs (top-1 among a pair's ``PER_PAIR``).

**Inlier bars** (``calibrate``): each descriptor's ``config.MIN_INLIERS`` is the most inliers that drops at most 5 %
of the right registrations on held-out simulated rooms (``inlier_bar``). ``bars`` reports what it admits among every
pair of the kitchen and the bunny.

**Evaluation** (``eval``): every gt.log pair of each scene is matched (``mutual_matches``) and registered
(``register_pair``, sc2) on FPFH and on the learned descriptor, from the same grid; a pair is right when the paper's
rmse under its gt.info is ≤ 0.2 m. Also the mutual matches within 2 voxels of GT (median over pairs).
"""

from __future__ import annotations

import argparse
import glob
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as nnf
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # data_tools
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_pairwise, when imported from elsewhere
from bench_pairwise import MATCH_SCENES, PAPER_RMSE, load_3dmatch, paper_rmse  # noqa: E402

from benchmarks._results import save  # noqa: E402
from data_tools.other_3dmatch_scenes import OTHER_SCENES  # noqa: E402
from data_tools.scene_gt import data_root  # noqa: E402
from sghr_gtsam.features.learned import PatchNet, encode_patches, learned_descriptors, load_patch_net, torch_network  # noqa: E402
from sghr_gtsam.features.local import ScanFeatures, compute_features  # noqa: E402

DATA_SEED = 99
PAIRS_A_SCENE = 30
PER_PAIR = 128
HOLD_OUT = 10  # every tenth room is held out of training


def learned_features(net: PatchNet, fpfh: list) -> list:
    """The scans of ``fpfh`` (``ScanFeatures``) with the learned descriptors of the same grid points."""
    return [
        ScanFeatures(
            f.points,
            f.normals,
            f.fpfh,
            f.voxel,
            f.points,
            learned_descriptors(f.points, f.normals, f.voxel, net, workers=2),
        )
        for f in fpfh
    ]


def _room(index: int):
    """Simulated room ``index`` of the data set, and the generator that drew its scan count."""
    from data_tools.simulate import make_training_scene

    rng = np.random.default_rng(index)
    return make_training_scene("room", int(rng.integers(12, 20)), [index, DATA_SEED, 1]), rng


# --- data -----------------------------------------------------------------------------------------------------


def _scene(args: tuple[Path, int]) -> int:

    folder, index = args
    path = folder / f"scene_{index:04d}.npz"
    if path.exists():
        return index
    scene, rng = _room(index)
    v = scene.voxel
    feats = [compute_features(P, v) for P in scene.scans]
    trees = [cKDTree(f.points) for f in feats]
    pairs = [(i, j) for i in range(len(feats)) for j in range(i + 1, len(feats)) if scene.overlap[i, j] > 0.25]
    rng.shuffle(pairs)
    a, b, pair = [], [], []
    for k, (i, j) in enumerate(pairs[:PAIRS_A_SCENE]):
        T = np.linalg.inv(scene.poses[i]) @ scene.poses[j]
        dist, nearest = trees[i].query(feats[j].points @ T[:3, :3].T + T[:3, 3])
        close = np.flatnonzero(dist < 0.6 * v)
        if len(close) < PER_PAIR:
            continue
        pick = rng.choice(close, PER_PAIR, replace=False)
        a.append(encode_patches(feats[i].points, feats[i].normals, v, nearest[pick], trees[i], workers=1))
        b.append(encode_patches(feats[j].points, feats[j].normals, v, pick, trees[j], workers=1))
        pair.append(np.full(PER_PAIR, k))
    if a:
        np.savez(
            path,
            a=np.concatenate(a).astype(np.float16),
            b=np.concatenate(b).astype(np.float16),
            pair=np.concatenate(pair),
        )
    return index


def make_data(folder: Path, scenes: int) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    # spawn: open3d's OpenMP pool deadlocks in a forked child
    with mp.get_context("spawn").Pool(2) as pool:
        for done, _ in enumerate(pool.imap_unordered(_scene, [(folder, k) for k in range(scenes)]), 1):
            print(f"\r{done}/{scenes} scenes", end="", flush=True)
    print()


# --- training -------------------------------------------------------------------------------------------------


def _load(files: list[str]) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    a, b, groups, start = [], [], [], 0
    for f in files:
        d = np.load(f)
        a.append(d["a"])
        b.append(d["b"])
        for p in np.unique(d["pair"]):
            groups.append(start + np.flatnonzero(d["pair"] == p))
        start += len(d["pair"])
    return np.concatenate(a), np.concatenate(b), groups


def _top1(net: torch.nn.Module, a: np.ndarray, b: np.ndarray, groups: list[np.ndarray]) -> float:
    net.eval()
    with torch.no_grad():
        hits = [
            (torch.argmax(net(torch.from_numpy(a[g])) @ net(torch.from_numpy(b[g])).T, 1) == torch.arange(len(g)))
            .float()
            .mean()
            .item()
            for g in groups
        ]
    net.train()
    return float(np.mean(hits))


def train(folder: Path, weights: Path, minutes: float) -> None:
    torch.manual_seed(0)
    files = sorted(glob.glob(str(folder / "scene_*.npz")))
    held = [f for f in files if int(f[-8:-4]) % HOLD_OUT == HOLD_OUT - 1]
    a, b, groups = _load([f for f in files if f not in held])
    va, vb, vgroups = _load(held)
    print(f"{len(files) - len(held)} scenes, {len(a)} correspondences; {len(held)} held out")
    net = torch_network()
    opt = torch.optim.Adam(net.parameters(), 1e-3)
    rng = np.random.default_rng(0)
    started, step, best = time.time(), 0, -1.0
    while time.time() - started < minutes * 60:
        loss = 0.0
        for g in rng.choice(len(groups), 8, replace=False):
            fa, fb = net(torch.from_numpy(a[groups[g]])), net(torch.from_numpy(b[groups[g]]))
            logits = fa @ fb.T / 0.07
            t = torch.arange(len(fa))
            loss = loss + 0.5 * (nnf.cross_entropy(logits, t) + nnf.cross_entropy(logits.T, t))
        opt.zero_grad()
        (loss / 8).backward()
        opt.step()
        step += 1
        if step % 200 == 0:
            top1 = _top1(net, va, vb, vgroups)
            print(f"step {step}, {time.time() - started:.0f} s: held-out top-1 {top1:.3f}", flush=True)
            if top1 > best:
                best = top1
                state = {k: v.detach().numpy().copy() for k, v in net.state_dict().items()}
                np.savez(weights, **PatchNet.from_state(state).state())
    print(f"best held-out top-1 {best:.3f}")


# --- evaluation -----------------------------------------------------------------------------------------------


def evaluate(weights: Path | None, scenes: list[str], root: Path) -> None:
    from sghr_gtsam.registration.pairwise import register_pair

    net = load_patch_net(weights)
    print(
        "| scene | descriptor | right / gt.log pairs | right / pairs \\|i−j\\| > 1 | mutual matches within 2 voxels "
        "of GT, median | pairs with ≥ 15 of them | s a scan to describe | CPU s a pair |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for name in scenes:
        _, log, info, scans, voxel = load_3dmatch(root, name, {**MATCH_SCENES, **OTHER_SCENES}[name])
        t0 = time.perf_counter()
        fpfh = [compute_features(s, voxel) for s in scans]
        seconds = {"FPFH": (time.perf_counter() - t0) / len(scans)}
        t0 = time.perf_counter()
        learned = learned_features(net, fpfh)
        seconds["learned"] = (time.perf_counter() - t0) / len(scans)
        right = {}
        far = [k for k, (i, j) in enumerate(sorted(log)) if abs(i - j) > 1]
        for label, feats in (("FPFH", fpfh), ("learned", learned)):
            good, ok, cpu = [], [], 0.0
            for (i, j), T_gt in sorted(log.items()):
                t0 = time.process_time()
                res = register_pair(feats[i], feats[j], voxel)
                cpu += time.process_time() - t0
                a, b = res.matches
                moved = feats[j].keypoints[b] @ T_gt[:3, :3].T + T_gt[:3, 3]
                good.append(int((np.linalg.norm(feats[i].keypoints[a] - moved, axis=1) < 2 * voxel).sum()))
                ok.append(paper_rmse(res.T, T_gt, info[(i, j)]) <= PAPER_RMSE)
            right[label] = np.array(ok)
            print(
                f"| {name} | {label} | {sum(ok)}/{len(ok)} | {sum(ok[k] for k in far)}/{len(far)} | "
                f"{np.median(good):.0f} | {np.mean(np.array(good) >= 15):.3f} | {seconds[label]:.2f} | "
                f"{cpu / len(ok):.3f} |",
                flush=True,
            )
        f, lr = right["FPFH"], right["learned"]
        print(
            f"|   | right with both {np.sum(f & lr)}, FPFH only {np.sum(f & ~lr)}, learned only {np.sum(~f & lr)}, "
            f"neither {np.sum(~f & ~lr)} | | | | | | |"
        )


CALIBRATION_ROOMS = 60
"""Held-out rooms ``calibrate`` registers (about 1,900 registrations a descriptor, ~700 of them right)."""
DROPPED_RIGHT = 0.05
"""The share of right registrations the inlier bar may drop: the level of its test "this registration is right"."""


def room_registrations(
    scene, feats: list, near: int = 15, apart: int = 20, estimates: bool = False
) -> list[tuple[bool, int, int | None]]:
    """(right, inliers, with ``estimates`` the inliers of the robust estimate before GICP) of ``register_pair`` (sc2)
    on up to ``near`` pairs of a generated ``scene`` with GT overlap > 0.1 (the least the 3DLoMatch protocol counts)
    and ``apart`` pairs under 0.02 (whatever these reach is chance agreement or alike structure); right: overlap >
    0.1 and within 5° / 10 voxels of GT."""
    from sghr_gtsam.registration.pairwise import register_pair
    from sghr_gtsam.se3 import relative_errors

    pairs = [(i, j) for i in range(len(feats)) for j in range(i + 1, len(feats))]
    overlapping = [p for p in pairs if scene.overlap[p] > 0.1][:near]
    out = []
    for i, j in overlapping + [p for p in pairs if scene.overlap[p] < 0.02][:apart]:
        res = register_pair(feats[i], feats[j], scene.voxel)
        rot, trans = relative_errors(res.T, np.linalg.inv(scene.poses[i]) @ scene.poses[j])
        right = bool(scene.overlap[i, j] > 0.1 and rot < 5 and trans < 10 * scene.voxel)
        out.append((right, res.inliers, _estimate_inliers(feats[i], feats[j], scene.voxel) if estimates else None))
    return out


def _estimate_inliers(target: ScanFeatures, source: ScanFeatures, voxel: float) -> int:
    """The matches that sc2's estimate (before ``register_pair``'s GICP) brings within the inlier distance."""
    from sghr_gtsam.registration.estimators import sc2_estimate
    from sghr_gtsam.registration.pairwise import mutual_matches

    a, b = mutual_matches(target, source)
    return int(sc2_estimate(target.keypoints[a], source.keypoints[b], voxel).inliers.sum()) if len(a) >= 3 else 0


def inlier_bar(registrations: list[tuple], dropped: float = DROPPED_RIGHT) -> int:
    """The most inliers a bar may ask for and still drop at most ``dropped`` of the right registrations. The
    bar tests "this registration is right", not "it is wrong": a dropped right registration is lost to the pose
    graph, an admitted wrong one is what synchronization's cycle consistency rejects."""
    right = np.sort([n for ok, n, *_ in registrations if ok])
    return int(right[int(np.floor(dropped * len(right)))])


def calibrate(weights: Path | None, scenes: int) -> None:
    """``config.MIN_INLIERS``: each descriptor's ``inlier_bar`` on ``scenes`` simulated rooms that ``train`` never
    sees (``room_registrations``; no real scan is used), and how far it moves when the rooms are resampled."""
    from sghr_gtsam.config import MIN_INLIERS

    net = load_patch_net(weights)
    rooms: dict[str, list[list[tuple[bool, int, int | None]]]] = {"fpfh": [], "learned": []}
    for index in range(HOLD_OUT - 1, HOLD_OUT * scenes, HOLD_OUT):  # every tenth: rooms ``train`` never sees
        scene, _ = _room(index)
        fpfh = [compute_features(P, scene.voxel) for P in scene.scans]
        rooms["fpfh"].append(room_registrations(scene, fpfh, estimates=True))
        rooms["learned"].append(room_registrations(scene, learned_features(net, fpfh), estimates=True))
    columns = [
        "descriptor",
        "right registrations",
        "right: inliers 5 % / median",
        "wrong registrations",
        "wrong: inliers median / 95 %",
        "bar",
        "bar, 5-95 % over rooms resampled",
        "wrong admitted / right dropped at it",
        "MIN_INLIERS",
        "under it at the estimate: all / reaching it after GICP",
    ]
    rows = []
    rng = np.random.default_rng(0)
    for label, per_room in rooms.items():
        c = [r for room in per_room for r in room]
        ok, inl, at_estimate = (np.array(column) for column in zip(*c))
        bar = inlier_bar(c)
        # Rooms, not registrations, are the independent draws: a hard room drops several right ones at once.
        resampled = [
            inlier_bar([r for k in rng.integers(len(per_room), size=len(per_room)) for r in per_room[k]])
            for _ in range(1000)
        ]
        rows.append(
            [
                label,
                int(ok.sum()),
                f"{np.quantile(inl[ok], 0.05):.0f} / {np.median(inl[ok]):.0f}",
                int((~ok).sum()),
                f"{np.median(inl[~ok]):.0f} / {np.quantile(inl[~ok], 0.95):.0f}",
                bar,
                f"{np.quantile(resampled, 0.05):.0f}-{np.quantile(resampled, 0.95):.0f}",
                f"{np.mean(inl[~ok] >= bar):.3f} / {np.mean(inl[ok] < bar):.3f}",
                MIN_INLIERS[label],
                f"{int((at_estimate < bar).sum())} / {int(((at_estimate < bar) & (inl >= bar)).sum())}",
            ]
        )
        print(" | ".join(str(x) for x in rows[-1]))
    save(
        "inlier_bar_simulated",
        rows,
        columns,
        section="Other",
        title="Inlier bars on held-out simulated rooms",
        notes=(
            "Per room up to 15 pairs of GT overlap > 0.1 and 20 under 0.02, registered by sc2; right: overlap > "
            "0.1 and within 5° / 10 voxels. No real scan is used. The bar is the most inliers that drops at most 5 % "
            "of the right registrations (inlier_bar); config.MIN_INLIERS holds it. The last column: the registrations "
            "whose robust estimate (before GICP) agrees with fewer matches than the bar, and of them those that GICP "
            "brings to the bar: why register_pair polishes every estimate."
        ),
    )


def bars(weights: Path | None) -> None:
    """What each descriptor's bar (``config.MIN_INLIERS``) admits among every pair of the kitchen and the bunny
    registered (sc2), right within 5° / 0.2 m (kitchen) and 1° / 1 mm (bunny)."""
    import itertools

    from bench_pairwise import SCENES, load_scene

    from sghr_gtsam.config import MIN_INLIERS
    from sghr_gtsam.registration.pairwise import register_pair
    from sghr_gtsam.se3 import inv_T, relative_errors

    net = load_patch_net(weights)
    counts: dict[str, list[tuple[bool, int]]] = {"fpfh": [], "learned": []}
    for name in ("kitchen", "bunny"):
        _, _, rot_bound, trans_bound = SCENES[name]
        _, poses, scans, voxel = load_scene(name)
        fpfh = [compute_features(s, voxel) for s in scans]
        for label, feats in (("fpfh", fpfh), ("learned", learned_features(net, fpfh))):
            for i, j in itertools.combinations(range(len(scans)), 2):
                res = register_pair(feats[i], feats[j], voxel)
                rot, trans = relative_errors(res.T, inv_T(poses[i]) @ poses[j])
                counts[label].append((bool(rot < rot_bound and trans < trans_bound), res.inliers))
    print(
        "| descriptor | MIN_INLIERS | right admitted | their inliers, lowest five | wrong admitted | "
        "their inliers, highest five |"
    )
    print("|---|---|---|---|---|---|")
    for label, c in counts.items():
        bar = MIN_INLIERS[label]
        right = sorted(n for ok, n in c if ok)
        wrong = sorted(n for ok, n in c if not ok)
        print(
            f"| {label} | {bar} | {sum(n >= bar for n in right)} of {len(right)} | {right[:5]} | "
            f"{sum(n >= bar for n in wrong)} of {len(wrong)} | {wrong[-5:]} |"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    d = sub.add_parser("data")
    d.add_argument("folder", type=Path)
    d.add_argument("--scenes", type=int, default=160)
    t = sub.add_parser("train")
    t.add_argument("folder", type=Path)
    t.add_argument("weights", type=Path)
    t.add_argument("--minutes", type=float, default=22.0)
    e = sub.add_parser("eval")
    e.add_argument("--weights", type=Path, help="a trained network (default: the shipped one)")
    e.add_argument("--scenes", nargs="+", default=list(MATCH_SCENES), choices=[*MATCH_SCENES, *OTHER_SCENES])
    e.add_argument(
        "--data",
        type=Path,
        default=data_root(),
        help="the shared data, or a folder made by data_tools.other_3dmatch_scenes for the other scenes",
    )
    c = sub.add_parser("calibrate")
    c.add_argument("--weights", type=Path, help="a trained network (default: the shipped one)")
    c.add_argument("--scenes", type=int, default=CALIBRATION_ROOMS, help="held-out rooms")
    r = sub.add_parser("bars")
    r.add_argument("--weights", type=Path, help="a trained network (default: the shipped one)")
    args = ap.parse_args()
    if args.command == "data":
        make_data(args.folder, args.scenes)
    elif args.command == "train":
        train(args.folder, args.weights, args.minutes)
    elif args.command == "eval":
        evaluate(args.weights, args.scenes, args.data)
    elif args.command == "bars":
        bars(args.weights)
    else:
        calibrate(args.weights, args.scenes)


if __name__ == "__main__":
    main()
