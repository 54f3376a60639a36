"""The one configuration object shared by the CLI and the Python API, with documented defaults."""

from __future__ import annotations

import importlib.util
import json
import math
import re
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from sghr_gtsam.types import InputError

MATCHERS = ("sc2", "kiss", "ransac")
"""Pairwise estimators (``registration.pairwise.register_pair``)."""
NOISE_MODELS = ("information", "isotropic")
"""Edge noise models of the gtsam graph (``gtsam_api.noise_model``)."""
KERNELS = ("none", "huber", "cauchy", "tls")
"""Robust kernels of the gtsam graph (``gtsam_api``)."""


MIN_INLIERS = {"fpfh": 14, "learned": 35}
"""``Config.min_inliers`` by descriptor (given descriptors use FPFH's): the most inliers a registration may be asked
for while at most 5 % of right registrations fall short, on 60 held-out simulated rooms
(``benchmarks/bench_learned_descriptor.py calibrate``; pairs of GT overlap > 0.1). The bar tests "this registration
is right": a right one it drops is lost to the pose graph, while the wrong ones it admits (there 17 % for FPFH, 14 %
for the learned descriptor; alike objects and repeated structure) are what synchronization's cycle consistency
rejects. Resampling the rooms moves it within 12-17 (FPFH) and 27-45: the calibration fixes it no closer."""
DESCRIPTORS = tuple(MIN_INLIERS)
"""Local descriptors (``features.local.compute_features``)."""

_TYPES = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}


def _check_type(name: str, annotation: str, value: object) -> None:
    """``InputError`` naming the key unless ``value`` has the field's type (``"float | None"`` and the like; an int
    is a float, a bool is no number)."""
    kinds = [kind.strip() for kind in annotation.split("|")]
    if value is None and "None" in kinds:
        return
    allowed = tuple(t for kind in kinds for t in _TYPES.get(kind, ()))
    if not isinstance(value, allowed) or (isinstance(value, bool) and bool not in allowed):
        wanted = " or ".join(k if k != "None" else "null" for k in kinds)
        raise InputError(f"{name} must be {wanted}; got {value!r} ({type(value).__name__})")


def _check_ray(address: str) -> None:
    if address not in ("local", "auto") and not re.fullmatch(r"(ray://)?[\w.-]+:\d+", address):
        raise InputError(f"ray must be local, auto, host:port or ray://host:port; got {address!r}")
    if importlib.util.find_spec("ray") is None:
        raise InputError("ray is not installed: pip install 'sghr_gtsam[ray]' (in a checkout: pip install -e '.[ray]')")


