"""Registrations across the border of a group of scans: which ones a descriptor gets right, and which ones agree.

A group of scans that a run places wrong as a block (studyroom's 58–65, a hotel's corridor half) can only be placed
right by registrations between it and the rest. This tool takes every pair of one scan in the group and one outside
it that overlaps under the GT (``MIN_OVERLAP``: the larger of the pair's two directed overlaps, points within
``RADIUS_VOXELS``), registers it with ``register_pair`` on each descriptor asked for and judges it against the GT.
Each registration with at least ``FAMILY_INLIERS`` inliers proposes a move of the group: where it puts its group
scan, against that scan's GT pose. Registrations whose moves agree form a family (``families``). A right family
larger than every wrong one is evidence a vote over the border could use; docs/BENCHMARKS.md, "Studyroom's group
58–65: what each descriptor registers across its border", is this tool's first use.

Command line: ``python -m data_tools.border_pairs SCENE_DIR LO-HI [--descriptors fpfh learned] [--all-pairs]``
reads the scans and ``gt_poses.txt`` of SCENE_DIR (scans named ``cloud_bin_<k>.ply``, the group ``cloud_bin_LO`` …
``cloud_bin_HI``) and prints, per descriptor, the right pairs, the pairs at or above the descriptor's inlier bar and
the families; ``--all-pairs`` takes every pair across the border, as a search that does not know the GT would.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from data_tools.gt_overlap import combine, directed_overlap_matrix
from sghr_gtsam.config import MIN_INLIERS
from sghr_gtsam.features.local import compute_features, default_voxel
from sghr_gtsam.io.poses import read_poses
from sghr_gtsam.io.scans import load_scan
from sghr_gtsam.registration.pairwise import register_pair
from sghr_gtsam.se3 import inv_T, relative_errors

MIN_OVERLAP = 0.3
"""3DMatch's own threshold for a benchmark pair."""
RADIUS_VOXELS = 2.0
"""Points closer than this (voxels) overlap."""
TOLERANCE = (5.0, 0.2)
"""Degrees and metres: a registration is right within this of the GT, and two moves agree within it."""
FAMILY_INLIERS = 12
"""Registrations with fewer inliers propose no move: a handful of matches agrees by chance (the threshold of the
measurement in docs/BENCHMARKS.md)."""


@dataclass
class Registration:
    """One border pair ``(a, b)`` (``a`` outside the group, ``b`` in it) registered: ``T_ab``, inliers, and whether
    it lies within ``TOLERANCE`` of the GT."""

    a: int
    b: int
    T: np.ndarray
    inliers: int
    right: bool


def border_pairs(
    scans: list[np.ndarray], poses: np.ndarray, group: set[int], voxel: float, min_overlap: float | None = MIN_OVERLAP
) -> list[tuple[int, int]]:
    """Pairs ``(a, b)``, ``a`` outside ``group`` and ``b`` in it, whose larger directed overlap under ``poses``
    exceeds ``min_overlap`` (the scans' points taken on a ``voxel`` grid); every such pair when it is None (what a
    search that does not know the GT would have to weigh)."""
    outside = [a for a in range(len(scans)) if a not in group]
    if min_overlap is None:
        return [(a, b) for a in outside for b in sorted(group)]
    M = combine(directed_overlap_matrix(scans, poses, RADIUS_VOXELS * voxel, voxel), "max")
    return [(a, b) for a in outside for b in sorted(group) if M[a, b] > min_overlap]


def group_moves(poses: np.ndarray, registrations: list[Registration], centre: np.ndarray) -> np.ndarray:
    """(K, 4, 4) the move of the group each registration proposes: ``P_a T_ab P_b⁻¹`` maps scan b's GT place to where
    the registration puts it (the identity for a right one). Expressed about ``centre`` (the group's, in the world),
    so that the translations of two moves differ by how far apart they put the group, not a point far from it."""
    C = np.eye(4)
    C[:3, 3] = centre
    return np.stack([inv_T(C) @ poses[r.a] @ r.T @ inv_T(poses[r.b]) @ C for r in registrations])


