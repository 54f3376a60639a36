"""Pose graphs with known outliers, built on the 8 real 3DMatch test scenes (the robustness benchmark) or on
generated buildings of any size (``data_tools.building``).

The corruption (``corrupt``) runs on any ground truth (``SceneGT``: poses, symmetric overlap, vertical, and
the gt.log pairs with their 6×6 information for the paper's recall). ``make_graph`` applies it to the scene
``ground_truth`` names: a real scene, or ``gen<N>`` for a generated building of N scans drawn with the
graph's seed. For the real scenes only their ground truth is used (``3dmatch-test-gt/`` of the shared data;
no point clouds):

- **Nodes**: the fragments with a finite pose in ``derived_abs_poses/<scene>.txt`` (the one NaN fragment of
  mit_lab_hj, which no GT edge reaches, is dropped; ``SceneGT.ids`` maps node → fragment number).
- **Edges**: every scan keeps its top-10 partners by overlap (symmetric union, ``graph.top_k_edges``), by the
  GT overlap of ``gt_overlap.log`` or, with ``noisy_overlap``, by ``overlap + N(0, 0.1)`` (symmetric noise).
  The score ``s`` is the overlap used for the ranking, clipped to [0.01, 1] (SGHR's score never reaches 0).
- **Inlier edges**: GT ``T_ij`` with scan j perturbed about its centre by a rotation with per-axis sigma
  2°/(2√(2/π)) = 1.25° (so the mean angle is 2°) and a translation with per-axis sigma 3.1 cm (mean 5 cm at
  the scan's centre; the translation of ``T_ij`` itself, at scan j's origin 2.3 m away, is off by 8 cm on
  average). Inlier count ``r = 3 + Poisson(300 · overlap)``.
- **Outliers**: exactly ``round(ratio · E)`` edges, drawn without replacement with probability ∝ 1.1 − overlap
  (registration fails more often on low overlap), of one kind:
  ``random``: uniform random rotation, translation uniform in [−3, 3] m per axis, ``r = 3 + Poisson(15)``;
  ``structured``: a plausible wrong placement of one scan as in a repetitive or symmetric room, i.e. the scan
  rotated by ±90° or 180° about the vertical through its centre, or shifted 0.8–1.5 m sideways (along the
  wall it faces). One placement is shared by 2 + Poisson(1) edges of that scan (capped by its edges), so the
  wrong edges agree with each other (the paper's Fig. 2 cycle); each carries the inlier noise and an inlier
  count as high as an inlier's: ``3 + Poisson(300 · o')`` with ``o'`` the overlap of a random edge of the graph.
- **Weight** ``w0 = s · r`` (SGHR's initial weight), or for the paper's ablations ``r`` or ``s`` alone.

Scene-level details without point clouds: a fragment's centre is the point (0, −0.3, 2.3) m of its own frame
(the centroid of the kitchen fragments in the shared data: z 2.0–2.7 m along the camera axis); the vertical is
the direction in which the fragments' camera positions vary least (a hand-held camera moves at about
constant height).

A generated building's scans use the same camera frame (x right, y down, z forward), so the same
``SCAN_CENTRE`` and perturbations apply; its vertical is the world's z.

Random streams: the overlap noise, inlier noise and counts depend on (seed, scene) only, so every ratio and
kind corrupts the same inlier graph; the outlier draw depends on (seed, scene, ratio, kind, noisy_overlap).
"""

from __future__ import annotations

import re
import zlib
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from data_tools.scene_gt import SceneGT, load_scene
from sghr_gtsam.graph import top_k_edges
from sghr_gtsam.se3 import inv_T, make_T
from sghr_gtsam.types import PoseGraph

SCENES = (
    "7-scenes-redkitchen",
    "sun3d-home_at-home_at_scan1_2013_jan_1",
    "sun3d-home_md-home_md_scan9_2012_sep_30",
    "sun3d-hotel_uc-scan3",
    "sun3d-hotel_umd-maryland_hotel1",
    "sun3d-hotel_umd-maryland_hotel3",
    "sun3d-mit_76_studyroom-76-1studyroom2",
    "sun3d-mit_lab_hj-lab_hj_tea_nov_2_2012_scan1_erika",
)
KINDS = ("random", "structured")

TOP_K = 10
OVERLAP_NOISE = 0.1
MIN_SCORE = 0.01
_MAXWELL_MEAN = 2.0 * np.sqrt(2.0 / np.pi)  # mean norm of a 3-vector of unit-sigma Gaussians
ROT_SIGMA = np.radians(2.0) / _MAXWELL_MEAN  # per axis, radians: mean angle 2°
TRANS_SIGMA = 0.05 / _MAXWELL_MEAN  # per axis, metres: mean 5 cm
MIN_INLIERS = 3
INLIERS_PER_OVERLAP = 300.0
FAILED_INLIERS = 15.0
RANDOM_TRANSLATION = 3.0  # metres, per axis
SCAN_CENTRE = np.array([0.0, -0.3, 2.3])  # metres, in the fragment's own frame
SHIFT_RANGE = (0.8, 1.5)  # metres
MIN_GROUP = 2  # edges sharing one structured wrong placement: MIN_GROUP + Poisson(1)


