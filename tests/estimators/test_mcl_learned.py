"""The learned measurement model (``estimators/mcl/learned.py``) with the shipped weights: the likelihood peaks at
the true pose of a co-registered frame, is blind to a global gain, the agent tracks a short flight, and missing or
corrupt weights are clear errors before any work."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_dense_models import ALT_M, briefing_standin, render_frame, textured_map
from test_mcl import fly, observation

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl import learned
from aerial_loc_env.estimators.mcl.measurement import make_model

MODEL = "aerial_loc_env.estimators.mcl.learned:LearnedModel"


@pytest.fixture(scope="module")
def scene():
    m = textured_map(400, seed=1)
    truth = (100.0, 100.0, 0.4)
    return m, truth, render_frame(m, *truth)


def _grid(truth, half_m: float = 20.0, step_m: float = 1.0) -> np.ndarray:
    d = np.arange(-half_m, half_m + step_m / 2, step_m)
    dx, dy = np.meshgrid(d, d)
    return np.column_stack([truth[0] + dx.ravel(), truth[1] + dy.ravel(), np.full(dx.size, truth[2])])


def test_shipped_weights_load_and_describe_themselves() -> None:
    w = learned.load_weights(learned.DEFAULT_WEIGHTS)
    assert w.encoder.stride >= 1 and w.encoder.channels >= 4
    assert w.meta["format"] == learned.WEIGHTS_FORMAT and w.meta["temperature"] > 0
    # trained on simulated worlds only (the card's claim, recorded by the recipe)
    assert w.meta["recipe"]["n_train"] > 0 and "training" in w.meta


def test_likelihood_peaks_at_the_true_pose(scene) -> None:
    """A frame rendered from the map itself: the best-scoring position of a 1 m grid over +-20 m lies within one
    embedding cell (stride * gsd) of the truth, and the truth's score is well above the far positions'."""
    m, truth, frame = scene
    model = make_model(MODEL)
    model.reset(briefing_standin(m), np.random.default_rng(0))
    states = _grid(truth)
    ll = model.log_likelihood(model.prepare(observation(frame, yaw=truth[2]), np.random.default_rng(0)), states,
                              ALT_M)
    assert np.all(np.isfinite(ll))
    cell_m = model.weights.encoder.stride * float(model.weights.meta["gsd_m"])
    best = states[int(np.argmax(ll))]
    assert math.hypot(best[0] - truth[0], best[1] - truth[1]) <= cell_m
    dist = np.hypot(states[:, 0] - truth[0], states[:, 1] - truth[1])
    score = model.scores(model.prepare(observation(frame, yaw=truth[2]), np.random.default_rng(0)), states)
    assert score[dist < 1.0].max() > score[dist > 10.0].max() + 0.1


def test_scores_ignore_a_global_gain(scene) -> None:
    """The local normalization takes out a gain: 0.6 x the frame (no clipping) scores as the frame, up to the
    uint8 rounding of the darker frame."""
    m, truth, frame = scene
    model = make_model(MODEL)
    model.reset(briefing_standin(m), np.random.default_rng(0))
    states = _grid(truth, 10.0, 2.0)
    dark = np.round(frame.astype(np.float32) * 0.6).astype(np.uint8)
    s1 = model.scores(model.prepare(observation(frame, yaw=truth[2]), np.random.default_rng(0)), states)
    s2 = model.scores(model.prepare(observation(dark, yaw=truth[2]), np.random.default_rng(0)), states)
    np.testing.assert_allclose(s1, s2, atol=0.03)
    assert int(np.argmax(s1)) == int(np.argmax(s2))


def test_particles_off_the_map_get_the_worst_score(scene) -> None:
    m, truth, frame = scene
    model = make_model(MODEL)
    model.reset(briefing_standin(m), np.random.default_rng(0))
    states = np.array([truth, (5000.0, 5000.0, 0.0), (-3000.0, 100.0, 0.0)])
    s = model.scores(model.prepare(observation(frame, yaw=truth[2]), np.random.default_rng(0)), states)
    assert s[1] == -1.0 and s[2] == -1.0 and s[0] > 0.3


def test_agent_tracks_a_short_flight() -> None:
    """The filter with the learned model on the synthetic flight of test_mcl (prior 7.8 m off): it ends within a
    few metres and beats dead reckoning by a wide margin."""
    m = textured_map(400, seed=1)
    names = ["dead-reckoning", "mcl-learned"]
    e = fly(names, m, seed=0, overrides={"mcl-learned": {"n_particles": 300}})
    dr = float(np.sqrt(np.mean(e["dead-reckoning"] ** 2)))
    assert dr > 6.0
    assert e["mcl-learned"][-5:].max() < 3.0, e["mcl-learned"]
    assert np.sqrt(np.mean(e["mcl-learned"] ** 2)) < dr / 2


# ------------------------------------------------------------------------------------------ bad weights
def test_missing_weights_name_the_file(tmp_path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        make_model(MODEL, {"weights": str(tmp_path / "nope.npz")})


def _shipped_arrays() -> dict:
    with np.load(learned.resolve_weights(learned.DEFAULT_WEIGHTS)) as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("damage", ["garbage", "no_meta", "old_format", "missing_layer", "nan"])
def test_corrupt_weights_are_clear_errors(tmp_path, damage: str) -> None:
    path = tmp_path / "w.npz"
    arrays = _shipped_arrays()
    meta = json.loads(str(arrays["meta"]))
    if damage == "garbage":
        path.write_bytes(b"not a zip archive at all")
    else:
        if damage == "no_meta":
            del arrays["meta"]
        elif damage == "old_format":
            arrays["meta"] = np.array(json.dumps({**meta, "format": 0}))
        elif damage == "missing_layer":
            del arrays["layer1_w"]
        else:
            arrays["layer0_w"] = np.full_like(arrays["layer0_w"], np.nan)
        np.savez(path, **arrays)
    with pytest.raises(ConfigError, match=str(path.name)):
        make_model(MODEL, {"weights": str(path)})


def test_a_map_read_by_window_is_declared() -> None:
    model = make_model(MODEL)
    assert model.reads_windows
