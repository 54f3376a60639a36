"""NetVLAD global feature (torch): local descriptors of one scan -> one unit vector ``F``.

The head follows the NetVLAD layer the SGHR authors use (parameter names ``centroids``,
``conv.weight``, ``conv.bias``): per-point L2-normalised descriptors, soft assignment to
``clusters`` centres by a 1x1 convolution + softmax, residual sums intra-normalised per
cluster, flattened and L2-normalised. Without trained weights it is initialised from an
unsupervised k-means codebook of the scene's own descriptors (``from_codebook``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch
import torch.nn.functional as nnf
from torch import nn

from sghr_gtsam.types import InputError


class NetVLAD(nn.Module):
    def __init__(self, clusters: int = 64, dim: int = 32):
        super().__init__()
        self.centroids = nn.Parameter(torch.zeros(clusters, dim))
        self.conv = nn.Conv2d(dim, clusters, kernel_size=1, bias=True)

    def forward(self, desc: torch.Tensor) -> torch.Tensor:
        """``desc``: (B, D, P) descriptors of B scans with P points each -> (B, clusters·D) unit vectors."""
        x = nnf.normalize(desc, p=2, dim=1)
        assign = torch.softmax(self.conv(x.unsqueeze(-1)).squeeze(-1), dim=1)  # (B, K, P)
        # sum_p a_kp (x_p - c_k) = sum_p a_kp x_p - c_k sum_p a_kp
        vlad = torch.einsum("bkp,bdp->bkd", assign, x) - self.centroids[None] * assign.sum(-1, keepdim=True)
        vlad = nnf.normalize(vlad, p=2, dim=2)
        return nnf.normalize(vlad.flatten(1), p=2, dim=1)

    @classmethod
    def from_codebook(cls, centres: np.ndarray, alpha: float = 100.0) -> "NetVLAD":
        """The standard NetVLAD initialisation: soft assignment ~ nearest unit centre, sharpness ``alpha``."""
        c = torch.as_tensor(centres, dtype=torch.float32)
        c = nnf.normalize(c, p=2, dim=1)
        model = cls(clusters=c.shape[0], dim=c.shape[1])
        with torch.no_grad():
            model.centroids.copy_(c)
            model.conv.weight.copy_((2.0 * alpha * c)[:, :, None, None])
            model.conv.bias.copy_(-alpha * (c * c).sum(1))
        return model


def load_checkpoint(path: str, prefix: str = "vlador.pool.") -> NetVLAD:
    """A NetVLAD head from a checkpoint of the authors' overlap network (``network_state_dict`` with
    keys ``vlador.pool.*``; saved on cuda, so mapped to the CPU) or from one of ours (the same keys).
    ``InputError`` when the file cannot be read or holds no such head."""
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
        state = state.get("network_state_dict", state)
        state = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
        clusters, dim = state["centroids"].shape
        model = NetVLAD(clusters, dim)
        model.load_state_dict(state)
    except Exception as e:  # noqa: BLE001 - a missing, corrupt or foreign file is bad input
        reason = f"no {prefix}centroids" if isinstance(e, KeyError) else " ".join(str(e).split()) or type(e).__name__
        raise InputError(f"cannot read overlap head {path}: {reason}") from None
    return model.eval()


def kmeans_codebook(descriptors: list[np.ndarray], clusters: int = 64, samples: int = 20000,
                    iters: int = 25, seed: int = 0) -> np.ndarray:
    """Unsupervised VLAD codebook: spherical k-means on (a seeded sample of) unit-normalised descriptors."""
    rng = np.random.default_rng(seed)
    X = np.concatenate(descriptors)
    if len(X) > samples:
        X = X[rng.choice(len(X), samples, replace=False)]
    X = X.astype(np.float32)
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


def global_features(model: NetVLAD, descriptors: list[np.ndarray], max_points: int = 5000,
                    seed: int = 0) -> np.ndarray:
    """Unit global feature (N, K·D) of each scan's descriptors (P_i, D); at most ``max_points`` per scan
    (the paper samples 5000 keypoints), sampled with a fixed seed so reruns give identical scores."""
    rng = np.random.default_rng(seed)
    out = []
    threads = torch.get_num_threads()
    # One scan is a few thousand points: torch's thread pool costs more than it gives (2.7 ms a scan on
    # one thread, 62 ms on two under load, measured), and a caller may run scans in parallel.
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            for d in descriptors:
                if len(d) > max_points:
                    d = d[rng.choice(len(d), max_points, replace=False)]
                x = torch.as_tensor(np.ascontiguousarray(d.T), dtype=torch.float32)[None]
                out.append(model(x)[0].numpy())
    finally:
        torch.set_num_threads(threads)
    return np.stack(out).astype(np.float64)


def codebook_features(descriptors: list[np.ndarray], seed: int = 0) -> tuple[np.ndarray, int]:
    """The unsupervised global feature: a NetVLAD initialised from a k-means codebook of these scans' own
    descriptors (``kmeans_codebook``, ``from_codebook``); the (N, K·D) unit features and the cluster count."""
    codebook = kmeans_codebook(descriptors, seed=seed)
    return global_features(NetVLAD.from_codebook(codebook), descriptors, seed=seed), len(codebook)


DEFAULT_HEAD = Path(__file__).resolve().parents[1] / "weights" / "netvlad_fpfh.pth"
"""The head shipped with the package: trained on FPFH (``compute_features`` at the scene's default voxel)
of simulated scans only (``sghr_gtsam/weights/README.md`` says how)."""


def load_default_head(path: str | Path | None = None) -> NetVLAD:
    """The shipped overlap head (``DEFAULT_HEAD``, for 33-d FPFH), or the head at ``path``."""
    return load_checkpoint(str(path or DEFAULT_HEAD))
