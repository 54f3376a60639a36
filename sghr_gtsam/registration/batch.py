"""Global registration of many pairs at once, over the executor's processes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from sghr_gtsam.cache import Cache, pair_key
from sghr_gtsam.config import Config
from sghr_gtsam.registration.pairwise import PAIRS, PairResult, register_pair
from sghr_gtsam.store import Stored, pair_map


def _register(shared: tuple[Stored, float, Config], pair: tuple[int, int]) -> PairResult:
    features, voxel, config = shared
    a, b = pair
    return register_pair(
        features[a],
        features[b],
        voxel,
        matcher=config.matcher,
        icp_distance=config.icp_distance,
        seed=config.seed,
        min_inliers=config.inlier_bar,
    )


def register_edges(
    features: Stored,
    edges: np.ndarray,
    voxel: float,
    config: Config,
    on_result: Callable[[int, PairResult], None] | None = None,
    cache: Cache | None = None,
) -> list[PairResult]:
    """``register_pair`` on every (i, j) row of ``edges`` of the scans' stored ``features``, over the executor's
    processes (``config.workers``, ``config.ray``); ``on_result`` as in ``parallel_map`` (progress); ``cache``:
    results stored as they arrive and reused (``cache.Cache``)."""
    pairs = [(int(a), int(b)) for a, b in edges]
    keys = [pair_key(features.keys[a], features.keys[b], config) for a, b in pairs]
    return pair_map(
        cache, PAIRS, _register, (features, voxel, config), edges, pairs, keys, config.workers, on_result, config.ray
    )
