"""Georeferenced scans (1e5-1e7 m from the origin) are registered in local frames at full precision and handed
back in their input frames: float32 code on the way (kiss-matcher's correspondences, rerun) would lose metres.

``centres`` says where each scan is centred (nowhere, near the origin); the pipeline registers the centred scans;
``to_input_frame`` maps the run's poses, edges, information and covariances back."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from sghr_gtsam.result import RunResult
from sghr_gtsam.types import PoseGraph

FAR_VOXELS = 1e4
"""Scans farther than this many voxels from the origin are centred (``centres``): float32 code (kiss-matcher's
correspondences in voxel units, rerun) resolves 6e-4 voxels there, and loses metres at 1e6 m."""


def centres(medians: np.ndarray, voxel: float) -> np.ndarray:
    """(N, 3) the point each scan is centred at: its median (``medians`` (N, 3), ``ScanStats.median``) when some scan
    lies farther than ``FAR_VOXELS`` from the origin (georeferenced coordinates), else zero. Scans near the origin are
    not moved, since centring changes a run's rounding (and so, at the margin, its results: one 3DMatch
    fragment went from 1.5° to 3.4°)."""
    return medians if np.abs(medians).max() > FAR_VOXELS * voxel else np.zeros_like(medians)


def translation(c: np.ndarray) -> np.ndarray:
    """(..., 4, 4) translations by ``c`` (..., 3)."""
    S = np.broadcast_to(np.eye(4), c.shape[:-1] + (4, 4)).copy()
    S[..., :3, 3] = c
    return S


def _adjoint(c: np.ndarray) -> np.ndarray:
    """(..., 6, 6) adjoint of the translation by ``c`` in gtsam's tangent order [rotation, translation]:
    ``S(c) exp(ξ) S(-c) = exp(Ad ξ)``."""
    A = np.broadcast_to(np.eye(6), c.shape[:-1] + (6, 6)).copy()
    A[..., 3:, :3] = np.cross(c[..., None, :], -np.eye(3))  # the skew matrix [c]×: [c]× ω = c × ω
    return A


def graph_to_input_frame(g: PoseGraph, centres: np.ndarray) -> np.ndarray:
    """``g``'s transforms and information, between scans centred at ``centres``, mapped to the input frames in place
    (``T_ij = S(c_i) T_ij' S(-c_j)``); returns each edge's adjoint ``Ad(-c_j)`` (E, 6, 6), with ``ξ' = Ad(c_j) ξ``."""
    g.T = translation(centres[g.i]) @ g.T @ translation(-centres[g.j])
    back = _adjoint(-centres[g.j])  # the information is Ad(-c_j)ᵀ Ω Ad(-c_j)
    if g.information is not None:
        g.information = np.swapaxes(back, 1, 2) @ g.information @ back
    return back


def to_input_frame(run: RunResult, centres: np.ndarray) -> None:
    """Poses, edges, their information (also its free directions' bounds and grid terms) and the pose covariances
    of a run on centred scans, in the scans' input frames: scan k centred at ``c_k``, ``T_k = S(c_a) T_k' S(-c_k)``
    with the world at scan a, ``T_ij = S(c_i) T_ij' S(-c_j)``. Features and ``sync`` stay in the centred frames
    (``centres`` is kept to map them back)."""
    anchor = int(np.flatnonzero(run.sync.component == 0)[0])
    g = run.graph
    run.poses[anchor] = np.eye(4)  # exactly: its rounding residue would be multiplied by the offset
    run.poses = translation(centres[anchor]) @ run.poses @ translation(-centres)
    back = graph_to_input_frame(g, centres)
    run.pairs = [
        replace(
            p,
            T=T,
            grid=None if p.grid is None else np.linalg.solve(A, p.grid),  # ξ' = Ad(c_j) ξ
            **{
                name: None if getattr(p, name) is None else A.T @ getattr(p, name) @ A
                for name in ("information", "bounded", "loose")
            },
        )
        for p, T, A in zip(run.pairs, g.T, back)
    ]
    if run.covariances is not None:
        forward = _adjoint(centres)
        run.covariances = forward @ run.covariances @ np.swapaxes(forward, 1, 2)
    run.centres = centres
