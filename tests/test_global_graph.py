import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sghr_gtsam.features.netvlad import VladHead, global_features, kmeans_codebook, load_checkpoint
from sghr_gtsam.graph import gram32, overlap_scores, scores_from_gram, top_k_edges, top_k_graph


def test_authors_checkpoint_reproduces_their_overlap_scores(data_dir):
    ref = data_dir / "sghr-reference"
    model = load_checkpoint(str(ref / "netvlad_overlap_model_best.pth"))
    desc = [np.load(ref / "yoho" / f"cloud_bin_{i}.desc.npy") for i in range(6)]
    scores = overlap_scores(global_features(model, desc), form="authors")
    np.fill_diagonal(scores, 0.0)  # their file has zeros on the diagonal
    expected = np.loadtxt(ref / "multi_reg" / "overlap.txt")
    np.testing.assert_allclose(scores, expected, atol=1e-5)


@settings(max_examples=30, deadline=None)
@given(
    clusters=st.integers(1, 12),
    dim=st.integers(2, 40),
    points=st.integers(1, 300),
    alpha=st.floats(0.1, 200),
    scale=st.floats(1e-3, 1e3),
    seed=st.integers(0, 10_000),
)
def test_numpy_head_computes_what_the_trained_torch_layer_computes(clusters, dim, points, alpha, scale, seed):
    """The pipeline's numpy NetVLAD (no torch on a run) and training's torch layer are one function, before
    and after the torch parameters move away from the codebook initialisation."""
    import torch

    from sghr_gtsam.train import NetVLAD

    rng = np.random.default_rng(seed)
    head = VladHead.from_codebook(rng.normal(size=(clusters, dim)), alpha)
    model = NetVLAD.from_head(head)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.as_tensor(rng.normal(size=tuple(p.shape)), dtype=torch.float32))
    head = model.head()
    desc = scale * rng.normal(size=(points, dim))
    with torch.no_grad():
        expected = model(torch.as_tensor(desc.T, dtype=torch.float32)[None])[0].double().numpy()
    np.testing.assert_allclose(head(desc), expected, atol=2e-5)


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
    head = VladHead.from_codebook(kmeans_codebook(descs, clusters=16, seed=0))
    F = global_features(head, descs)
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


def _reference_top_k(S: np.ndarray, k: int) -> np.ndarray:
    """The definition: each row's k best columns by a stable sort (ties to the lower index), symmetric union."""
    n = len(S)
    kk = min(k, n - 1)
    D = np.asarray(S, dtype=float).copy()
    np.fill_diagonal(D, -np.inf)
    best = np.argsort(-D, axis=1, kind="stable")[:, :kk]
    return np.unique(np.sort(np.stack([np.repeat(np.arange(n), kk), best.ravel()], axis=1), axis=1), axis=0)


def _features(kind: str, n: int, d: int, rng: np.random.Generator) -> np.ndarray:
    """Unit features; ``grid`` and ``dups`` make many exactly equal scores (ties at the k-th place, clipping at ±1)."""
    if kind == "gauss":
        F = rng.normal(size=(n, d))
    elif kind == "grid":  # entries in {-1, 0, 1}: few distinct dot products, antipodal pairs clip at -1
        F = rng.integers(-1, 2, size=(n, d)).astype(float)
        F[~F.any(axis=1), 0] = 1.0
    else:  # a few distinct features, each repeated (the same scan read twice); duplicates score 1 after clipping
        base = rng.normal(size=(int(rng.integers(1, 4)), d))
        F = base[rng.integers(0, len(base), size=n)]
    return F / np.linalg.norm(F, axis=1, keepdims=True)


@settings(max_examples=80, deadline=None)
@given(
    n=st.integers(2, 60),
    k=st.integers(1, 12),
    d=st.integers(1, 6),
    form=st.sampled_from(["paper", "authors"]),
    kind=st.sampled_from(["gauss", "grid", "dups"]),
    seed=st.integers(0, 10_000),
)
def test_fast_top_k_graph_matches_the_reference_on_the_float32_scores(n, k, d, form, kind, seed):
    """``top_k_graph`` (float32 Gram, torch.topk candidates, exact fallback for spilling ties) chooses exactly the
    reference's edges on ``overlap_scores`` — the float64 scores of the same float32 Gram values — ties included."""
    F = _features(kind, n, d, np.random.default_rng(seed))
    S = overlap_scores(F, form)
    expected = _reference_top_k(S, k)
    edges, s = top_k_graph(F, k, form)
    np.testing.assert_array_equal(edges, expected)
    np.testing.assert_array_equal(s, S[expected[:, 0], expected[:, 1]])
    np.testing.assert_array_equal(top_k_edges(S, k), expected)
    np.testing.assert_array_equal(top_k_edges(S.astype(np.float32), k), _reference_top_k(S.astype(np.float32), k))


