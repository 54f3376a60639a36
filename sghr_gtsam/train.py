"""Training the NetVLAD overlap head on FPFH descriptors (the SGHR recipe), from a cache of simulated scenes.

Recipe (Wang et al., CVPR 2023, Sec. 3.1 and their ``train.py``): every step takes one scene, α ∈ [8, 60] of
its scans and β ∈ [1024, 5000] keypoints a scan (their descriptors), computes the unit global features ``F``
with the NetVLAD head, the scores ``s_ij = (F_iᵀF_j + 1)/2`` of all α(α−1)/2 pairs, and the L1 loss between
them and the pairs' GT overlap ratios; Adam, learning rate 1e-3, ×0.7 every 50 epochs. An epoch is one step
per training scene. The head starts from a k-means codebook of the training descriptors
(``VladHead.from_codebook``), i.e. from the unsupervised feature, and learns from there.

Losses (``loss=``): ``"l1"`` is the paper's (above). It cannot be met by scores of that form (α unit vectors
have mean cosine ≥ −1/(α−1), so the mean score is ≥ ~0.5, while most GT overlaps are ~0) and spends itself
pulling every score down, at the expense of the ranking. The top-k graph only uses each scan's ranking of its
partners, which the two ranking losses target instead, on the cosines ``C = F Fᵀ`` (the scores' order):

- ``"listwise"`` (``listwise_loss``): per scan i, the KL divergence from its normalised GT overlaps
  ``p_ij = o_ij / Σ_l o_il`` to ``softmax_j(C_ij / τ)`` over its partners j ≠ i, averaged over the scans with
  some overlap; τ is learned (log τ, from ``tau``) with the head. Invariant to scaling the GT overlaps and to
  shifting a scan's cosines by a constant.
- ``"pairwise"`` (``pairwise_loss``): per scan i, the logistic loss ``log(1 + exp(−(C_ij − C_il)/τ))`` over the
  partners j, l ≠ i with ``o_ij − o_il > 0.05``, averaged; τ learned likewise. Invariant to a common shift of
  the GT overlaps and of the cosines.

With the L1 loss the kept head is the one with the lowest validation L1 (the paper's recipe); with a ranking
loss, the one with the highest validation Spearman ρ (scores vs GT overlap over all pairs of a held-out scene,
averaged over those scenes).

Descriptors: FPFH from ``features.local.compute_features`` at the scene's default voxel — what the pipeline
computes at run time. The simulated scenes and their descriptors are made once and cached by
``python -m data_tools.simulate CACHE_DIR`` (one ``scene_XXXXX.npz`` a scene, see ``write_cache_scene``);
training reads only that folder, so it takes minutes, not hours.

Outputs in ``out_dir``: ``last.pth`` (model, optimizer, scheduler, epoch, history, the loss's log τ: what
``resume`` continues from), ``best.pth`` (the best head on the validation scenes, as above: every 10th scene
of the cache is held out) and
``netvlad_fpfh.pth`` (that head alone, in the key layout ``features.netvlad.load_checkpoint`` reads, for
shipping). Runs are seeded: the draws of epoch e depend only on (seed, e), so an interrupted and resumed run
ends with the same weights as an uninterrupted one.
"""

from __future__ import annotations

import io
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as nnf
import typer
from torch import nn

from sghr_gtsam.features.netvlad import VladHead, codebook_features, global_features, kmeans_codebook
from sghr_gtsam.graph import overlap_scores
from sghr_gtsam.io.atomic import atomic_write
from sghr_gtsam.types import InputError

PREFIX = "vlador.pool."  # the authors' key prefix, which load_checkpoint strips
ALPHA = (8, 60)  # scans a step
BETA = (1024, 5000)  # keypoints a scan
VAL_EVERY = 10  # every 10th cached scene (by index) is held out for validation
LOSSES = ("l1", "listwise", "pairwise")
TAU = 0.05  # initial temperature of the ranking losses (the cosines of a scene spread over ~0.3)
MARGIN = 0.05  # pairwise loss: only partners whose GT overlaps differ by more than this are ordered

Log = Callable[[str], None]