@dataclass
class Config:
    # --- scans and local features -------------------------------------------------------------
    voxel: float | None = None
    """Voxel size in scene units. None: derived from the scene as 1/100 of the median scan's
    bounding-box diagonal (4.2 cm on 3DMatch fragments, 2.5 mm on an object's range scans: where the
    pairwise benchmark got the most pairs right on both)."""
    min_points: int = 100
    """A scan with fewer finite points (after loading) is skipped and reported."""
    normal_radius: float = 2.0
    """Normal-estimation radius, in voxels."""
    fpfh_radius: float = 5.0
    """FPFH feature radius, in voxels."""
    descriptor: str = "fpfh"
    """Local descriptor that pairs are matched on: 'fpfh' (open3d's FPFH of the voxel grid) or 'learned' (a
    network trained on simulated rooms, ``features.learned``). The learned one registers more gt.log pairs right
    on every 3DMatch test scene, and gives better whole models on two of them but worse ones on two others, in twice
    the time (the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md).
    The top-k graph is built on FPFH either way."""
    features: str | None = None
    """Folder of precomputed local features, per scan ``<stem>.kpts.npy`` (K×3 keypoints in the scan's
    frame) and ``<stem>.desc.npy`` (K×D descriptors), in the folder or any sub-folder (the SGHR authors'
    ``kpts/`` + ``yoho/`` layout works as it is). They replace FPFH for matching and for the global
    feature; a scan without them is skipped and reported. None: FPFH on the voxel grid."""

    # --- sparse pose graph ---------------------------------------------------------------------
    k: int = 10
    """Top-k partners per scan by overlap score (the paper: 10 indoor, 6 outdoor)."""
    connect: bool = True
    """Join the parts of the top-k graph by their best-scoring pairs (``graph.bridge_components``): with a
    small k the union of top-k choices can split the scans into parts that could never be placed together
    (nine 3DMatch fragments at k = 2 with the learned head: two parts of four scans). False: the paper's graph as is."""
    global_feature: str = "vlad"
    """Global feature: 'vlad' (NetVLAD initialised from a k-means codebook of this scene's descriptors)
    or 'learned' (a trained NetVLAD head, ``overlap_head``). 'vlad' is the default because it ranks
    overlaps better on 3DMatch fragments and an object's range scans than the shipped FPFH head
    (``benchmarks/bench_overlap.py``; the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""
    overlap_head: str | None = None
    """Checkpoint of a trained NetVLAD head (ours, or the SGHR authors' ``netvlad_overlap_model_best.pth``
    for their 32-d YOHO descriptors); given, it scores the overlaps whatever ``global_feature`` says. Its
    descriptor dimension must match the scans' descriptors. None: 'learned' uses the head shipped in
    sghr_gtsam/weights (33-d FPFH, trained on simulated scans)."""

    # --- pairwise registration ---------------------------------------------------------------------
    matcher: str = "sc2"
    """Robust estimator on mutual-nearest-neighbour matches: 'sc2' (second-order spatial compatibility,
    ``registration.estimators``), 'kiss' (kiss-matcher) or 'ransac' (open3d). 'sc2' gets the most pairs
    right on the 3DMatch scenes at about the same cost
    (the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""
    icp_distance: float = 1.5
    """ICP correspondence distance, in voxels."""
    min_inliers: int | None = None
    """A pair whose final transform agrees with fewer descriptor matches than this counts as not
    registered (initial weight 0). None: the descriptor's own bar (``MIN_INLIERS``; ``inlier_bar``)."""

    # --- after the first synchronization (registration.densify) ------------------------------------
    refine: bool = True
    """Re-register every kept edge by multi-scale GICP (v, v/2, v/4) from the synchronized relative pose."""
    loops: bool = True
    """Register the pairs never tried that overlap under the synchronized poses (loop closures)."""
    retry: bool = True
    """Give scans left unregistered, unverified or on fewer than 2 kept edges global registration against
    their next k candidates by overlap score: once a run for a scan placed in the largest part, every round for one
    left outside it."""
    groups: bool = False
    """Register each group of unverified scans (held together by its own kept edges), merged, onto the merged
    verified rest, and the pairs that placement makes overlap by ICP from it (``registration.groups``)."""
    max_sigma: float | None = None
    """The largest σ (scene units) of a scan's points along a direction only its registrations' overlap bounds (a
    plane, a corridor) for which it is not doubted as loose (``verify.Verification``); None: the consistency test's
    translation tolerance (0.10-0.14 m on the 3DMatch scenes at hand)."""
    free_space: bool = True
    """Give weight 0 to registrations that put one scan's surfaces in the space the other saw empty
    (``registration.visibility``; only scans seen from their frame's origin can be checked), and to those that hold
    a group of scans where the scans' free space rules it out (``registration.overrule``), then synchronize again."""
    rounds: int = 2
    """At most this many rounds of refine / loops / retry / groups, each followed by synchronization; a round that
    changes nothing ends them."""

    # --- synchronization -----------------------------------------------------------------------------
    iters: int = 50
    """IRLS iterations M with history reweighting."""
    method: str = "history"
    """Synchronization method (see ``sghr_gtsam.sync.METHODS``)."""
    reweight: str = "authors"
    """History-reweighting units: 'authors' (residual in degrees, factor 2, as the authors' code; drops
    outliers) or 'paper' (residual in radians as the paper writes it; too weak to reject outliers)."""
    polish: str = "loops"
    """After IRLS (``sghr_gtsam.sync.POLISHES``): 'loops' (scans grown from the most consistent core and
    the IRLS poses, each re-placed by groups and scans by counted loop evidence, the better kept, then
    Levenberg-Marquardt on the consistent edges: best on the robustness benchmark, ``sync.cycles``),
    'robust' (consensus re-placement, gtsam GNC, consensus, LM), 'lm' (Levenberg-Marquardt on the edges
    IRLS kept) or 'none'."""
    initial_weight: str = "s*r"
    """Initial edge weight w⁰: 's*r' (overlap score × inlier count, SGHR) or the paper's ablations 's'
    (score only) and 'r' (inlier count only)."""
    min_weight: float = 1e-3
    """An edge is dropped once the history reweighting has scaled it below this fraction of its initial weight; a
    scan left without edges is reported as unregistered. Initial weights are never cut: a right registration of a
    thin overlap weighs little but still agrees with the loops (cutting edges under 1e-3 of the largest initial
    weight cost 0.03 of all-pairs recall at 60 % random outliers:
    the journal at 18b90a6: git show 18b90a6:docs/BENCHMARKS.md)."""

    # --- gtsam graph (sghr_gtsam.gtsam_api, the incremental session, ``sync``'s final LM) ---------------
    noise_model: str = "information"
    """Noise of an edge's factor: 'information' (its own, calibrated from the registration's residuals) or
    'isotropic' (SE-Sync's precisions 2κ, τ from it)."""
    kernel: str = "none"
    """Robust kernel on the edges' factors: 'none', 'huber', 'cauchy' (m-estimators at the χ²₆ 99 % residual)
    or 'tls' (truncated least squares through gtsam GNC)."""

    # --- run ----------------------------------------------------------------------------------------
    seed: int = 0
    workers: int | None = None
    """Processes for local features, pairwise registration, refinement grids, refinement and loop closure
    (``sghr_gtsam.executor``); None: every core. Results do not depend on it."""
    ray: str | None = None
    """Run those stages on a Ray cluster instead (``sghr_gtsam.executor_ray``; the optional extra ``ray``):
    'local' (a Ray instance started on this machine with ``workers`` CPUs), 'auto' (the cluster this machine
    belongs to), 'host:port' or 'ray://host:port' (a cluster's head); on ``workers`` of its CPUs (None: all).
    None: the local processes. Results do not depend on it."""
    record: bool = True
    """Write recording.rrd (rerun)."""
    cache: bool = True
    """Keep features, refinement grids and pair registrations in ``OUT/cache`` as they are computed, keyed by the
    scans' content and every parameter that made them, and reuse them: a run stopped in the middle and started
    again redoes only what is missing (``sghr_gtsam.cache``). False: neither read nor written (the run keeps its
    features and grids in a temporary folder beside ``OUT`` while it runs: ``sghr_gtsam.store``)."""

    def validate(self) -> Config:
        """Raise ``InputError`` (one line) for a value no stage accepts, before any work is done."""
        from sghr_gtsam.sync import MAX_ITERS, METHODS, POLISHES
        from sghr_gtsam.sync.irls import REWEIGHTS

        choices = {
            "descriptor": DESCRIPTORS,
            "global_feature": ("vlad", "learned"),
            "matcher": MATCHERS,
            "method": tuple(METHODS),
            "polish": tuple(POLISHES),
            "reweight": REWEIGHTS,
            "initial_weight": ("s*r", "s", "r"),
            "noise_model": NOISE_MODELS,
            "kernel": KERNELS,
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise InputError(f"{name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, (np.integer, np.floating, np.bool_)):  # numpy's scalars as Python's: to_json
                setattr(self, f.name, value := value.item())
            _check_type(f.name, f.type, value)
        for name in ("k", "iters", "min_points", "rounds"):
            if getattr(self, name) < 1:
                raise InputError(f"{name} must be a positive integer; got {getattr(self, name)!r}")
        if self.iters > MAX_ITERS:
            raise InputError(f"iters must be an integer from 1 to {MAX_ITERS:,}; got {self.iters:,}")
        if self.features is not None and not str(self.features).strip():  # Path("") is the current folder
            raise InputError("features must name a folder; got an empty path")
        if self.workers is not None and self.workers < 1:
            raise InputError(f"workers must be a positive integer; got {self.workers!r}")
        if self.ray is not None:
            _check_ray(self.ray)
        for name in ("voxel", "normal_radius", "fpfh_radius", "icp_distance", "max_sigma"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise InputError(f"{name} must be a positive finite number; got {value!r}")
        if self.overlap_head is not None and not Path(self.overlap_head).is_file():  # before hours of features
            raise InputError(f"overlap head {self.overlap_head} is not a file")
        if self.features is not None and self.descriptor != "fpfh":
            raise InputError(
                f"descriptor {self.descriptor!r} describes the voxel grid, and --features gives the "
                "descriptors to match: choose one"
            )
        if self.inlier_bar < 0:
            raise InputError(f"min_inliers must be a non-negative integer; got {self.min_inliers!r}")
        if not 0 <= self.seed < 2**31:  # open3d's RANSAC takes a C int
            raise InputError(f"seed must be an integer in [0, 2^31); got {self.seed!r}")
        if not 0 <= self.min_weight < 1:
            raise InputError(f"min_weight must be a fraction in [0, 1); got {self.min_weight!r}")
        return self

    def __setattr__(self, name: str, value: object) -> None:
        # A misspelt setting (``cfg.voxle = 0.1``) was kept as a new attribute and silently ignored.
        if name not in self.__dataclass_fields__:
            raise AttributeError(f"Config has no setting {name!r}")
        super().__setattr__(name, value)

    @property
    def inlier_bar(self) -> int:
        """``min_inliers``, or the descriptor's own bar when it is None (``MIN_INLIERS``)."""
        return MIN_INLIERS[self.descriptor] if self.min_inliers is None else self.min_inliers

    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2)

    @classmethod
    def from_json(cls, path: str | Path) -> Config:
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as e:  # ValueError: also a 5000-digit int
            raise InputError(f"cannot read config {path}: {e}") from None
        if not isinstance(data, dict):
            raise InputError(f"config {path} must hold a JSON object")
        unknown = set(data) - {f.name for f in fields(cls)}
        if unknown:
            raise InputError(f"config {path}: unknown keys {sorted(unknown)}")
        return cls(**data)
