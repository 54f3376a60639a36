"""The merged cloud's streamed voxel means equal the means computed at once, however the points arrive."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sghr_gtsam import merged


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(1, 400), min_size=1, max_size=6), st.integers(5, 300))
def test_streamed_voxel_means_are_the_means_of_the_cells(seed, batches, batch_size):
    rng = np.random.default_rng(seed)
    voxel = 0.1
    parts = [rng.uniform(-0.5, 0.5, (n, 3)) for n in batches]
    original = merged._VoxelMeans._BATCH
    merged._VoxelMeans._BATCH = batch_size  # merges happen between and inside the parts
    try:
        means = merged._VoxelMeans(voxel)
        for part in parts:
            means.add(part)
        got = means.points()
    finally:
        merged._VoxelMeans._BATCH = original
    P = np.concatenate(parts)
    cells, inverse = np.unique(np.floor(P / voxel).astype(np.int64), axis=0, return_inverse=True)
    want = np.zeros((len(cells), 3))
    np.add.at(want, inverse.ravel(), P)
    want /= np.bincount(inverse.ravel())[:, None]
    order = np.lexsort(want.T[::-1])
    np.testing.assert_allclose(got[np.lexsort(got.T[::-1])], want[order], atol=1e-12)