# --- the cache -----------------------------------------------------------------------------------------------


def cache_path(folder: str | Path, index: int) -> Path:
    return Path(folder) / f"scene_{index:05d}.npz"


def write_cache_scene(path: str | Path, descriptors: list[np.ndarray], overlap: np.ndarray, **extra) -> None:
    """One scene of the cache, atomically: ``desc`` (all scans' descriptors stacked, float16: FPFH values
    are 0–100 and keep 3 significant digits), ``offsets`` (scan k is ``desc[offsets[k]:offsets[k+1]]``),
    ``overlap`` (N, N) GT overlap ratios, and any ``extra`` arrays or scalars (poses, voxel, kind, ...)."""
    overlap = np.asarray(overlap, dtype=np.float32)
    if overlap.shape != (len(descriptors), len(descriptors)):
        raise ValueError(f"overlap is {overlap.shape} for {len(descriptors)} scans")
    offsets = np.cumsum([0] + [len(d) for d in descriptors])
    buffer = io.BytesIO()
    np.savez(
        buffer,
        desc=np.concatenate(descriptors).astype(np.float16),
        offsets=offsets,
        overlap=overlap,
        **{k: np.asarray(v) for k, v in extra.items()},
    )
    with atomic_write(path, "wb") as f:
        f.write(buffer.getvalue())


@dataclass
class CachedScene:
    name: str
    descriptors: list[np.ndarray]  # (P_k, D) float32 a scan
    overlap: np.ndarray  # (N, N) float32
    kind: str = ""


def load_cache(folder: str | Path, limit: int | None = None) -> list[CachedScene]:
    """Every ``scene_*.npz`` of ``folder`` in name order (the first ``limit`` only, if given)."""
    folder = Path(folder)
    paths = sorted(folder.glob("scene_*.npz")) if folder.is_dir() else []
    if not paths:
        raise InputError(
            f"no cached scenes (scene_*.npz) in {folder}: make them with 'python -m data_tools.simulate {folder}'"
        )
    return [_read_cached(path) for path in paths[:limit]]


def _read_cached(path: Path) -> CachedScene:
    """One cached scene, checked: ``InputError`` naming the file when it is unreadable or inconsistent."""
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = sorted({"desc", "offsets", "overlap"} - set(z.files))
            if missing:
                raise InputError(f"no {', '.join(missing)} array")
            desc, off, overlap = z["desc"].astype(np.float32), z["offsets"], z["overlap"].astype(np.float32)
            kind = str(z["kind"]) if "kind" in z.files else ""
    except InputError as e:
        raise InputError(f"cached scene {path}: {e}") from None
    except Exception as e:  # noqa: BLE001 - a corrupt or truncated archive fails in numpy or zipfile
        raise InputError(f"cannot read cached scene {path}: {' '.join(str(e).split()) or type(e).__name__}") from None
    n = len(off) - 1
    if (
        desc.ndim != 2
        or off.ndim != 1
        or n < 2
        or off[0] != 0
        or off[-1] != len(desc)
        or np.any(np.diff(off) < 1)
        or overlap.shape != (n, n)
        or not np.isfinite(desc).all()
        or not np.isfinite(overlap).all()
    ):
        raise InputError(
            f"cached scene {path} is inconsistent: descriptors {desc.shape}, offsets {off.shape}, "
            f"overlap {overlap.shape} (expected at least 2 scans of at least one descriptor)"
        )
    return CachedScene(path.stem, [desc[a:b] for a, b in zip(off[:-1], off[1:])], overlap, kind)


def split(scenes: list[CachedScene]) -> tuple[list[CachedScene], list[CachedScene]]:
    """(training, validation): every ``VAL_EVERY``-th scene is held out (none if there are fewer than 2)."""
    if len(scenes) < 2:
        return scenes, []
    held = {k for k in range(len(scenes)) if k % VAL_EVERY == VAL_EVERY - 1} or {len(scenes) - 1}
    return [s for k, s in enumerate(scenes) if k not in held], [s for k, s in enumerate(scenes) if k in held]


# --- model, loss and one step --------------------------------------------------------------------------------


