"""Overlap-head training: it learns on a simulated scene, resumes exactly, saves and reloads exactly, and the
shipped head loads and gives unit features."""

import numpy as np
import pytest
import torch

from data_tools.simulate import make_training_scene, scene_descriptors
from sghr_gtsam.features.netvlad import DEFAULT_HEAD, global_features, load_checkpoint, load_default_head
from sghr_gtsam.graph import overlap_scores
from sghr_gtsam.train import (
    cache_path,
    evaluate,
    init_head,
    load_cache,
    pair_loss,
    sample_step,
    save_head,
    train,
    write_cache_scene,
)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One tiny simulated object scene (8 scans), its FPFH and GT overlaps, cached as training reads it."""
    folder = tmp_path_factory.mktemp("cache")
    scene = make_training_scene("object", 8, seed=[7, 0])
    iu = np.triu_indices(8, 1)
    assert scene.overlap[iu].min() < 0.3 < scene.overlap[iu].max()  # low and high overlaps both present
    write_cache_scene(cache_path(folder, 0), scene_descriptors(scene), scene.overlap, poses=scene.poses,
                      voxel=scene.voxel, kind=scene.kind)
    return folder


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
    a = overlap_scores(global_features(model.eval(), scene.descriptors))
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
