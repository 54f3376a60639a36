"""Scans whose placement the graph itself argues against: the registrations synchronization dropped outweigh
those the placement rests on, for one scan or for a group of scans placed wrong together."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy.spatial.distance import cdist
from scipy.spatial.transform import Rotation

from ..se3 import inv_T
from ..types import PoseGraph, SyncResult
from .consensus import MAX_DEG, translation_tolerance

_CHUNK = 512
"""Candidate moves compared at once (bounds the pairwise arrays' memory)."""


def contested(graph: PoseGraph, result: SyncResult) -> np.ndarray:
    """(N,) bool: nodes of the largest part against whose placement the graph holds more registration evidence
    than for it.

    A node is contested when its dropped edges carry more initial weight ``w⁰`` than its kept ones. The vote
    that placed it counted agreeing edges, and edges from scans that see the same place agree without being
    independent: 3DMatch home_at fragment 32 sat 90° off on 8 weak edges from fragments 11-18 (``w⁰`` 117 in
    all) against 2 strong ones to fragments 23 and 31 (490). No right scan of that run came above 0.68 of that
    ratio (docs/BENCHMARKS.md).

    Scans can also be placed wrong together, held to each other by right edges: studyroom fragments 41 and 42
    (one edge of ``w⁰`` 155 between them) sat 95° off on weak look-alike edges (100 in all) while their strong
    edges to fragment 43 and others (186, agreeing on one other place) were dropped. So a group is contested
    (``_contested_groups``) when the dropped edges leaving it that agree on one move of the whole group outweigh
    the kept edges leaving it.
    """
    main = result.component == 0
    signed = np.where(result.weights > 0, graph.weight, -graph.weight)
    balance = np.bincount(graph.i, signed, graph.n) + np.bincount(graph.j, signed, graph.n)
    return _contested_groups(graph, result, main & (balance < 0))


def _contested_groups(graph: PoseGraph, result: SyncResult, flagged: np.ndarray) -> np.ndarray:
    """``flagged`` with every contested group of the largest part added.

    The groups tried are ``linkage_groups``. A group whose agreeing dropped edges outweigh its kept ones
    is not flagged when moving the scans at their other ends would cost less kept weight: the dropped edges
    then accuse those scans (home_at: fragment 32's two strong edges against the 20 scans they leave from).
    """
    main = result.component == 0
    kept = result.weights > 0
    inside = (graph.weight > 0) & main[graph.i] & main[graph.j]
    tolerance = translation_tolerance(graph)
    flagged = flagged.copy()
    for group in linkage_groups(graph, result):
        if _outweighed(graph, result.poses, group, inside, kept, tolerance):
            flagged |= group
    return flagged


def linkage_groups(graph: PoseGraph, result: SyncResult) -> Iterator[np.ndarray]:
    """(N,) bool masks: the groups of the largest part that its kept edges join in order of decreasing ``w⁰``
    (single linkage: scans held by their strongest registrations first), each as it forms, up to half the largest
    part (a larger group's outside is the smaller one, with the same edges leaving it)."""
    main = result.component == 0
    i, j, w = graph.i, graph.j, graph.weight
    half = main.sum() / 2
    parent = np.arange(graph.n)
    members = {k: [k] for k in range(graph.n)}

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    joins = np.flatnonzero((result.weights > 0) & (w > 0) & main[i] & main[j])
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


def _outweighed(graph: PoseGraph, poses: np.ndarray, group: np.ndarray, inside: np.ndarray, kept: np.ndarray,
                tolerance: float) -> bool:
    """Whether the dropped edges leaving ``group`` that agree on one move of it outweigh the kept edges leaving
    it, and moving the scans at their other ends instead would cost at least as much kept weight."""
    i, j, w = graph.i, graph.j, graph.weight
    leaving = inside & (group[i] != group[j])
    held = w[leaving & kept].sum()
    dropped = np.flatnonzero(leaving & ~kept)
    if w[dropped].sum() <= held:  # the agreeing ones cannot outweigh the kept ones either
        return False
    agreeing, _ = agreeing_edges(graph, poses, group, dropped, tolerance)
    if w[agreeing].sum() <= held:
        return False
    accused = np.zeros(graph.n, dtype=bool)
    accused[np.where(group[i[agreeing]], j[agreeing], i[agreeing])] = True
    return w[inside & kept & (accused[i] != accused[j])].sum() >= held


def agreeing_edges(graph: PoseGraph, poses: np.ndarray, group: np.ndarray, edges: np.ndarray,
                   tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """The largest-weight subset of ``edges`` (each leaving ``group``) that agree on one rigid move of the group
    in the world: rotations within ``consensus.MAX_DEG`` and the group's centre moved to within ``tolerance``;
    and that move (4, 4), as its heaviest-supported edge measures it (left-multiplies the group's poses)."""
    i, j = graph.i[edges], graph.j[edges]
    T = graph.T[edges]
    starts = group[i]
    # Where each edge would put the group: its end in the group moved onto what the edge measures.
    moves = np.where(starts[:, None, None], poses[j] @ inv_T(T) @ inv_T(poses[i]), poses[i] @ T @ inv_T(poses[j]))
    q = Rotation.from_matrix(moves[:, :3, :3]).as_quat()
    centre = poses[group, :3, 3].mean(axis=0)
    moved = moves[:, :3, :3] @ centre + moves[:, :3, 3]
    weight = graph.weight[edges]
    cos_half = np.cos(np.radians(MAX_DEG) / 2)
    best, best_support = 0, -1.0
    for s in range(0, len(edges), _CHUNK):
        agree = (np.abs(q[s:s + _CHUNK] @ q.T) >= cos_half) & (cdist(moved[s:s + _CHUNK], moved) <= tolerance)
        support = agree @ weight
        k = int(np.argmax(support))
        if support[k] > best_support:
            best, best_support = s + k, support[k]
    agree = (np.abs(q @ q[best]) >= cos_half) & (np.linalg.norm(moved - moved[best], axis=1) <= tolerance)
    return edges[agree], moves[best]