class NetVLAD(nn.Module):
    """The trainable form of a ``VladHead`` (the same layer and parameter names, batched)."""

    def __init__(self, clusters: int = 64, dim: int = 32):
        super().__init__()
        self.centroids = nn.Parameter(torch.zeros(clusters, dim))
        self.conv = nn.Conv2d(dim, clusters, kernel_size=1, bias=True)

    def forward(self, desc: torch.Tensor) -> torch.Tensor:
        """``desc``: (B, D, P) descriptors of B scans with P points each -> (B, clusters·D) unit vectors."""
        x = nnf.normalize(desc, p=2, dim=1)
        assign = torch.softmax(self.conv(x.unsqueeze(-1)).squeeze(-1), dim=1)  # (B, K, P)
        vlad = torch.einsum("bkp,bdp->bkd", assign, x) - self.centroids[None] * assign.sum(-1, keepdim=True)
        vlad = nnf.normalize(vlad, p=2, dim=2)
        return nnf.normalize(vlad.flatten(1), p=2, dim=1)

    @classmethod
    def from_head(cls, head: VladHead) -> NetVLAD:
        model = cls(*head.centroids.shape)
        with torch.no_grad():
            model.centroids.copy_(torch.as_tensor(head.centroids))
            model.conv.weight.copy_(torch.as_tensor(head.weight)[:, :, None, None])
            model.conv.bias.copy_(torch.as_tensor(head.bias))
        return model

    def head(self) -> VladHead:
        """The parameters as the pipeline's numpy ``VladHead``."""

        def array(t: torch.Tensor) -> np.ndarray:
            return t.detach().double().numpy().copy()

        return VladHead(
            array(self.centroids), array(self.conv.weight).reshape(len(self.centroids), -1), array(self.conv.bias)
        )


MAX_CLUSTERS = 1024
"""The most NetVLAD clusters ``train`` takes (16 times the usual 64): 100,000 grew past 24 GB before an epoch."""


def init_head(scenes: list[CachedScene], clusters: int = 64, seed: int = 0) -> NetVLAD:
    """NetVLAD initialised from a spherical k-means codebook of (a sample of) the training descriptors."""
    rng = np.random.default_rng([seed, 1])
    sample = []
    for s in scenes:
        for d in s.descriptors:
            sample.append(d[rng.choice(len(d), min(len(d), 200), replace=False)])
    return NetVLAD.from_head(
        VladHead.from_codebook(kmeans_codebook(sample, clusters=clusters, samples=50_000, seed=seed))
    )


def pair_loss(model: NetVLAD, x: torch.Tensor, overlap: torch.Tensor) -> torch.Tensor:
    """Mean L1 between ``s_ij = (F_iᵀF_j + 1)/2`` and ``overlap`` over the pairs i < j; ``x`` (α, D, β)."""
    F = model(x)
    scores = (F @ F.T + 1.0) / 2.0
    i, j = torch.triu_indices(len(F), len(F), offset=1)
    return (scores[i, j] - overlap[i, j]).abs().mean()


def listwise_loss(cosines: torch.Tensor, overlap: torch.Tensor, log_tau: torch.Tensor | float) -> torch.Tensor:
    """Listwise loss: mean over the rows i with some GT overlap of KL(p_i ‖ q_i), ``p_ij = o_ij / Σ_l o_il``
    and ``q_i = softmax_j(C_ij / τ)`` over j ≠ i; ``cosines`` and ``overlap`` (α, α), ``τ = exp(log_tau)``."""
    n = len(cosines)
    eye = torch.eye(n, dtype=torch.bool)
    target = overlap.clamp_min(0).masked_fill(eye, 0.0)
    mass = target.sum(1)
    rows = mass > 0
    if not bool(rows.any()):
        return cosines.sum() * 0.0
    p = target[rows] / mass[rows, None]
    tau = torch.exp(torch.as_tensor(log_tau, dtype=cosines.dtype))
    logq = torch.log_softmax((cosines / tau).masked_fill(eye, float("-inf"))[rows], dim=1)
    logq = logq.masked_fill(eye[rows], 0.0)  # p is 0 there; keeps 0·(−inf) out of the sum and its gradient
    return (p * (torch.log(p.clamp_min(1e-30)) - logq)).sum(1).mean()