WEIGHTS = ("s*r", "r", "s")
"""Initial edge weights: SGHR's ``s · r``, and the paper's ablations without ``s`` and without ``r``."""


GENERATED = re.compile(r"gen(\d+)")
"""Scene names of generated buildings: ``gen200`` is a building of 200 scans."""


def ground_truth(scene: str, seed: int, root: Path | None = None) -> SceneGT:
    """A real scene's GT (``load_scene``; ``seed`` unused) or, for ``gen<N>``, the building of N scans drawn
    with ``seed`` (``data_tools.building.make_building``; cached, so callers must not modify the arrays)."""
    generated = GENERATED.fullmatch(scene)
    if generated is None:
        return load_scene(scene, root)
    from data_tools.building import make_building  # open3d's ray casting, only for generated scenes

    return make_building(int(generated.group(1)), seed)


def make_graph(
    scene: str,
    ratio: float,
    kind: str,
    seed: int,
    noisy_overlap: bool = False,
    root: Path | None = None,
    weight: str = "s*r",
) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """``corrupt`` on the ground truth of ``scene`` (``ground_truth``: a real scene or ``gen<N>``)."""
    return corrupt(ground_truth(scene, seed, root), ratio, kind, seed, noisy_overlap, weight)


def corrupt(
    gt: SceneGT, ratio: float, kind: str, seed: int, noisy_overlap: bool = False, weight: str = "s*r"
) -> tuple[PoseGraph, np.ndarray, np.ndarray]:
    """The top-k pose graph of ``gt`` with ``round(ratio · E)`` outlier edges of ``kind``; ``weight``: one of
    ``WEIGHTS`` (the same edges and measurements whichever is chosen). The random streams are keyed by
    ``seed`` and ``gt.name``.

    Returns the graph, the GT poses (N, 4, 4) of its nodes and the (E,) boolean outlier mask.
    """
    if weight not in WEIGHTS:
        raise ValueError(f"unknown initial weight {weight!r} ({', '.join(WEIGHTS)})")
    if kind not in KINDS:
        raise ValueError(f"unknown outlier kind {kind!r} ({', '.join(KINDS)})")
    if not 0.0 <= ratio < 1.0:
        raise ValueError(f"outlier ratio must be in [0, 1), got {ratio}")
    P, n = gt.poses, len(gt.ids)
    key = [seed, zlib.crc32(gt.name.encode())]
    rng = np.random.default_rng(key)

    predicted = gt.overlap
    if noisy_overlap:
        noise = np.triu(rng.normal(0.0, OVERLAP_NOISE, (n, n)), 1)
        predicted = gt.overlap + noise + noise.T
    i, j = top_k_edges(predicted, TOP_K).T
    E = len(i)
    overlap = gt.overlap[i, j]
    score = np.clip(predicted[i, j], MIN_SCORE, 1.0)
    perturb = _perturbations(rng, E)
    T = inv_T(P[i]) @ P[j] @ perturb
    inliers = MIN_INLIERS + rng.poisson(INLIERS_PER_OVERLAP * overlap)

    out_rng = np.random.default_rng(key + [round(ratio * 1000), KINDS.index(kind), int(noisy_overlap)])
    n_out = round(ratio * E)
    p_out = 1.1 - overlap
    is_outlier = np.zeros(E, dtype=bool)
    if kind == "random":
        chosen = out_rng.choice(E, n_out, replace=False, p=p_out / p_out.sum())
        T[chosen] = make_T(
            Rotation.random(n_out, random_state=out_rng).as_matrix(),
            out_rng.uniform(-RANDOM_TRANSLATION, RANDOM_TRANSLATION, (n_out, 3)),
        )
        inliers[chosen] = MIN_INLIERS + out_rng.poisson(FAILED_INLIERS, n_out)
        is_outlier[chosen] = True
    else:
        for scan, chosen in _structured_groups(out_rng, n, i, j, p_out, n_out):
            wrong = _wrong_placement(out_rng, P[scan], gt.vertical) @ P[scan]
            Pi, Pj = P[i[chosen]].copy(), P[j[chosen]].copy()
            Pi[i[chosen] == scan] = wrong
            Pj[j[chosen] == scan] = wrong
            T[chosen] = inv_T(Pi) @ Pj @ perturb[chosen]
            like = out_rng.choice(overlap, len(chosen))
            inliers[chosen] = MIN_INLIERS + out_rng.poisson(INLIERS_PER_OVERLAP * like)
            is_outlier[chosen] = True

    w0 = {"s*r": score * inliers, "r": inliers.astype(float), "s": score}[weight]
    graph = PoseGraph(n=n, i=i, j=j, T=T, weight=w0)
    return graph, P.copy(), is_outlier


