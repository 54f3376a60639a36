"""Overlap-head training: it learns on a simulated scene, resumes exactly, saves and reloads exactly, and the
shipped head loads and gives unit features; the ranking losses learn, keep the head with the best validation
Spearman, and have the invariances they claim."""

import shutil

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from data_tools.simulate import make_training_scene, scene_descriptors
from sghr_gtsam.features.netvlad import DEFAULT_HEAD, global_features, load_checkpoint, load_default_head
from sghr_gtsam.graph import overlap_scores
from sghr_gtsam.train import (
    cache_path,
    evaluate,
    evaluate_codebook,
    init_head,
    listwise_loss,
    load_cache,
    pair_loss,
    pairwise_loss,
    sample_step,
    save_head,
    step_loss,
    train,
    write_cache_scene,
)
from sghr_gtsam.types import InputError


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One tiny simulated object scene (8 scans), its FPFH and GT overlaps, cached as training reads it."""
    folder = tmp_path_factory.mktemp("cache")
    scene = make_training_scene("object", 8, seed=[7, 0])
    iu = np.triu_indices(8, 1)
    assert scene.overlap[iu].min() < 0.3 < scene.overlap[iu].max()  # low and high overlaps both present
    write_cache_scene(
        cache_path(folder, 0),
        scene_descriptors(scene),
        scene.overlap,
        poses=scene.poses,
        voxel=scene.voxel,
        kind=scene.kind,
    )
    return folder


def test_per_scene_codebook_reference_ranks_overlaps(cache):
    """The reference a trained head is held against (logged by ``train``): the pipeline's default feature,
    a codebook of the scene's own descriptors, scored like a head on the same scene."""
    scenes = load_cache(cache)
    reference = evaluate_codebook(scenes)
    assert reference["spearman"] > 0.5, reference
    assert reference == evaluate_codebook(scenes)  # seeded


def test_training_lowers_the_loss_and_resumes_exactly(cache, tmp_path):
    scenes = load_cache(cache)
    assert len(scenes) == 1 and len(scenes[0].descriptors) == 8
    before = evaluate(init_head(scenes, clusters=16, seed=0), scenes)["l1"]
    kwargs = dict(seed=0, clusters=16, alpha=(8, 8), beta=(1024, 2048), progress=False, log=lambda _: None)
    summary = train(cache, tmp_path / "a", epochs=8, **kwargs)
    after = evaluate(load_checkpoint(summary["head"]), scenes)["l1"]
    assert after < before - 0.02, (before, after)

    # Interrupted after 5 epochs and resumed: the same weights as the uninterrupted run.
    train(cache, tmp_path / "b", epochs=5, **kwargs)
    train(cache, tmp_path / "b", epochs=8, resume=True, **kwargs)
    a = torch.load(tmp_path / "a" / "last.pth", weights_only=False)["network_state_dict"]
    b = torch.load(tmp_path / "b" / "last.pth", weights_only=False)["network_state_dict"]
    assert a.keys() == b.keys()
    for key in a:
        torch.testing.assert_close(a[key], b[key], rtol=0, atol=0)


def test_one_step_is_the_l1_between_scores_and_overlaps(cache):
    scene = load_cache(cache)[0]
    x, target = sample_step(scene, np.random.default_rng(0), alpha=(8, 8), beta=(1024, 1024))
    assert tuple(x.shape) == (8, 33, 1024) and tuple(target.shape) == (8, 8)
    model = init_head([scene], clusters=8, seed=0)
    with torch.no_grad():
        loss = float(pair_loss(model, x, target))
        F = model(x).numpy().astype(np.float64)
    S = overlap_scores(F)
    iu = np.triu_indices(8, 1)
    assert loss == pytest.approx(np.abs(S[iu] - target.numpy()[iu]).mean(), abs=1e-5)


def test_saved_and_reloaded_head_gives_identical_scores(cache, tmp_path):
    scene = load_cache(cache)[0]
    model = init_head([scene], clusters=16, seed=3)
    with torch.no_grad():  # move it off the codebook initialisation
        model.conv.bias.add_(torch.linspace(-1, 1, 16))
    save_head(model, tmp_path / "head.pth", {"note": "test"})
    again = load_checkpoint(str(tmp_path / "head.pth"))
    a = overlap_scores(global_features(model.head(), scene.descriptors))
    b = overlap_scores(global_features(again, scene.descriptors))
    np.testing.assert_array_equal(a, b)