def pairwise_loss(
    cosines: torch.Tensor, overlap: torch.Tensor, log_tau: torch.Tensor | float, margin: float = MARGIN
) -> torch.Tensor:
    """Pairwise logistic loss: mean of ``softplus(−(C_ij − C_il)/τ)`` over the triples (i, j, l), j, l ≠ i,
    with ``o_ij − o_il > margin``; ``cosines`` and ``overlap`` (α, α), ``τ = exp(log_tau)``."""
    n = len(cosines)
    ordered = (overlap[:, :, None] - overlap[:, None, :]) > margin  # (i, j, l): o_ij − o_il > margin
    partner = ~torch.eye(n, dtype=torch.bool)
    ordered &= partner[:, :, None] & partner[:, None, :]
    if not bool(ordered.any()):
        return cosines.sum() * 0.0
    tau = torch.exp(torch.as_tensor(log_tau, dtype=cosines.dtype))
    diff = (cosines[:, :, None] - cosines[:, None, :])[ordered]
    return torch.nn.functional.softplus(-diff / tau).mean()


def step_loss(
    model: NetVLAD,
    x: torch.Tensor,
    overlap: torch.Tensor,
    loss: str = "l1",
    log_tau: torch.Tensor | float = float(np.log(TAU)),
    margin: float = MARGIN,
) -> torch.Tensor:
    """The training loss ``loss`` (one of ``LOSSES``) of one step: ``x`` (α, D, β), ``overlap`` (α, α)."""
    if loss == "l1":
        return pair_loss(model, x, overlap)
    F = model(x)
    if loss == "listwise":
        return listwise_loss(F @ F.T, overlap, log_tau)
    if loss == "pairwise":
        return pairwise_loss(F @ F.T, overlap, log_tau, margin)
    raise InputError(f"unknown loss {loss!r} ({', '.join(LOSSES)})")


def sample_step(
    scene: CachedScene, rng: np.random.Generator, alpha: tuple[int, int] = ALPHA, beta: tuple[int, int] = BETA
) -> tuple[torch.Tensor, torch.Tensor]:
    """α scans of ``scene`` (all if it has fewer), β descriptors each (drawn with replacement only from a
    scan with fewer): (α, D, β) descriptors and the (α, α) GT overlaps."""
    n = len(scene.descriptors)
    a = min(n, int(rng.integers(alpha[0], alpha[1] + 1)))
    b = int(rng.integers(beta[0], beta[1] + 1))
    scans = np.sort(rng.choice(n, a, replace=False))
    x = np.stack([d[rng.choice(len(d), b, replace=len(d) < b)] for d in (scene.descriptors[k] for k in scans)])
    target = scene.overlap[np.ix_(scans, scans)]
    return torch.from_numpy(np.ascontiguousarray(x.transpose(0, 2, 1))), torch.from_numpy(target)


def _score(scenes: list[CachedScene], features: Callable[[list[np.ndarray]], np.ndarray]) -> dict[str, float]:
    """Mean L1 between the scores of ``features`` and the GT overlaps over all pairs of each scene, and the
    mean Spearman correlation, averaged over scenes."""
    from scipy.stats import spearmanr

    l1, rho = [], []
    for s in scenes:
        S = overlap_scores(features(s.descriptors))
        iu = np.triu_indices(len(S), 1)
        l1.append(float(np.abs(S[iu] - s.overlap[iu]).mean()))
        rho.append(float(spearmanr(S[iu], s.overlap[iu]).statistic))
    return {
        "l1": float(np.mean(l1)) if l1 else float("nan"),
        "spearman": float(np.nanmean(rho)) if rho else float("nan"),
    }


def evaluate(model: NetVLAD | VladHead, scenes: list[CachedScene], seed: int = 0) -> dict[str, float]:
    """``_score`` of the head (in training or loaded), features as the pipeline computes them
    (``global_features``, at most 5000 descriptors a scan)."""
    head = model.head() if isinstance(model, NetVLAD) else model
    return _score(scenes, lambda d: global_features(head, d, seed=seed))


