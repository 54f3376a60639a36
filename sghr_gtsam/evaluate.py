"""Scoring estimated poses against ground truth: per-scan errors and the paper's registration recall."""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .se3 import inv_T, project_to_so3, relative_errors


@dataclass
class ScanErrors:
    """Errors of each scan's pose relative to the reference scan, in degrees and scene units."""

    names: list[str]
    rotation_deg: np.ndarray
    translation: np.ndarray

    def within(self, max_deg: float, max_trans: float) -> np.ndarray:
        return (self.rotation_deg <= max_deg) & (self.translation <= max_trans)


def scan_errors(names: list[str], poses: np.ndarray, gt_poses: np.ndarray, reference: int = 0) -> ScanErrors:
    """Compare ``inv(T_ref) @ T_i`` of the estimate with the same of GT (the gauge cancels)."""
    est = inv_T(poses[reference])[None] @ poses
    gt = inv_T(gt_poses[reference])[None] @ gt_poses
    rot, trans = relative_errors(est, gt)
    return ScanErrors(list(names), rot, trans)


def fragment_id(name: str) -> int | None:
    """3DMatch fragment number of a file name such as ``cloud_bin_21.ply``."""
    m = re.search(r"(\d+)(?!.*\d)", name)
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


def registration_recall(ids: list[int], poses: np.ndarray, gt_log: dict, gt_info: dict,
                        threshold: float = 0.2) -> RecallResult:
    """The paper's registration recall (authors' ``T_eval``) over the ``gt.log`` pairs among ``ids``.

    For every GT pair (i, j) with |i − j| > 1 and both scans present: ``E = inv(T_gt) @ inv(T_i) @ T_j``,
    ``e = [t_E, q_E.xyz]``, ``rmse² = eᵀ·Info·e / Info[0, 0]``; recalled when ``rmse ≤ threshold``.
    """
    index = {f: k for k, f in enumerate(ids)}
    pairs, rmse = [], []
    for (a, b), T_gt in sorted(gt_log.items()):
        if abs(a - b) <= 1 or a not in index or b not in index:
            continue
        T_est = inv_T(poses[index[a]]) @ poses[index[b]]
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