def test_shipped_head_loads_and_gives_unit_features(cache):
    assert DEFAULT_HEAD.is_file() and DEFAULT_HEAD.stat().st_size < 1_000_000
    head = load_default_head()
    assert tuple(head.centroids.shape) == (64, 33)  # FPFH
    scene = load_cache(cache)[0]
    F = global_features(head, scene.descriptors)
    assert F.shape == (8, 64 * 33) and np.isfinite(F).all()
    np.testing.assert_allclose(np.linalg.norm(F, axis=1), 1.0, atol=1e-5)
    meta = torch.load(DEFAULT_HEAD, map_location="cpu", weights_only=False)["meta"]
    assert meta["descriptor"] == "fpfh"


# --- the ranking losses --------------------------------------------------------------------------------------


@pytest.mark.parametrize("loss", ["listwise", "pairwise"])
def test_a_few_steps_of_a_ranking_loss_lower_it(cache, loss):
    scene = load_cache(cache)[0]
    x, target = sample_step(scene, np.random.default_rng(0), alpha=(8, 8), beta=(1024, 1024))
    torch.manual_seed(0)
    model = init_head([scene], clusters=16, seed=0)
    log_tau = torch.nn.Parameter(torch.tensor(np.log(0.05), dtype=torch.float32))
    optimizer = torch.optim.Adam([*model.parameters(), log_tau], lr=1e-3)
    values = []
    for _ in range(6):
        value = step_loss(model, x, target, loss, log_tau)
        optimizer.zero_grad()
        value.backward()
        optimizer.step()
        values.append(float(value.detach()))
    with torch.no_grad():
        values.append(float(step_loss(model, x, target, loss, log_tau)))
    assert np.isfinite(values).all() and values[-1] < 0.95 * values[0], values


def test_pairwise_training_keeps_the_best_validation_spearman_and_resumes_exactly(cache, tmp_path):
    # Two copies of the scene: the second is held out for validation (only the mechanics are tested here).
    folder = tmp_path / "cache"
    folder.mkdir()
    for k in range(2):
        shutil.copy(cache_path(cache, 0), cache_path(folder, k))
    kwargs = dict(
        seed=0,
        clusters=16,
        alpha=(8, 8),
        beta=(1024, 2048),
        eval_every=1,
        loss="pairwise",
        progress=False,
        log=lambda _: None,
    )
    summary = train(folder, tmp_path / "a", epochs=4, **kwargs)
    history = torch.load(tmp_path / "a" / "last.pth", weights_only=False)["history"]
    rho = [h["val_spearman"] for h in history if h["epoch"] >= 0]
    assert all(np.isfinite(rho)) and summary["best"]["epoch"] == int(np.argmax(rho))
    meta = torch.load(summary["head"], weights_only=False)["meta"]
    assert meta["loss"] == "pairwise" and meta["val_spearman"] == max(rho)
    # The kept head gives the validation Spearman it was kept for.
    assert evaluate(load_checkpoint(summary["head"]), load_cache(folder)[1:])["spearman"] == pytest.approx(max(rho))

    train(folder, tmp_path / "b", epochs=2, **kwargs)
    train(folder, tmp_path / "b", epochs=4, resume=True, **kwargs)
    a = torch.load(tmp_path / "a" / "last.pth", weights_only=False)
    b = torch.load(tmp_path / "b" / "last.pth", weights_only=False)
    assert a["log_tau"] == b["log_tau"] != np.log(0.05)  # the temperature is learned and resumed too
    for key in a["network_state_dict"]:
        torch.testing.assert_close(a["network_state_dict"][key], b["network_state_dict"][key], rtol=0, atol=0)
    with pytest.raises(InputError, match="settings differ"):  # another loss cannot continue this run
        train(folder, tmp_path / "b", epochs=5, resume=True, **{**kwargs, "loss": "listwise"})
    with pytest.raises(InputError, match="unknown loss"):
        train(folder, tmp_path / "c", epochs=1, **{**kwargs, "loss": "hinge"})