def evaluate_codebook(scenes: list[CachedScene], seed: int = 0) -> dict[str, float]:
    """``_score`` of the pipeline's unsupervised feature (a codebook of each scene's own descriptors,
    ``codebook_features``): the reference a trained head has to beat on the same scenes."""
    return _score(scenes, lambda d: codebook_features(d, seed=seed)[0])


# --- checkpoints ---------------------------------------------------------------------------------------------


def head_state(model: NetVLAD) -> dict[str, torch.Tensor]:
    """The head's tensors under the authors' keys (``vlador.pool.*``), which ``load_checkpoint`` reads."""
    return {PREFIX + k: v.detach().clone() for k, v in model.state_dict().items()}


def save_head(model: NetVLAD, path: str | Path, meta: dict | None = None) -> None:
    """The head alone (``network_state_dict`` + a ``meta`` dict of plain values), written atomically."""
    buffer = io.BytesIO()
    torch.save({"network_state_dict": head_state(model), "meta": dict(meta or {})}, buffer)
    with atomic_write(path, "wb") as f:
        f.write(buffer.getvalue())


def _save(path: Path, state: dict) -> None:
    buffer = io.BytesIO()
    torch.save(state, buffer)
    with atomic_write(path, "wb") as f:
        f.write(buffer.getvalue())


# --- training ------------------------------------------------------------------------------------------------


