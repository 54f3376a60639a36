import numpy as np
from hypothesis import given, settings, strategies as st

from sghr_gtsam.features.netvlad import NetVLAD, global_features, kmeans_codebook, load_checkpoint
from sghr_gtsam.graph import overlap_scores, top_k_edges


def test_authors_checkpoint_reproduces_their_overlap_scores(data_dir):
    ref = data_dir / "sghr-reference"
    model = load_checkpoint(str(ref / "netvlad_overlap_model_best.pth"))
    desc = [np.load(ref / "yoho" / f"cloud_bin_{i}.desc.npy") for i in range(6)]
    scores = overlap_scores(global_features(model, desc), form="authors")
    np.fill_diagonal(scores, 0.0)  # their file has zeros on the diagonal
    expected = np.loadtxt(ref / "multi_reg" / "overlap.txt")
    np.testing.assert_allclose(scores, expected, atol=1e-5)


@settings(max_examples=50, deadline=None)
@given(n=st.integers(2, 40), k=st.integers(1, 12), seed=st.integers(0, 10_000))
def test_top_k_graph_keeps_each_scans_best_partners(n, k, seed):
    rng = np.random.default_rng(seed)
    F = rng.normal(size=(n, 8))
    F /= np.linalg.norm(F, axis=1, keepdims=True)
    S = overlap_scores(F)
    edges = top_k_edges(S, k)
    kk = min(k, n - 1)
    assert np.all(edges[:, 0] < edges[:, 1])
    assert len(np.unique(edges, axis=0)) == len(edges)
    assert n * kk / 2 <= len(edges) <= min(n * kk, n * (n - 1) // 2)
    chosen = set(map(tuple, edges))
    for i in range(n):
        others = np.delete(np.arange(n), i)
        best = others[np.argsort(-S[i, others], kind="stable")[:kk]]
        assert all(tuple(sorted((i, j))) in chosen for j in best)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_score_forms_agree_on_ranking_and_range(seed):
    rng = np.random.default_rng(seed)
    F = rng.normal(size=(12, 16))
    F /= np.linalg.norm(F, axis=1, keepdims=True)
    a, b = overlap_scores(F, "paper"), overlap_scores(F, "authors")
    assert np.all((a >= 0) & (a <= 1)) and np.all((b >= 0) & (b <= 1))
    iu = np.triu_indices(12, 1)
    assert np.array_equal(np.argsort(a[iu], kind="stable"), np.argsort(b[iu], kind="stable"))


def test_netvlad_feature_is_unit_and_scores_like_scans_higher():
    rng = np.random.default_rng(0)
    base = [rng.normal(size=(800, 33)) + rng.normal(scale=3, size=(1, 33)) for _ in range(3)]
    # scan 3 resamples the points of scan 0: its feature must be closest to scan 0's
    descs = base + [base[0][rng.permutation(800)[:600]] + 0.01 * rng.normal(size=(600, 33))]
    model = NetVLAD.from_codebook(kmeans_codebook(descs, clusters=16, seed=0))
    F = global_features(model, descs)
    np.testing.assert_allclose(np.linalg.norm(F, axis=1), 1.0, atol=1e-5)
    S = overlap_scores(F)
    assert np.argmax(np.where(np.eye(4, dtype=bool), -1, S)[3]) == 0


@settings(max_examples=30, deadline=None)
@given(n=st.integers(2, 30), k=st.integers(1, 8), levels=st.integers(1, 4), seed=st.integers(0, 10_000))
def test_top_k_graph_breaks_ties_like_a_stable_sort(n, k, levels, seed):
    """Scores with few distinct values (many ties at the k-th place) give the stable-sort choice."""
    rng = np.random.default_rng(seed)
    S = rng.integers(0, levels, size=(n, n)).astype(float)
    S = (S + S.T) / 2
    kk = min(k, n - 1)
    D = S.copy()
    np.fill_diagonal(D, -np.inf)
    best = np.argsort(-D, axis=1, kind="stable")[:, :kk]
    expected = np.unique(np.sort(np.stack([np.repeat(np.arange(n), kk), best.ravel()], axis=1), axis=1), axis=0)
    np.testing.assert_array_equal(top_k_edges(S, k), expected)
