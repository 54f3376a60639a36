"""Groups of scans that synchronization's kept edges hold together, and the dropped registrations that agree on
another placement of such a group: the candidates the free-space overrule (``registration.overrule``) tries."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from sghr_gtsam.se3 import inv_T, rotation_angle
from sghr_gtsam.sync.consensus import MAX_DEG
from sghr_gtsam.types import PoseGraph

_CHUNK = 512
"""Candidate moves compared at once (bounds the pairwise arrays' memory)."""


def linkage_groups(graph: PoseGraph, kept: np.ndarray, main: np.ndarray) -> Iterator[np.ndarray]:
    """(N,) bool masks: the groups of the ``main`` scans that the ``kept`` edges join in order of decreasing ``w⁰``
    (single linkage: scans held by their strongest registrations first), each as it forms, up to half the ``main``
    scans (a larger group's outside is the smaller one, with the same edges leaving it)."""
    i, j, w = graph.i, graph.j, graph.weight
    half = main.sum() / 2
    parent = np.arange(graph.n)
    members = {k: [k] for k in range(graph.n)}

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    joins = np.flatnonzero(kept & (w > 0) & main[i] & main[j])
    for e in joins[np.argsort(-w[joins], kind="stable")]:
        a, b = root(int(i[e])), root(int(j[e]))
        if a == b:
            continue
        if len(members[a]) < len(members[b]):
            a, b = b, a
        parent[b] = a
        members[a] += members.pop(b)
        if len(members[a]) > half:
            continue
        group = np.zeros(graph.n, dtype=bool)
        group[members[a]] = True
        yield group


def _moves(graph: PoseGraph, poses: np.ndarray, group: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(E, 4, 4): where each of ``edges`` (each leaving ``group``) would put the group, its end in the group moved
    onto what the edge measures, as a move that left-multiplies the group's poses."""
    i, j, T = graph.i[edges], graph.j[edges], graph.T[edges]
    starts = group[i]
    return np.where(starts[:, None, None], poses[j] @ inv_T(T) @ inv_T(poses[i]), poses[i] @ T @ inv_T(poses[j]))


def elsewhere(
    graph: PoseGraph, poses: np.ndarray, group: np.ndarray, edges: np.ndarray, tolerance: float
) -> np.ndarray:
    """The ``edges`` (each leaving ``group``) that would move it farther than two error budgets (rotation
    ``2 · consensus.MAX_DEG`` or its centre ``2 · tolerance``): a right registration may lie one budget off the
    truth and the kept ones that hold the group one more, so a nearer move is the same placement, not another."""
    turn, shift = move_size(poses, group, _moves(graph, poses, group, edges))
    return edges[(turn > 2 * MAX_DEG) | (shift > 2 * tolerance)]


def move_size(poses: np.ndarray, group: np.ndarray, moves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far each of ``moves`` (..., 4, 4; left-multiplying the poses of ``group``) takes the group: its turn
    (degrees) and how far it moves the group's centre."""
    centre = poses[group, :3, 3].mean(axis=0)
    shift = np.linalg.norm(moves[..., :3, :3] @ centre + moves[..., :3, 3] - centre, axis=-1)
    return np.degrees(rotation_angle(moves[..., :3, :3])), shift


def agreeing_edges(
    graph: PoseGraph, poses: np.ndarray, group: np.ndarray, edges: np.ndarray, tolerance: float
) -> tuple[np.ndarray, np.ndarray]:
    """The largest-weight subset of ``edges`` (each leaving ``group``) that agree on one rigid move of the group
    in the world: rotations within ``consensus.MAX_DEG`` and the group's centre moved to within ``tolerance``;
    and that move (4, 4), as its heaviest-supported edge measures it (left-multiplies the group's poses)."""
    moves = _moves(graph, poses, group, edges)
    q = Rotation.from_matrix(moves[:, :3, :3]).as_quat()
    centre = poses[group, :3, 3].mean(axis=0)
    moved = moves[:, :3, :3] @ centre + moves[:, :3, 3]
    weight = graph.weight[edges]
    cos_half = np.cos(np.radians(MAX_DEG) / 2)
    best, best_support = 0, -1.0
    for s in range(0, len(edges), _CHUNK):
        agree = (np.abs(q[s : s + _CHUNK] @ q.T) >= cos_half) & (cdist(moved[s : s + _CHUNK], moved) <= tolerance)
        support = agree @ weight
        k = int(np.argmax(support))
        if support[k] > best_support:
            best, best_support = s + k, support[k]
    agree = (np.abs(q @ q[best]) >= cos_half) & (np.linalg.norm(moved - moved[best], axis=1) <= tolerance)
    return edges[agree], moves[best]