def _symmetric(draw, n, values):
    M = np.zeros((n, n))
    iu = np.triu_indices(n, 1)
    M[iu] = draw(st.lists(values, min_size=len(iu[0]), max_size=len(iu[0])))
    M = M + M.T
    np.fill_diagonal(M, 1.0)
    return M


@st.composite
def scenes(draw):
    """A symmetric GT overlap matrix on a 1/32 grid (so shifts by multiples of 1/32 are exact) and cosines."""
    n = draw(st.integers(3, 9))
    overlap = _symmetric(draw, n, st.integers(0, 24).map(lambda k: k / 32))
    cosines = _symmetric(draw, n, st.floats(-1, 1, allow_nan=False))
    return torch.tensor(overlap), torch.tensor(cosines)


@settings(max_examples=60, deadline=None)
@given(scenes(), st.integers(-8, 8).map(lambda m: m / 32), st.floats(-0.5, 0.5), st.floats(np.log(0.01), 0.0))
def test_pairwise_loss_sees_only_the_order_of_the_overlaps(scene, shift, cos_shift, log_tau):
    overlap, C = scene
    loss = float(pairwise_loss(C, overlap, log_tau))
    # Invariant to a common shift of the GT overlaps (exact on this grid: the same pairs are > 0.05 apart) ...
    assert float(pairwise_loss(C, overlap + shift, log_tau)) == loss
    # ... and to a common shift of the cosines (the top-k graph is too).
    assert float(pairwise_loss(C + cos_shift, overlap, log_tau)) == pytest.approx(loss, rel=1e-9, abs=1e-12)
    # Cosines ordered as the overlaps beat cosines ordered against them, whenever some pair is ordered.
    partner = ~torch.eye(len(C), dtype=torch.bool)
    gaps = (overlap[:, :, None] - overlap[:, None, :] > 0.05) & partner[:, :, None] & partner[:, None, :]
    if gaps.any():
        assert float(pairwise_loss(overlap, overlap, log_tau)) < float(pairwise_loss(-overlap, overlap, log_tau))
    else:
        assert loss == 0.0


@settings(max_examples=60, deadline=None)
@given(scenes(), st.floats(0.1, 10.0), st.floats(np.log(0.01), 0.0))
def test_listwise_loss_is_a_kl_divergence_blind_to_overlap_scale(scene, scale, log_tau):
    overlap, C = scene
    loss = float(listwise_loss(C, overlap, log_tau))
    assert loss >= -1e-12
    # Invariant to scaling the GT overlaps and to shifting each scan's cosines by its own constant.
    assert float(listwise_loss(C, overlap * scale, log_tau)) == pytest.approx(loss, rel=1e-9, abs=1e-12)
    row_shift = torch.linspace(-0.3, 0.3, len(C))[:, None].double()
    assert float(listwise_loss(C + row_shift, overlap, log_tau)) == pytest.approx(loss, rel=1e-9, abs=1e-9)
    # Zero exactly when each scan's softmax of cosines is its normalised overlaps (where they are all > 0).
    positive = overlap + 1 / 64
    ideal = np.exp(log_tau) * torch.log(positive)
    assert float(listwise_loss(ideal, positive, log_tau)) == pytest.approx(0.0, abs=1e-9)
    if not torch.allclose(
        torch.softmax(C / np.exp(log_tau) - 1e9 * torch.eye(len(C)), 1),
        torch.softmax(ideal / np.exp(log_tau) - 1e9 * torch.eye(len(C)), 1),
        atol=1e-3,
    ):
        assert float(listwise_loss(C, positive, log_tau)) > 0


@pytest.mark.parametrize(
    "option, value", [("clusters", 0), ("clusters", 100_000), ("lr", -1.0), ("lr", float("nan")), ("tau", float("inf"))]
)
def test_a_setting_training_cannot_use_is_refused_before_anything_is_written(cache, tmp_path, option, value):
    """``--clusters 0`` and ``--lr -1`` failed deep in training ("argmax of an empty sequence", torch's "Invalid
    learning rate") and left an empty output folder; ``--lr nan`` trained on NaN; ``--clusters 100000`` grew to 24 GB
    until the kernel killed it."""
    with pytest.raises(InputError, match=f"{option} must be"):
        train(cache, tmp_path / "out", epochs=1, progress=False, log=lambda _: None, **{option: value})
    assert not (tmp_path / "out").exists()