def test_top_k_graph_full_scores_and_gram_are_consistent():
    rng = np.random.default_rng(1)
    F = rng.normal(size=(300, 40))
    F /= np.linalg.norm(F, axis=1, keepdims=True)
    G = gram32(F)
    assert G.dtype == np.float32 and np.array_equal(G, G.T)
    np.testing.assert_allclose(G, F @ F.T, atol=1e-6)
    for form in ("paper", "authors"):
        edges, s, S = top_k_graph(F, 7, form, full_scores=True)
        np.testing.assert_array_equal(S, overlap_scores(F, form))
        np.testing.assert_array_equal(S, scores_from_gram(G, form))
        np.testing.assert_array_equal(edges, _reference_top_k(S, 7))
        np.testing.assert_array_equal(s, S[edges[:, 0], edges[:, 1]])
    np.testing.assert_allclose(overlap_scores(F), (F @ F.T + 1) / 2, atol=1e-6)


def test_top_k_with_many_rows_of_ties_uses_the_exact_path_in_chunks():
    """1100 scans from 3 distinct features: every row's k-th place is a tie spilling past the candidates."""
    rng = np.random.default_rng(2)
    base = rng.normal(size=(3, 16))
    F = base[rng.integers(0, 3, size=1100)]
    F /= np.linalg.norm(F, axis=1, keepdims=True)
    S = overlap_scores(F)
    edges, _ = top_k_graph(F, 10)
    np.testing.assert_array_equal(edges, _reference_top_k(S, 10))
    levels = rng.integers(0, 2, size=(700, 700))
    np.testing.assert_array_equal(top_k_edges(levels, 5), _reference_top_k(levels, 5))  # integer scores


def test_top_k_small_and_degenerate_inputs():
    F = np.eye(3)
    assert top_k_graph(F[:1], 5)[0].shape == (0, 2) and top_k_edges(np.ones((1, 1)), 3).shape == (0, 2)
    assert top_k_edges(np.ones((4, 4)), 0).shape == (0, 2)
    edges, s = top_k_graph(F, 10)  # k above N - 1: the complete graph
    np.testing.assert_array_equal(edges, [[0, 1], [0, 2], [1, 2]])
    np.testing.assert_array_equal(s, [0.5, 0.5, 0.5])
    S = overlap_scores(F)
    S.setflags(write=False)
    np.testing.assert_array_equal(top_k_edges(S, 1), _reference_top_k(S, 1))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10**6), n=st.integers(2, 30), k=st.integers(1, 3), rooms=st.integers(1, 4))
def test_bridged_top_k_graph_is_connected_with_one_bridge_per_extra_part(seed, n, k, rooms):
    """Scans in ``rooms`` groups that score high only within their group: the top-k union can split; the
    bridges join every part with exactly parts − 1 new pairs, each the best-scoring pair between two parts
    not yet joined when it was added (Kruskal order)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from sghr_gtsam.graph import bridge_components

    rng = np.random.default_rng(seed)
    room = rng.integers(0, rooms, n)
    S = rng.uniform(0.0, 0.3, (n, n)) + 0.6 * (room[:, None] == room[None, :])
    S = np.triu(S, 1) + np.triu(S, 1).T + np.eye(n)
    edges = top_k_edges(S, k)

    def parts(e):
        return connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)

    before, label = parts(edges)
    out = bridge_components(edges, S)
    np.testing.assert_array_equal(out[: len(edges)], edges)
    assert len(out) - len(edges) == before - 1
    assert parts(out)[0] == 1
    added = out[len(edges) :]
    assert np.all(added[:, 0] < added[:, 1]) and np.all(label[added[:, 0]] != label[added[:, 1]])
    if len(added):  # the first bridge is the best-scoring pair between any two parts
        a, b = np.triu_indices(n, 1)
        cross = label[a] != label[b]
        assert S[added[0, 0], added[0, 1]] == S[a[cross], b[cross]].max()