def train(
    data_dir: str | Path,
    out_dir: str | Path,
    epochs: int = 100,
    seed: int = 0,
    resume: bool = False,
    clusters: int = 64,
    lr: float = 1e-3,
    decay_every: int = 50,
    decay: float = 0.7,
    alpha: tuple[int, int] = ALPHA,
    beta: tuple[int, int] = BETA,
    limit: int | None = None,
    eval_every: int = 5,
    loss: str = "l1",
    tau: float = TAU,
    progress: bool = True,
    log: Log = print,
) -> dict:
    """Train the overlap head on the cached scenes of ``data_dir``; write checkpoints into ``out_dir``.

    ``resume``: continue from ``out_dir/last.pth`` (its settings must match) up to ``epochs`` in all.
    ``loss``: ``"l1"`` (the paper's), ``"listwise"`` or ``"pairwise"`` (see the module), ``tau`` the initial
    temperature of the latter two. The validation scenes are scored every ``eval_every`` epochs and after the
    last; ``best.pth`` is the best of those (lowest L1 with ``"l1"``, else highest Spearman ρ; without
    validation scenes, the lowest training loss).
    Returns a summary: epochs run, final training loss, best validation numbers and their epoch, the
    validation numbers of the per-scene codebook (``evaluate_codebook``, the reference), paths, seconds.
    """
    from tqdm import tqdm

    if epochs < 1:
        raise InputError(f"epochs must be at least 1, got {epochs}")
    if not (1 <= alpha[0] <= alpha[1] and 2 <= alpha[1] and 1 <= beta[0] <= beta[1]):
        raise InputError(f"bad alpha {alpha} / beta {beta} ranges")
    if loss not in LOSSES:
        raise InputError(f"unknown loss {loss!r} ({', '.join(LOSSES)})")
    if not (math.isfinite(tau) and tau > 0):
        raise InputError(f"tau must be positive and finite, got {tau}")
    if not (math.isfinite(lr) and lr > 0):  # torch's Adam refused a negative one mid-start, NaN it took
        raise InputError(f"lr must be positive and finite, got {lr}")
    if not 1 <= clusters <= MAX_CLUSTERS:
        raise InputError(
            f"clusters must be from 1 to {MAX_CLUSTERS:,} (NetVLAD's usual 64; each adds a block of the "
            f"global feature and of every batch's memory), got {clusters:,}"
        )
    started = time.perf_counter()
    torch.manual_seed(seed)
    scenes = load_cache(data_dir, limit)
    train_set, val_set = split(scenes)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    settings = {
        "data_dir": str(Path(data_dir).resolve()),
        "scenes": len(scenes),
        "seed": seed,
        "clusters": clusters,
        "lr": lr,
        "decay_every": decay_every,
        "decay": decay,
        "alpha": list(alpha),
        "beta": list(beta),
        "loss": loss,
    }
    if loss != "l1":
        settings["tau"] = tau
        if loss == "pairwise":
            settings["margin"] = MARGIN
    by_spearman = loss != "l1"  # which validation number picks best.pth

    last, best_path, head_path = out / "last.pth", out / "best.pth", out / "netvlad_fpfh.pth"
    if resume and last.exists():
        state = torch.load(last, map_location="cpu", weights_only=False)
        old = {"loss": "l1", **state["settings"]}  # runs from before the loss option were L1 runs
        mismatch = {k: (old.get(k), v) for k, v in settings.items() if k != "data_dir" and old.get(k) != v}
        if mismatch:
            raise InputError(f"cannot resume {last}: settings differ {mismatch}")
        model = NetVLAD(*state["network_state_dict"][PREFIX + "centroids"].shape)
        model.load_state_dict({k[len(PREFIX) :]: v for k, v in state["network_state_dict"].items()})
        history, start = state["history"], state["epoch"] + 1
        best = {"val_spearman": float("-inf"), "train_loss": float("inf"), **state["best"]}
        log_tau = torch.nn.Parameter(torch.tensor(float(state.get("log_tau", np.log(tau))), dtype=torch.float32))
    else:
        if resume:
            log(f"nothing to resume in {out}: starting afresh")
        model = init_head(train_set, clusters, seed)
        history, start = [], 0
        best = {"val_l1": float("inf"), "val_spearman": float("-inf"), "train_loss": float("inf"), "epoch": -1}
        log_tau = torch.nn.Parameter(torch.tensor(float(np.log(tau)), dtype=torch.float32))
        state = None
    params = list(model.parameters()) + ([log_tau] if loss != "l1" else [])
    optimizer = torch.optim.Adam(params, lr=lr)
    scheduler = torch.optim.lr_scheduler.StepLR(optimizer, step_size=decay_every, gamma=decay)
    if state is not None:
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
    reference = evaluate_codebook(val_set, seed) if val_set else {"l1": float("nan"), "spearman": float("nan")}
    if start == 0:
        v = evaluate(model, val_set, seed) if val_set else {"l1": float("nan"), "spearman": float("nan")}
        log(
            f"{len(train_set)} training + {len(val_set)} validation scenes, {loss} loss; initial (k-means "
            f"codebook of the training scenes) validation L1 {v['l1']:.4f}, Spearman {v['spearman']:.3f}; the "
            f"pipeline's per-scene codebook: Spearman {reference['spearman']:.3f}"
        )
        history.append(
            {"epoch": -1, "train_loss": float("nan"), "val_l1": v["l1"], "val_spearman": v["spearman"], "lr": lr}
        )

    bar = tqdm(range(start, epochs), total=epochs, initial=start, desc="train", unit="epoch", disable=not progress)
    for epoch in bar:
        rng = np.random.default_rng([seed, epoch])
        model.train()
        losses = []
        for k in rng.permutation(len(train_set)):
            x, target = sample_step(train_set[k], rng, alpha, beta)
            value = step_loss(model, x, target, loss, log_tau)
            optimizer.zero_grad()
            value.backward()
            optimizer.step()
            losses.append(float(value.detach()))
        scheduler.step()
        if val_set and (epoch % eval_every == eval_every - 1 or epoch == epochs - 1):
            v = evaluate(model, val_set, seed)
        elif val_set:
            v = {"l1": float("nan"), "spearman": float("nan")}  # not evaluated this epoch
        else:
            v = {"l1": float(np.mean(losses)) if loss == "l1" else float("nan"), "spearman": float("nan")}
        train_loss = float(np.mean(losses))
        history.append(
            {
                "epoch": epoch,
                "train_loss": train_loss,
                "val_l1": v["l1"],
                "val_spearman": v["spearman"],
                "lr": optimizer.param_groups[0]["lr"],
            }
            | ({"tau": float(torch.exp(log_tau.detach()))} if loss != "l1" else {})
        )
        meta = {
            **settings,
            "epoch": epoch,
            "train_loss": train_loss,
            "val_l1": v["l1"],
            "val_spearman": v["spearman"],
            "descriptor": "fpfh",
        }
        if not val_set and by_spearman:
            better = train_loss < best["train_loss"]
        elif by_spearman:
            better = v["spearman"] > best["val_spearman"]  # False for NaN (epochs not evaluated)
        else:
            better = v["l1"] < best["val_l1"]
        if better:
            best = {"val_l1": v["l1"], "val_spearman": v["spearman"], "train_loss": train_loss, "epoch": epoch}
            save_head(model, best_path, meta)
        _save(
            last,
            {
                "network_state_dict": head_state(model),
                "optimizer": optimizer.state_dict(),
                "scheduler": scheduler.state_dict(),
                "epoch": epoch,
                "history": history,
                "best": best,
                "settings": settings,
                "log_tau": float(log_tau.detach()),
            },
        )
        if np.isfinite(v["spearman"]):
            bar.set_postfix(train=f"{train_loss:.4f}", val=f"{v['l1']:.4f}", rho=f"{v['spearman']:.3f}")
        else:
            bar.set_postfix(train=f"{train_loss:.4f}")
    bar.close()

    if best_path.exists():
        best_state = torch.load(best_path, map_location="cpu", weights_only=False)
        with atomic_write(head_path, "wb") as f:
            buffer = io.BytesIO()
            torch.save(best_state, buffer)
            f.write(buffer.getvalue())
    with atomic_write(out / "history.json") as f:
        json.dump(
            {"settings": settings, "best": best, "history": history, "per_scene_codebook": reference}, f, indent=1
        )
    summary = {
        "epochs": epochs,
        "loss": loss,
        "final_train_loss": history[-1]["train_loss"],
        "final_val_l1": history[-1]["val_l1"],
        "final_val_spearman": history[-1]["val_spearman"],
        "best": best,
        "per_scene_codebook": reference,
        "head": str(head_path),
        "seconds": time.perf_counter() - started,
    }
    log(
        f"done: epoch {epochs}, training {loss} loss {summary['final_train_loss']:.4f}, validation L1 "
        f"{summary['final_val_l1']:.4f}, Spearman {summary['final_val_spearman']:.3f}; kept epoch {best['epoch']} "
        f"(validation L1 {best['val_l1']:.4f}, Spearman {best['val_spearman']:.3f}; the per-scene codebook: "
        f"{reference['spearman']:.3f}) -> {head_path}"
    )
    return summary


