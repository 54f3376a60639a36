"""NetVLAD global feature: local descriptors of one scan -> one unit vector ``F``.

The head follows the NetVLAD layer the SGHR authors use (parameter names ``centroids``,
``conv.weight``, ``conv.bias``): per-point L2-normalised descriptors, soft assignment to
``clusters`` centres by a 1x1 convolution + softmax, residual sums intra-normalised per
cluster, flattened and L2-normalised. Without trained weights it is initialised from an
unsupervised k-means codebook of the scene's own descriptors (``VladHead.from_codebook``).
Inference is numpy: torch is imported only to read a checkpoint (and to train, ``sghr_gtsam.train``),
which keeps it off the default run (seconds of import).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from sghr_gtsam.errors import one_line
from sghr_gtsam.types import InputError

_EPS = 1e-12  # torch.nn.functional.normalize's floor on a norm


def _unit(x: np.ndarray, axis: int) -> np.ndarray:
    return x / np.maximum(np.linalg.norm(x, axis=axis, keepdims=True), _EPS)


@dataclass(frozen=True)
class VladHead:
    """A NetVLAD layer's parameters: cluster ``centroids`` (K, D) and the 1x1 convolution's ``weight`` (K, D)
    and ``bias`` (K,) that soft-assign descriptors to them."""

    centroids: np.ndarray
    weight: np.ndarray
    bias: np.ndarray

    @classmethod
    def from_codebook(cls, centres: np.ndarray, alpha: float = 100.0) -> VladHead:
        """The standard NetVLAD initialisation: soft assignment ~ nearest unit centre, sharpness ``alpha``."""
        c = _unit(np.asarray(centres, dtype=np.float64), 1)
        return cls(c, 2.0 * alpha * c, -alpha * (c * c).sum(1))

    def __call__(self, desc: np.ndarray) -> np.ndarray:
        """``desc``: (P, D) descriptors of one scan -> its (K·D,) unit feature."""
        x = _unit(np.asarray(desc, dtype=np.float64), 1)
        logits = x @ self.weight.T + self.bias
        assign = np.exp(logits - logits.max(axis=1, keepdims=True))
        assign /= assign.sum(axis=1, keepdims=True)  # (P, K)
        # sum_p a_pk (x_p - c_k) = sum_p a_pk x_p - c_k sum_p a_pk
        vlad = assign.T @ x - self.centroids * assign.sum(0)[:, None]
        return _unit(_unit(vlad, 1).ravel(), 0)


def load_checkpoint(path: str, prefix: str = "vlador.pool.") -> VladHead:
    """A NetVLAD head from a checkpoint of the authors' overlap network (``network_state_dict`` with
    keys ``vlador.pool.*``; saved on cuda, so mapped to the CPU) or from one of ours (the same keys).
    ``InputError`` when the file cannot be read or holds no such head."""
    import torch  # the checkpoint format; only here

    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as e:  # noqa: BLE001 - a missing, corrupt or foreign file is bad input
        raise InputError(f"cannot read overlap head {path}: not a PyTorch checkpoint ({one_line(e)})") from None
    try:
        state = state.get("network_state_dict", state)
        state = {k[len(prefix) :]: v.detach().double().numpy() for k, v in state.items() if k.startswith(prefix)}
        centroids, weight, bias = state["centroids"], state["conv.weight"], state["conv.bias"]
        head = VladHead(centroids, weight.reshape(len(weight), -1), bias.ravel())
        if head.weight.shape != centroids.shape or head.bias.shape != (len(centroids),):
            raise ValueError(
                f"centroids {centroids.shape}, conv.weight {weight.shape}, conv.bias {bias.shape} do not make one head"
            )
    except Exception as e:  # noqa: BLE001 - a checkpoint of something else
        reason = f"no {prefix}{e.args[0]}" if isinstance(e, KeyError) else one_line(e)
        raise InputError(f"cannot read overlap head {path}: {reason}") from None
    return head


def kmeans_codebook(
    descriptors: Sequence[np.ndarray],
    clusters: int = 64,
    samples: int = 20000,
    iters: int = 25,
    seed: int = 0,
    counts: Sequence[int] | None = None,
) -> np.ndarray:
    """Unsupervised VLAD codebook: spherical k-means on (a seeded sample of) unit-normalised descriptors.

    ``descriptors[k]`` (P_k, D) is read one scan at a time, for its sampled rows only; ``counts``: the P_k when
    known (otherwise each scan is read once more, for its length). The sample is the same as from the scans'
    concatenation."""
    rng = np.random.default_rng(seed)
    counts = [len(d) for d in descriptors] if counts is None else list(counts)
    total = int(sum(counts))
    X = _rows(descriptors, counts, rng.choice(total, samples, replace=False) if total > samples else np.arange(total))
    X /= np.linalg.norm(X, axis=1, keepdims=True) + 1e-12
    clusters = min(clusters, len(X))
    C = X[rng.choice(len(X), clusters, replace=False)]
    rows = np.arange(len(X))
    for _ in range(iters):
        labels = np.argmax(X @ C.T, axis=1)
        sums = sp.csr_matrix((np.ones(len(X), np.float32), (labels, rows)), shape=(clusters, len(X))) @ X
        norms = np.linalg.norm(sums, axis=1)
        filled = norms > 0  # an empty cluster keeps its centre
        C[filled] = sums[filled] / norms[filled, None]
    return C


def _rows(descriptors: Sequence[np.ndarray], counts: list[int], picks: np.ndarray) -> np.ndarray:
    """Rows ``picks`` of the descriptors' concatenation, in that order, as float32; each scan with a pick read
    once."""
    starts = np.concatenate([[0], np.cumsum(counts)])
    scan = np.searchsorted(starts, picks, side="right") - 1
    order = np.argsort(scan, kind="stable")
    X = None
    for group in np.split(order, np.flatnonzero(np.diff(scan[order])) + 1):
        k = int(scan[group[0]])
        rows = np.asarray(descriptors[k])[picks[group] - starts[k]]
        if X is None:
            X = np.empty((len(picks), rows.shape[1]), dtype=np.float32)
        X[group] = rows
    return X


def global_features(
    head: VladHead, descriptors: Iterable[np.ndarray], max_points: int = 5000, seed: int = 0
) -> np.ndarray:
    """Unit global feature (N, K·D) of each scan's descriptors (P_i, D), read one scan at a time; at most
    ``max_points`` per scan (the paper samples 5000 keypoints), sampled with a fixed seed so reruns give identical
    scores."""
    rng = np.random.default_rng(seed)
    out = []
    for d in descriptors:
        if len(d) > max_points:
            d = d[rng.choice(len(d), max_points, replace=False)]
        out.append(head(d))
    return np.stack(out)


def codebook_features(
    descriptors: Sequence[np.ndarray], seed: int = 0, counts: Sequence[int] | None = None
) -> tuple[np.ndarray, int]:
    """The unsupervised global feature: a NetVLAD initialised from a k-means codebook of these scans' own
    descriptors (``kmeans_codebook``, ``from_codebook``); the (N, K·D) unit features and the cluster count.
    ``descriptors[k]`` is read one scan at a time (``counts``: as in ``kmeans_codebook``)."""
    codebook = kmeans_codebook(descriptors, seed=seed, counts=counts)
    return global_features(VladHead.from_codebook(codebook), descriptors, seed=seed), len(codebook)


DEFAULT_HEAD = Path(__file__).resolve().parents[1] / "weights" / "netvlad_fpfh.pth"
"""The head shipped with the package: trained on FPFH (``compute_features`` at the scene's default voxel)
of simulated scans only (``sghr_gtsam/weights/README.md`` says how)."""


def load_default_head(path: str | Path | None = None) -> VladHead:
    """The shipped overlap head (``DEFAULT_HEAD``, for 33-d FPFH), or the head at ``path``."""
    return load_checkpoint(str(path or DEFAULT_HEAD))
