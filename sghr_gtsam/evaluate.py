"""Scoring estimated poses against ground truth: per-scan errors, the paper's registration recall and the
whole-model check (one rigid alignment of all scan positions to GT, then every scan's error)."""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import PurePath
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial.transform import Rotation

from sghr_gtsam.se3 import inv_T, make_T, project_to_so3, relative_errors
from sghr_gtsam.types import InputError

if TYPE_CHECKING:
    from sghr_gtsam.result import RunResult


@dataclass
class ScanErrors:
    """Errors of each scan's pose relative to the reference scan, in degrees and scene units."""

    names: list[str]
    rotation_deg: np.ndarray
    translation: np.ndarray

    def within(self, max_deg: float, max_trans: float) -> np.ndarray:
        return (self.rotation_deg <= max_deg) & (self.translation <= max_trans)


def _scored(names: list[str], poses: np.ndarray, gt_poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``poses`` and ``gt_poses`` as float arrays, or an ``InputError`` unless both are (N, 4, 4) for the N names."""
    poses, gt_poses = np.asarray(poses, dtype=float), np.asarray(gt_poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or gt_poses.shape != poses.shape or len(names) != len(poses):
        raise InputError(
            f"{len(names)} names, poses {poses.shape} and GT poses {gt_poses.shape}: need N names and "
            f"two (N, 4, 4) arrays"
        )
    return poses, gt_poses


def scan_errors(names: list[str], poses: np.ndarray, gt_poses: np.ndarray, reference: int = 0) -> ScanErrors:
    """Compare ``inv(T_ref) @ T_i`` of the estimate with the same of GT (the gauge cancels); a NaN pose (a scan
    not placed) gets NaN errors."""
    poses, gt_poses = _scored(names, poses, gt_poses)
    if not 0 <= reference < len(poses):
        raise InputError(f"reference scan {reference} is not one of the {len(poses)} scans")
    est = inv_T(poses[reference])[None] @ poses
    gt = inv_T(gt_poses[reference])[None] @ gt_poses
    rot, trans = relative_errors(est, gt)
    return ScanErrors(list(names), rot, trans)


def fragment_id(name: str) -> int | None:
    """3DMatch fragment number of a file name such as ``cloud_bin_21.ply``: the last digits before the suffix
    (``.e57`` holds digits)."""
    m = re.search(r"(\d+)(?!.*\d)", PurePath(name).stem)
    return int(m.group(1)) if m else None


@dataclass
class RecallResult:
    pairs: list[tuple[int, int]]
    rmse: np.ndarray
    recalled: np.ndarray
    threshold: float

    @property
    def recall(self) -> float:
        return float(self.recalled.mean()) if len(self.recalled) else float("nan")


def registration_recall(
    ids: list[int], poses: np.ndarray, gt_log: dict, gt_info: dict, threshold: float = 0.2
) -> RecallResult:
    """The paper's registration recall (authors' ``T_eval``) over the ``gt.log`` pairs among ``ids``.

    For every GT pair (i, j) with |i − j| > 1 and both scans present: ``E = inv(T_gt) @ inv(T_i) @ T_j``,
    ``e = [t_E, q_E.xyz]``, ``rmse² = eᵀ·Info·e / Info[0, 0]``; recalled when ``rmse ≤ threshold``.
    """
    if len(ids) != len(poses):
        raise InputError(f"{len(ids)} fragment ids for {len(poses)} poses")
    index = {f: k for k, f in enumerate(ids)}
    pairs, rmse = [], []
    for (a, b), T_gt in sorted(gt_log.items()):
        if abs(a - b) <= 1 or a not in index or b not in index:
            continue
        if (a, b) not in gt_info:
            raise InputError(f"gt.info has no entry for the gt.log pair ({a}, {b})")
        T_est = inv_T(poses[index[a]]) @ poses[index[b]]
        if not np.isfinite(T_est).all():
            raise InputError(f"the pose of fragment {a} or {b} is not finite")
        gt = T_gt.copy()
        gt[:3, :3] = project_to_so3(gt[:3, :3])
        E = inv_T(gt) @ T_est
        q = Rotation.from_matrix(E[:3, :3]).as_quat()  # x, y, z, w
        if q[3] < 0:
            q = -q
        e = np.concatenate([E[:3, 3], q[:3]])
        info = gt_info[(a, b)]
        pairs.append((a, b))
        rmse.append(float(np.sqrt(max(e @ info @ e / info[0, 0], 0.0))))
    rmse_arr = np.array(rmse)
    return RecallResult(pairs, rmse_arr, rmse_arr <= threshold, threshold)


def registration_recall_counting_unplaced(
    ids: list[int], poses: np.ndarray, gt_log: dict, gt_info: dict, scene_ids: list[int], threshold: float = 0.2
) -> RecallResult:
    """The paper's protocol in full: like ``registration_recall``, but a ``gt.log`` pair (|i − j| > 1) whose
    fragments are both in the scene (``scene_ids``) while one of them was not placed (not in ``ids``)
    counts as FAILED (rmse ``inf``) instead of being skipped. Pairs naming a fragment outside the scene
    (a folder holding 9 of a scene's 60 fragments) are left out."""
    placed = registration_recall(ids, poses, gt_log, gt_info, threshold)
    scene, index = set(scene_ids), set(ids)
    unplaced = [
        (a, b)
        for (a, b) in sorted(gt_log)
        if abs(a - b) > 1 and a in scene and b in scene and not (a in index and b in index)
    ]
    rmse = np.concatenate([placed.rmse, np.full(len(unplaced), np.inf)])
    return RecallResult(placed.pairs + unplaced, rmse, rmse <= threshold, threshold)


def align_rigid(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The rigid transform A (4, 4; rotation + translation, no scale) minimising Σ‖dst_k − A·src_k‖² over
    points (N, 3): Umeyama's / Horn's closed form, as ``evo_ape --align``. With fewer than three
    non-collinear points the rotation about their line is not determined (SVD picks one)."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) == 0:
        raise InputError(f"need two (N, 3) point sets of one shape, got {src.shape} and {dst.shape}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise InputError("cannot align points that are not finite")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((dst - mu_d).T @ (src - mu_s))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0])  # a proper rotation, never a reflection
    R = U @ D @ Vt
    return make_T(R, mu_d - R @ mu_s)


@dataclass
class WholeModelErrors:
    """Each scan's error after ONE rigid alignment of all estimated scan positions to GT (``align_rigid``),
    so a model that drifts reads wrong even where every overlapping pair is right. ``alignment`` maps the
    estimate's world into GT's."""

    names: list[str]
    rotation_deg: np.ndarray
    translation: np.ndarray
    alignment: np.ndarray

    @property
    def ate_rmse(self) -> float:
        """Absolute trajectory error: RMS of the position errors after alignment (evo's APE rmse)."""
        return float(np.sqrt(np.mean(self.translation**2))) if len(self.translation) else float("nan")

    def within(self, max_deg: float, max_trans: float) -> np.ndarray:
        return (self.rotation_deg <= max_deg) & (self.translation <= max_trans)

    def doubted(self, max_deg: float, max_trans: float) -> list[str]:
        """Names of the scans outside the tolerance: those the whole-model check calls misplaced."""
        return [n for n, ok in zip(self.names, self.within(max_deg, max_trans)) if not ok]


ALIGNMENTS = ("positions", "poses")


def align_poses(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The rigid transform A (4, 4) aligning whole poses (N, 4, 4): rotation the SO(3) projection of
    Σ R_dst,k R_src,kᵀ (the chordal mean), translation the mean position offset after it. For object scans
    whose sensor positions nearly coincide or lie on a circle around the object, the positions alone
    leave the rotation poorly determined; the scans' orientations fix it."""
    src, dst = np.asarray(src, float), np.asarray(dst, float)
    if src.shape != dst.shape or src.ndim != 3 or src.shape[1:] != (4, 4) or len(src) == 0:
        raise InputError(f"need two (N, 4, 4) pose sets of one shape, got {src.shape} and {dst.shape}")
    if not (np.isfinite(src).all() and np.isfinite(dst).all()):
        raise InputError("cannot align poses that are not finite")
    R = project_to_so3(np.einsum("kij,klj->il", dst[:, :3, :3], src[:, :3, :3]))
    return make_T(R, (dst[:, :3, 3] - src[:, :3, 3] @ R.T).mean(0))


def whole_model_errors(
    names: list[str], poses: np.ndarray, gt_poses: np.ndarray, align: str = "positions", fit: np.ndarray | None = None
) -> WholeModelErrors:
    """Align ``poses`` (N, 4, 4) to ``gt_poses`` (same order) by their positions (``align_rigid``, as
    ``evo_ape --align``) or by whole poses (``align_poses``), then per scan the rotation error (degrees) and
    position error of ``A @ T_i`` against ``T_i^gt``. ``fit``: (N,) bool, the scans the alignment is fitted to
    (default all). Positions that leave a rotation free (fewer than three, or on one line) are aligned as whole
    poses."""
    poses, gt_poses = _scored(names, poses, gt_poses)
    if align not in ALIGNMENTS:
        raise InputError(f"align must be one of {', '.join(ALIGNMENTS)}; got {align!r}")
    if not (np.isfinite(poses).all() and np.isfinite(gt_poses).all()):
        raise InputError("whole-model errors need finite poses (leave out the scans not placed)")
    if fit is not None:
        fit = np.asarray(fit)
        if fit.dtype != bool or fit.shape != (len(poses),) or not fit.any():
            raise InputError(f"fit must be a boolean mask of shape ({len(poses)},) choosing at least one scan")
    src, dst = (poses, gt_poses) if fit is None else (poses[fit], gt_poses[fit])
    if align == "positions" and not _on_one_line(dst[:, :3, 3]):
        A = align_rigid(src[:, :3, 3], dst[:, :3, 3])
    else:
        A = align_poses(src, dst)
    rot, trans = relative_errors(A[None] @ poses, gt_poses)
    return WholeModelErrors(list(names), rot, trans, A)


def _on_one_line(points: np.ndarray) -> bool:
    """Whether points (N, 3) leave the rotation about their line free: fewer than three, or all on one line (the
    SVD of ``align_rigid`` then picks any: two right scans of ``demo --scans 2`` read 0 of 2 within)."""
    if len(points) < 3:
        return True
    spread = np.linalg.svd(points - points.mean(0), compute_uv=False)
    return bool(spread[1] <= 1e-9 * spread[0])


@dataclass
class SceneScore:
    """A run scored against a scene's GT: how many scans were placed, the paper's registration recall
    (unplaced fragments count as failed; None without a gt.log) and the whole-model errors of the placed
    scans. ``doubted`` are the placed scans outside the tolerance, ``flagged`` those the run itself doubted (any
    of ``RunResult.flags``); scans in GT the run never loaded count as unregistered. ``certain`` are the placed
    scans' errors under the alignment fitted to the unflagged ones alone, the model a user who trusts the flags
    keeps (None with fewer than 3 unflagged: no alignment to judge them by)."""

    scans: int
    placed: list[str]
    unregistered: list[str]
    flagged: list[str]
    recall: RecallResult | None
    whole: WholeModelErrors
    certain: WholeModelErrors | None
    max_deg: float
    max_trans: float

    @property
    def within(self) -> int:
        return int(self.whole.within(self.max_deg, self.max_trans).sum())

    @property
    def doubted(self) -> list[str]:
        return self.whole.doubted(self.max_deg, self.max_trans)

    @property
    def unflagged_wrong(self) -> list[str]:
        """Scans placed without a flag that are wrong even when only such scans are aligned to GT: a wrong model
        that looks right."""
        if self.certain is None:
            return []
        flagged = set(self.flagged)
        return [n for n in self.certain.doubted(self.max_deg, self.max_trans) if n not in flagged]


def score_run(
    names: list[str],
    poses: np.ndarray,
    gt_names: list[str],
    gt_poses: np.ndarray,
    *,
    unregistered: list[str] = (),
    flagged: Iterable[str] = (),
    gt_log: dict | None = None,
    gt_info: dict | None = None,
    max_deg: float = 5.0,
    max_trans: float = 0.2,
    align: str = "positions",
) -> SceneScore:
    """Score estimated ``poses`` of ``names`` (scans in ``unregistered`` have no pose that counts; ``flagged`` the
    run doubted) against GT poses by name (``io.poses.read_poses`` of a ``gt_poses.txt``); with
    ``gt_log``/``gt_info`` also the registration recall by the paper's protocol
    (``registration_recall_counting_unplaced``)."""
    if len(names) != len(poses) or len(gt_names) != len(gt_poses):
        raise InputError(
            f"{len(names)} names for {len(poses)} poses, {len(gt_names)} GT names for {len(gt_poses)} GT poses"
        )
    gt_index = {n: k for k, n in enumerate(gt_names)}
    if len(gt_index) != len(gt_names) or len(set(names)) != len(names):
        raise InputError("scan names must be distinct (in the run and in the ground truth)")
    strangers = [n for n in names if n not in gt_index]
    if strangers:
        raise InputError(f"{len(strangers)} scans have no ground-truth pose, e.g. {strangers[0]!r}")
    bad = set(unregistered)
    keep = [k for k, n in enumerate(names) if n not in bad]
    placed = [names[k] for k in keep]
    if not placed:
        raise InputError("no scan was placed: nothing to score")
    placed_set, doubted = set(placed), set(flagged)
    missing = [n for n in gt_names if n not in placed_set]
    poses, gt_poses = np.asarray(poses), np.asarray(gt_poses)

    def errors(fit: np.ndarray | None = None) -> WholeModelErrors:
        return whole_model_errors(placed, poses[keep], gt_poses[[gt_index[n] for n in placed]], align, fit)

    sure = np.array([n not in doubted for n in placed])
    recall = None
    if gt_log is not None and gt_info is not None:
        recall = registration_recall_counting_unplaced(
            [fragment_id(n) for n in placed], poses[keep], gt_log, gt_info, scene_ids=[fragment_id(n) for n in gt_names]
        )
    return SceneScore(
        len(gt_names),
        placed,
        missing,
        [n for n in placed if n in doubted],
        recall,
        errors(),
        errors(sure) if sure.sum() >= 3 else None,
        max_deg,
        max_trans,
    )


def score_result(result: RunResult, gt_names: list[str], gt_poses: np.ndarray, **kwargs) -> SceneScore:
    """``score_run`` of a pipeline ``RunResult`` (its poses and unregistered scans), every scan outside its trusted
    model flagged (doubtful, or in a part whose join to the world failed: ``verify.Verdict.trusted``)."""
    trusted = set(result.names if result.verdict is None else result.verdict.trusted())
    return score_run(
        result.names,
        result.poses,
        gt_names,
        gt_poses,
        unregistered=result.unregistered,
        flagged={n for n in result.names if n not in trusted},
        **kwargs,
    )


@dataclass
class PartsScore:
    """The parts of a run against GT: per part (largest first) its scans and its largest rigid piece (the most
    scans whose poses relative to one of them all lie within the tolerance of GT's), the ``misplaced`` scans
    (outside the largest rigid piece of their own part) and the ``doubted`` ones (the run's doubts)."""

    parts: list[list[str]]
    pieces: list[list[str]]
    misplaced: list[str]
    doubted: list[str]

    @property
    def caught(self) -> list[str]:
        """The misplaced scans the run doubted."""
        return [n for n in self.misplaced if n in set(self.doubted)]


def score_parts(
    names: list[str],
    poses: np.ndarray,
    gt_poses: np.ndarray,
    parts: list[list[str]],
    doubted: Iterable[str],
    max_deg: float = 15.0,
    max_trans: float = 0.6,
) -> PartsScore:
    """``PartsScore`` of ``parts`` (lists of names) of the scans ``names`` at ``poses`` against ``gt_poses``."""
    poses, gt_poses = _scored(names, poses, gt_poses)
    index = {n: k for k, n in enumerate(names)}
    pieces, misplaced = [], []
    for part in parts:
        ks = [index[n] for n in part]
        best: list[int] = []
        for r in ks:
            rot, trans = relative_errors(inv_T(poses[r])[None] @ poses[ks], inv_T(gt_poses[r])[None] @ gt_poses[ks])
            piece = [k for k, a, b in zip(ks, rot, trans) if a <= max_deg and b <= max_trans]
            if len(piece) > len(best):
                best = piece
        pieces.append([names[k] for k in best])
        misplaced += [names[k] for k in ks if k not in best]
    return PartsScore([list(p) for p in parts], pieces, misplaced, sorted(set(doubted), key=index.get))
