"""Information matrices of registrations, in gtsam's tangent order [rotation, translation]."""

from __future__ import annotations

import numpy as np


def point_information(p: np.ndarray) -> np.ndarray:
    """Sum over points p (N, 3) of J^T J, J = [-[p]x, I] = d(exp(xi) p)/d xi, xi = [rotation, translation]."""
    s = p.sum(axis=0)
    S = np.array([[0.0, -s[2], s[1]], [s[2], 0.0, -s[0]], [-s[1], s[0], 0.0]])
    info = np.zeros((6, 6))
    info[:3, :3] = np.sum(p * p) * np.eye(3) - p.T @ p
    info[:3, 3:] = S
    info[3:, :3] = S.T
    info[3:, 3:] = len(p) * np.eye(3)
    return info