def train_command(
    data_dir: Path = typer.Argument(..., help="Cache of simulated scenes (python -m data_tools.simulate DATA_DIR)."),
    out: Path = typer.Option(Path("runs/overlap_head"), "--out", help="Checkpoints, history and netvlad_fpfh.pth."),
    epochs: int = typer.Option(100, help="Epochs (one step per training scene each)."),
    seed: int = typer.Option(0, help="Seed of the initial codebook and of every draw."),
    resume: bool = typer.Option(False, help="Continue from OUT/last.pth up to EPOCHS."),
    clusters: int = typer.Option(64, help="NetVLAD clusters."),
    lr: float = typer.Option(1e-3, help="Adam learning rate (x0.7 every 50 epochs)."),
    loss: str = typer.Option(
        "l1",
        help="l1 (the paper's: L1 between scores and GT overlaps; best.pth by "
        "validation L1), listwise (softmax KL, per scan) or pairwise (logistic, per scan); the "
        "last two keep the head with the best validation Spearman.",
    ),
    tau: float = typer.Option(TAU, help="Initial temperature of the listwise / pairwise loss (learned)."),
) -> None:
    """Train the NetVLAD overlap head on FPFH descriptors of simulated scenes (SGHR's recipe)."""
    try:
        train(
            data_dir,
            out,
            epochs=epochs,
            seed=seed,
            resume=resume,
            clusters=clusters,
            lr=lr,
            loss=loss,
            tau=tau,
            log=typer.echo,
        )
    except InputError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(2) from None
