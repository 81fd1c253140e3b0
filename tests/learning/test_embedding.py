"""Training the learned MCL encoder (``learning/embedding.py``, ``learning/embedding_data.py``): the NumPy encoder
is the torch one, training is a function of its seed, the recipe parses and runs end to end, nothing the user wrote
is overwritten."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl import learned
from aerial_loc_env.learning.embedding_data import PairSet

th = pytest.importorskip("torch", reason="training the encoder needs the 'rl' extra (torch)")
emb = pytest.importorskip("aerial_loc_env.learning.embedding")


def _recipe(**kw):
    base = {"steps": 3, "batch": 4, "window_px": 32, "query_cells": 32, "threads": 1, "seed": 0}
    return build_config(emb.EmbeddingRecipe, {**base, **kw}, where="test")


def _pairs(n: int = 6, seed: int = 0) -> PairSet:
    """Blurred-noise 'ground' and a map of it with another gain, offset and noise (co-registered)."""
    g = np.random.default_rng(seed)
    frames = np.stack([cv2.GaussianBlur(g.uniform(0, 255, (48, 48)).astype(np.float32), (0, 0), 1.5)
                       for _ in range(n)])
    maps = 0.7 * frames + 30 + g.normal(0, 3, frames.shape).astype(np.float32)
    return PairSet(frames, maps.astype(np.float32), np.full((n, 2), 48, np.int32), ("synthetic",) * n)


@pytest.mark.parametrize("shape", [(37, 52), (64, 64), (9, 5)])
def test_numpy_encoder_equals_torch(tmp_path, shape) -> None:
    recipe = _recipe()
    th.manual_seed(3)
    net = emb.torch_encoder(recipe)
    path = emb.write_weights(emb.export_weights(net, recipe, 0.05), tmp_path / "w.npz")
    w = learned.load_weights(str(path))
    x = np.random.default_rng(1).standard_normal(shape).astype(np.float32)
    with th.no_grad():
        ref = net(th.from_numpy(x)[None, None])[0].permute(1, 2, 0).numpy()
    out = w.encoder(x)
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, atol=2e-5)
    np.testing.assert_allclose(np.linalg.norm(out, axis=2), 1.0, atol=1e-5)


def test_training_is_a_function_of_the_seed(tmp_path) -> None:
    pairs = (_pairs(), _pairs(4, seed=1))
    a = emb.train_embedding(_recipe(), tmp_path / "a.npz", pairs=pairs)
    b = emb.train_embedding(_recipe(), tmp_path / "b.npz", pairs=pairs)
    c = emb.train_embedding(_recipe(seed=1), tmp_path / "c.npz", pairs=pairs)
    wa, wb, wc = (np.load(r.path) for r in (a, b, c))
    for k in wa.files:
        if k != "meta":
            np.testing.assert_array_equal(wa[k], wb[k])
    assert any(not np.array_equal(wa[k], wc[k]) for k in wa.files if k != "meta")
    assert a.temperature == b.temperature > 0
    assert [r["cells"] for r in a.history] == [r["cells"] for r in b.history]


def test_training_lowers_the_loss_on_easy_pairs() -> None:
    """The contrastive losses fall on co-registered pairs that differ by gain, offset and noise (a few dozen
    steps; the first logged window against the last)."""
    res = emb.train_embedding(_recipe(steps=60, batch=8, learning_rate=0.01), None, pairs=(_pairs(), _pairs(4, 1)),
                              log_every=20)
    assert res.history[-1]["cells"] < res.history[0]["cells"]
    assert res.history[-1]["offsets"] < res.history[0]["offsets"]


def test_existing_weights_are_never_overwritten(tmp_path) -> None:
    path = tmp_path / "mine.npz"
    path.write_bytes(b"the user's model")
    with pytest.raises(ConfigError, match="exists"):
        emb.train_embedding(_recipe(), path, pairs=(_pairs(), _pairs(4, 1)))
    with pytest.raises(ConfigError, match="exists"):
        emb.write_weights({"x": np.zeros(1)}, path)
    assert path.read_bytes() == b"the user's model"


def test_the_shipped_recipe_parses_and_bad_keys_are_refused(tmp_path) -> None:
    r = emb.read_recipe("mcl-learned")
    assert emb.is_embedding_recipe("mcl-learned") and not emb.is_embedding_recipe("ppo-local-registration")
    assert r.channels[-1] == learned.load_weights(learned.DEFAULT_WEIGHTS).encoder.channels
    assert emb.read_recipe("mcl-learned", steps=5).steps == 5
    bad = tmp_path / "bad.toml"
    bad.write_text('class = "MCLAgent"\n[train]\nkind = "embedding"\nstepz = 3\n')
    with pytest.raises(ConfigError, match="stepz"):
        emb.read_recipe(str(bad))
    with pytest.raises(ConfigError, match="multiple"):
        _recipe(window_px=30)


@pytest.mark.slow
def test_the_recipe_runs_end_to_end_on_a_tiny_budget(tmp_path) -> None:
    """Simulated pairs of one train world and one val world, two steps: weights the model loads and runs."""
    recipe = _recipe(n_train=2, n_train_worlds=1, n_val=2, n_val_worlds=1, city_size_m=300.0, steps=2, workers=1)
    res = emb.train_embedding(recipe, tmp_path / "w.npz")
    w = learned.load_weights(str(res.path))
    assert w.meta["training"]["steps"] == 2 and w.meta["recipe"]["n_train"] == 2
    e = w.encoder(np.zeros((20, 20), np.float32))
    assert e.shape == (10, 10, recipe.channels[-1])