def families(moves: np.ndarray, weights: np.ndarray, tolerance: tuple[float, float] = TOLERANCE) -> list[list[int]]:
    """The moves grouped so that every two moves of a group agree within ``tolerance``: the heaviest move not yet
    taken starts a family, which takes, heaviest first, every move left that agrees with all its members. A
    partition of ``range(len(moves))``, heaviest families' seeds first."""
    rot, trans = relative_errors(moves[:, None], moves[None])
    agree = (rot <= tolerance[0]) & (trans <= tolerance[1])
    order = np.argsort(-np.asarray(weights), kind="stable")
    taken = np.zeros(len(moves), dtype=bool)
    out = []
    for seed in order:
        if taken[seed]:
            continue
        family = [int(seed)]
        for k in order:
            if not taken[k] and k != seed and agree[k, family].all():
                family.append(int(k))
        taken[family] = True
        out.append(family)
    return out


def register_border(
    scans: list[np.ndarray], poses: np.ndarray, pairs: list[tuple[int, int]], voxel: float, descriptor: str
) -> list[Registration]:
    """``register_pair`` of every border pair on ``descriptor``, judged against ``poses`` (the GT)."""
    features = {
        k: compute_features(scans[k], voxel, descriptor=descriptor) for k in sorted({x for p in pairs for x in p})
    }
    out = []
    for a, b in pairs:
        result = register_pair(features[a], features[b], voxel)
        rot, trans = relative_errors(result.T[None], (inv_T(poses[a]) @ poses[b])[None])
        out.append(
            Registration(a, b, result.T, result.inliers, bool(rot[0] <= TOLERANCE[0] and trans[0] <= TOLERANCE[1]))
        )
    return out


def _listed(registrations: list[Registration]) -> str:
    return ", ".join(f"{r.a}–{r.b} ({r.inliers})" for r in sorted(registrations, key=lambda r: -r.inliers)) or "none"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("group", help="LO-HI: the group's scans cloud_bin_LO ... cloud_bin_HI")
    ap.add_argument("--descriptors", nargs="+", default=["fpfh", "learned"], choices=sorted(MIN_INLIERS))
    ap.add_argument(
        "--all-pairs",
        action="store_true",
        help=f"every pair across the border, not only those whose GT overlap exceeds {MIN_OVERLAP}",
    )
    args = ap.parse_args(argv)
    lo, hi = (int(x) for x in args.group.split("-"))
    gt_names, gt_poses = read_poses(args.scene / "gt_poses.txt")
    index = {n: k for k, n in enumerate(gt_names)}
    names = [f"cloud_bin_{k}.ply" for k in range(len(gt_names))]
    poses = gt_poses[[index[n] for n in names]]
    scans = [load_scan(args.scene / n) for n in names]
    voxel = default_voxel(scans)
    group = set(range(lo, hi + 1))
    pairs = border_pairs(scans, poses, group, voxel, None if args.all_pairs else MIN_OVERLAP)
    which = "every pair" if args.all_pairs else f"GT overlap > {MIN_OVERLAP}"
    print(f"{args.scene.name}: group {lo}–{hi}, {len(pairs)} border pairs ({which})")
    for descriptor in args.descriptors:
        registrations = register_border(scans, poses, pairs, voxel, descriptor)
        bar = MIN_INLIERS[descriptor]
        print(f"{descriptor} (bar {bar}): right {_listed([r for r in registrations if r.right])}")
        print(f"  wrong at or above the bar: {_listed([r for r in registrations if not r.right and r.inliers >= bar])}")
        strong = [r for r in registrations if r.inliers >= FAMILY_INLIERS]
        if strong:
            centre = poses[sorted(group), :3, 3].mean(axis=0)
            found = [
                [strong[k] for k in f]
                for f in families(group_moves(poses, strong, centre), [r.inliers for r in strong])
            ]
            for members in sorted(found, key=lambda f: (-len(f), -sum(r.inliers for r in f)))[:4]:
                kind = "right" if members[0].right else "wrong"
                print(
                    f"  family of {len(members)}, {sum(r.inliers for r in members)} inliers, {kind}: {_listed(members)}"
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