def add_random_outliers(graph: PoseGraph, count: int, seed: int) -> tuple[PoseGraph, np.ndarray]:
    """``graph`` (a pose-graph benchmark's) with ``count`` more edges of the ``random`` kind between random pairs of
    distinct nodes, each with the weight and information of a random edge of ``graph``; and the (E,) mask of the
    added ones (the last ``count`` edges)."""
    rng = np.random.default_rng(seed)
    i = rng.integers(0, graph.n, count)
    j = (i + rng.integers(1, graph.n, count)) % graph.n
    like = rng.integers(0, graph.num_edges, count)
    T = make_T(
        Rotation.random(count, random_state=rng).as_matrix(),
        rng.uniform(-RANDOM_TRANSLATION, RANDOM_TRANSLATION, (count, 3)),
    )
    info = None if graph.information is None else np.concatenate([graph.information, graph.information[like]])
    out = PoseGraph(
        n=graph.n,
        i=np.r_[graph.i, i],
        j=np.r_[graph.j, j],
        T=np.concatenate([graph.T, T]),
        weight=np.r_[graph.weight, graph.weight[like]],
        information=info,
    )
    return out, np.r_[np.zeros(graph.num_edges, dtype=bool), np.ones(count, dtype=bool)]


def _perturbations(rng: np.random.Generator, E: int) -> np.ndarray:
    """(E, 4, 4) registration errors: scan j rotated about its centre, then shifted."""
    R = Rotation.from_rotvec(rng.normal(0.0, ROT_SIGMA, (E, 3))).as_matrix()
    shift = rng.normal(0.0, TRANS_SIGMA, (E, 3))
    return make_T(R, SCAN_CENTRE - R @ SCAN_CENTRE + shift)


def _structured_groups(
    rng: np.random.Generator, n: int, i: np.ndarray, j: np.ndarray, p_out: np.ndarray, n_out: int
) -> list[tuple[int, np.ndarray]]:
    """Split ``n_out`` edges into groups (scan, edge indices), each group's edges all touching its scan.

    Scans are drawn by the summed outlier probability of their free edges, then the group's edges by theirs.
    Every group has at least two edges unless a single outlier is asked for in all.
    """
    free = np.ones(len(i), dtype=bool)
    groups: list[tuple[int, np.ndarray]] = []
    remaining = n_out
    while remaining > 0:
        if remaining == 1 and groups:
            # Grow an existing group rather than leave one placement on a single edge.
            open_groups = [k for k, (scan, _) in enumerate(groups) if (free & ((i == scan) | (j == scan))).any()]
            if open_groups:
                k = open_groups[rng.integers(len(open_groups))]
                scan, members = groups[k]
                cand = np.flatnonzero(free & ((i == scan) | (j == scan)))
                extra = rng.choice(cand, p=p_out[cand] / p_out[cand].sum())
                groups[k] = (scan, np.append(members, extra))
                break
        count = np.bincount(i[free], minlength=n) + np.bincount(j[free], minlength=n)
        mass = np.bincount(i[free], p_out[free], n) + np.bincount(j[free], p_out[free], n)
        mass[count < min(MIN_GROUP, remaining)] = 0.0
        if not mass.any():  # no scan has two free edges left: fall back to single edges
            mass = np.bincount(i[free], p_out[free], n) + np.bincount(j[free], p_out[free], n)
        scan = rng.choice(n, p=mass / mass.sum())
        cand = np.flatnonzero(free & ((i == scan) | (j == scan)))
        size = min(MIN_GROUP + rng.poisson(1.0), len(cand), remaining)
        chosen = rng.choice(cand, size, replace=False, p=p_out[cand] / p_out[cand].sum())
        free[chosen] = False
        groups.append((scan, chosen))
        remaining -= size
    return groups


def _wrong_placement(rng: np.random.Generator, T_scan: np.ndarray, vertical: np.ndarray) -> np.ndarray:
    """A world-frame transform G moving the scan to a symmetric-looking wrong place (``G @ T_scan``)."""
    centre = T_scan[:3, :3] @ SCAN_CENTRE + T_scan[:3, 3]
    mode = rng.integers(4)
    if mode < 3:
        R = Rotation.from_rotvec((np.pi / 2, np.pi, -np.pi / 2)[mode] * vertical).as_matrix()
        return make_T(R, centre - R @ centre)
    # Sideways: the camera's x axis, made horizontal, runs along the wall the scan faces.
    along = T_scan[:3, 0] - (T_scan[:3, 0] @ vertical) * vertical
    along /= np.linalg.norm(along)
    return make_T(np.eye(3), rng.choice((-1.0, 1.0)) * rng.uniform(*SHIFT_RANGE) * along)
