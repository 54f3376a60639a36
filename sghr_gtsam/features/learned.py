"""A local descriptor learned on simulated rooms (``Config.descriptor = "learned"``): each grid point's neighbourhood
as a cylinder patch about its normal, and a small network that turns the patch into a unit 32-d vector.

**Patch** (``encode_patches``). The neighbours within ``RADIUS`` voxels (at most ``NEIGHBOURS``) in ``RINGS`` radial
× ``LEVELS`` height (±``RADIUS``) × ``SECTORS`` azimuth bins; three channels a bin: the share of the neighbours in it,
their mean normal·axis and their mean normal·radial. The azimuth origin is arbitrary (a function of the normal
alone): the network's circular convolutions over azimuth and its max over it make the descriptor invariant to turning
the patch about its normal by whole sectors, so no reference direction in the tangent plane is needed.

**Network** (``PatchNet``, 48,672 weights): three circular 1-d convolutions over the sectors (64 channels,
GroupNorm, ReLU), a max over the sectors, a two-layer head, unit length. Inference is numpy, as the NetVLAD head's.

**Weights** (``WEIGHTS``): trained by ``benchmarks/bench_learned_descriptor.py`` on simulated rooms of
``data_tools.simulate`` only, never on a real scan (``sghr_gtsam/weights/README.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from sghr_gtsam.types import InputError

RADIUS = 7.5  # voxels
NEIGHBOURS = 256
RINGS, LEVELS, SECTORS, CHANNELS = 5, 6, 8, 3
GROUPS = 8  # GroupNorm's groups
_NORM_EPS = 1e-5  # GroupNorm's
_UNIT_EPS = 1e-12  # the floor on a norm (torch.nn.functional.normalize's)
# Patches encoded at a time: the neighbour arrays of a chunk take ~0.2 GB at 4000.
CHUNK = 4000
WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "patch_rooms.npz"


def encode_patches(
    points: np.ndarray,
    normals: np.ndarray,
    voxel: float,
    rows: np.ndarray | None = None,
    tree: cKDTree | None = None,
    workers: int = 1,
) -> np.ndarray:
    """(len(rows), CHANNELS, RINGS, LEVELS, SECTORS) float32 cylinder patches of ``points[rows]`` (all points when
    ``rows`` is None) among ``points`` (their k-d ``tree`` when built already); ``normals`` unit."""
    rows = np.arange(len(points)) if rows is None else rows
    tree = cKDTree(points) if tree is None else tree
    radius = RADIUS * voxel
    bins = RINGS * LEVELS * SECTORS
    out = np.zeros((len(rows), CHANNELS, RINGS, LEVELS, SECTORS), np.float32)
    for s in range(0, len(rows), CHUNK):
        q = rows[s : s + CHUNK]
        _, nb = tree.query(points[q], k=min(NEIGHBOURS, len(points)), distance_upper_bound=radius, workers=workers)
        nb = nb.reshape(len(q), -1)
        valid = nb < len(points)
        patch, slot = np.nonzero(valid)  # the neighbours found, flat: their patch and rank
        neighbour = nb[patch, slot]
        z = normals[q]
        a = np.where(np.abs(z[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        x = a - (a * z).sum(1, keepdims=True) * z
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        frame = np.stack([z, x, np.cross(z, x)], 1)[patch]  # rows: the patch's axis z and its tangents x, y
        h, u, w = np.einsum("eij,ej->ie", frame, points[neighbour] - points[q][patch])
        n = np.einsum("eij,ej->ie", frame, normals[neighbour])  # the neighbour's normal in the patch's frame
        rho = np.sqrt(u * u + w * w)
        ring = np.minimum((rho * (RINGS / radius)).astype(np.int64), RINGS - 1)
        level = np.clip(((h / radius + 1) * (LEVELS / 2)).astype(np.int64), 0, LEVELS - 1)
        sector = ((np.arctan2(w, u) + np.pi) / (2 * np.pi) * SECTORS).astype(np.int64) % SECTORS
        radial = (n[1] * u + n[2] * w) / np.maximum(rho, 1e-9)
        flat = patch * bins + (ring * LEVELS + level) * SECTORS + sector
        size = len(q) * bins
        count = np.bincount(flat, minlength=size).reshape(len(q), bins)
        along = np.bincount(flat, weights=n[0], minlength=size).reshape(len(q), bins)
        outward = np.bincount(flat, weights=radial, minlength=size).reshape(len(q), bins)
        per_bin = np.maximum(count, 1)
        share = count / np.maximum(valid.sum(1), 1)[:, None] * (bins / 8.0)
        block = np.stack([share, along / per_bin, outward / per_bin], 1)
        out[s : s + CHUNK] = block.reshape(len(q), CHANNELS, RINGS, LEVELS, SECTORS)
    return out


@dataclass(frozen=True)
class PatchNet:
    """The network's parameters, in torch's layouts: ``convs`` three (weight (O, C, 3), bias (O,)), ``norms`` three
    GroupNorm (weight (O,), bias (O,)), ``head`` two Linear (weight (O, I), bias (O,))."""

    convs: tuple[tuple[np.ndarray, np.ndarray], ...]
    norms: tuple[tuple[np.ndarray, np.ndarray], ...]
    head: tuple[tuple[np.ndarray, np.ndarray], ...]

    @classmethod
    def from_state(cls, state: dict[str, np.ndarray]) -> PatchNet:
        """From a state dict with torch's key names (``convs.k.weight``, ``norms.k.bias``, ``head.0.weight``,
        ``head.2.weight``, ...), as arrays."""

        def layer(name: str) -> tuple[np.ndarray, np.ndarray]:
            return tuple(np.asarray(state[f"{name}.{p}"], dtype=np.float32) for p in ("weight", "bias"))

        return cls(
            tuple(layer(f"convs.{k}") for k in range(3)),
            tuple(layer(f"norms.{k}") for k in range(3)),
            (layer("head.0"), layer("head.2")),
        )

    def state(self) -> dict[str, np.ndarray]:
        """The inverse of ``from_state``."""
        out = {}
        for name, layers in (("convs", self.convs), ("norms", self.norms)):
            for k, (w, b) in enumerate(layers):
                out[f"{name}.{k}.weight"], out[f"{name}.{k}.bias"] = w, b
        for k, (w, b) in zip((0, 2), self.head):
            out[f"head.{k}.weight"], out[f"head.{k}.bias"] = w, b
        return out

    def __call__(self, patches: np.ndarray) -> np.ndarray:
        """(B, CHANNELS, RINGS, LEVELS, SECTORS) patches -> (B, 32) float32 unit descriptors."""
        x = np.asarray(patches, dtype=np.float32)
        x = np.concatenate([np.log1p(8 * x[:, :1]), x[:, 1:]], 1).reshape(len(x), -1, SECTORS)
        x = np.ascontiguousarray(x.transpose(0, 2, 1))  # (B, L, C): the sectors as rows
        b, length = x.shape[:2]
        for (w, bias), (gamma, beta) in zip(self.convs, self.norms):
            # circular convolution, kernel 3: tap k reads sector t + k - 1, so its product is shifted by 1 - k
            taps = [(x.reshape(b * length, -1) @ w[:, :, k].T).reshape(b, length, -1) for k in range(3)]
            y = np.roll(taps[0], 1, axis=1) + taps[1] + np.roll(taps[2], -1, axis=1) + bias
            # GroupNorm: each group's mean and variance over its channels and the sectors, as one scale and shift
            # a channel (sums over the sectors first: a strided reduction over both axes is 5x slower)
            per_group = len(w) // GROUPS
            cells = length * per_group
            mean = y.sum(1, dtype=np.float64).reshape(b, GROUPS, per_group).sum(2) / cells
            var = np.maximum(
                (y * y).sum(1, dtype=np.float64).reshape(b, GROUPS, per_group).sum(2) / cells - mean * mean, 0.0
            )
            scale = (np.repeat(1.0 / np.sqrt(var + _NORM_EPS), per_group, axis=1) * gamma).astype(np.float32)
            shift = (beta - np.repeat(mean, per_group, axis=1) * scale).astype(np.float32)
            x = np.maximum(y * scale[:, None] + shift[:, None], 0.0)
        x = x.max(1)
        (w1, b1), (w2, b2) = self.head
        x = np.maximum(x @ w1.T + b1, 0.0) @ w2.T + b2
        return (x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), _UNIT_EPS)).astype(np.float32)


def torch_network(net: PatchNet | None = None, width: int = 64, dim: int = 32):
    """The same network as torch layers (``torch.nn.Module``), with ``net``'s weights or freshly initialised
    (``width`` channels, ``dim``-d output): what training optimises (``benchmarks/bench_learned_descriptor.py``)
    and the reference the numpy inference is tested against. ``PatchNet.from_state`` of its ``state_dict`` (as
    arrays) is the numpy network."""
    import torch  # training and tests only
    from torch import nn

    class _Network(nn.Module):
        def __init__(self):
            super().__init__()
            self.convs = nn.ModuleList(
                [
                    nn.Conv1d(c, width, 3, padding=1, padding_mode="circular")
                    for c in (CHANNELS * RINGS * LEVELS, width, width)
                ]
            )
            self.norms = nn.ModuleList([nn.GroupNorm(GROUPS, width) for _ in range(3)])
            self.head = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, dim))

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            x = x.float()
            x = torch.cat([torch.log1p(8 * x[:, :1]), x[:, 1:]], 1).reshape(len(x), -1, SECTORS)
            for conv, norm in zip(self.convs, self.norms):
                x = torch.relu(norm(conv(x)))
            return nn.functional.normalize(self.head(x.max(-1).values), dim=1)

    module = _Network()
    if net is not None:
        module.load_state_dict({k: torch.from_numpy(v) for k, v in net.state().items()})
    return module


@lru_cache(maxsize=2)
def load_patch_net(path: str | Path | None = None) -> PatchNet:
    """The shipped network (``WEIGHTS``), or the one saved at ``path`` (``np.savez`` of ``PatchNet.state``);
    ``InputError`` when it cannot be read."""
    path = Path(path or WEIGHTS)
    try:
        with np.load(path) as f:
            return PatchNet.from_state(dict(f))
    except (OSError, KeyError, ValueError) as e:
        raise InputError(f"cannot read the patch network {path}: {e}") from None


def learned_descriptors(
    points: np.ndarray, normals: np.ndarray, voxel: float, net: PatchNet | None = None, workers: int = 1
) -> np.ndarray:
    """(M, 32) float32 unit descriptors of every grid point (``points``, ``normals`` unit and oriented as
    ``features.local.compute_features`` orients them), by ``net`` (default the shipped one)."""
    net = load_patch_net() if net is None else net
    tree = cKDTree(points)
    return np.concatenate(
        [
            net(encode_patches(points, normals, voxel, rows, tree, workers))
            for rows in np.array_split(np.arange(len(points)), max(1, -(-len(points) // CHUNK)))
        ]
    )
