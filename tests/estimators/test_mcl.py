"""MCL math: XNOR similarity, the activation (eq. 8), the likelihood mappings, eq. (3) against the rendered
camera, motion, mean shift, and the filter's behaviour (tracking beats dead reckoning, injection recovers)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_dense_models import ALT_M, CAMERA, briefing_standin, orthomap_standin, render_frame, textured_map

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.estimate import mean_shift, weighted_cov, weighted_mean
from aerial_loc_env.estimators.mcl.intensity_pairs import (
    IntensityPairsConfig,
    IntensityPairsModel,
    activation,
    xnor_similarity,
)
from aerial_loc_env.estimators.mcl.measurement import make_model
from aerial_loc_env.estimators.mcl.motion import OdometryMotionModel, mid_heading
from aerial_loc_env.estimators.mcl.resampling import normalize_log_weights
from aerial_loc_env.estimators.protocol import Observation
from aerial_loc_env.estimators.registry import make_agent
from aerial_loc_env.sensors.render import CameraRenderer, Photometry
from aerial_loc_env.world.shadows import apply_shading


def observation(image: np.ndarray, speed: float = 0.0, yaw_rate: float = 0.0, yaw: float = 0.0,
                alt: float = ALT_M) -> dict:
    return {"image": image, "odometry": np.array([speed, yaw_rate, 0.0], np.float32),
            "yaw": np.array([yaw], np.float32), "altitude": np.array([alt], np.float32)}


# ------------------------------------------------------------------------------------------ eq. (4) and (6)
def test_xnor_similarity_counts() -> None:
    cam = np.array([[1, 0, 1], [0, 0, 1]], bool)                     # K = 2 pairs, c = 3
    db = np.array([[[1, 0, 1], [0, 0, 1]],                            # 6 of 6 agree
                   [[0, 1, 0], [1, 1, 0]],                            # 0 of 6
                   [[1, 1, 1], [0, 0, 1]]], bool)                     # 5 of 6
    np.testing.assert_allclose(xnor_similarity(cam, db), [1.0, 0.0, 5 / 6])
    keep = np.array([False, True])                                    # eq. (6): only the second pair
    np.testing.assert_allclose(xnor_similarity(cam, db, keep), [1.0, 0.0, 1.0])
    valid = np.array([[True, False], [True, True], [True, True]])     # a pair off the map: half credit
    np.testing.assert_allclose(xnor_similarity(cam, db, valid=valid), [(3 + 1.5) / 6, 0.0, 5 / 6])
    np.testing.assert_allclose(xnor_similarity(cam, db, np.zeros(2, bool)), 0.5)
    # padding channels (the alpha byte) agree by construction and do not count
    cam4 = np.concatenate([cam, np.zeros((2, 1), bool)], axis=1)
    db4 = np.concatenate([db, np.zeros((3, 2, 1), bool)], axis=2)
    np.testing.assert_allclose(xnor_similarity(cam4, db4, channels=3), xnor_similarity(cam, db))
    # soft allocation: pair weights (the second pair counts half): (6 * 1 + ... ) / (1.5 * 3)
    w = np.array([1.0, 0.5])
    np.testing.assert_allclose(xnor_similarity(cam, db, pair_weights=w), [1.0, 0.0, (2 + 0.5 * 3) / 4.5])
    np.testing.assert_allclose(xnor_similarity(cam4, db4, channels=3, pair_weights=w),
                               xnor_similarity(cam, db, pair_weights=w))
    np.testing.assert_allclose(xnor_similarity(cam4, db4, valid=valid, channels=3),
                               xnor_similarity(cam, db, valid=valid))


# ------------------------------------------------------------------------------------------ eq. (8)
@pytest.mark.parametrize("K", [10, 30, 50, 70])
def test_activation_values_and_slope(K: int) -> None:
    a = 10.0 / K
    assert activation(K, K / 2, a) == pytest.approx(0.5)
    assert activation(K, 0, a) == pytest.approx(1 - 1 / (1 + math.exp(a * K / 2)))
    lc = np.arange(K + 1)
    s = activation(K, lc, a)
    assert np.all(np.diff(s) < 0) and np.all((s > 0) & (s < 1))
    h = 1e-4                                       # slope at the midpoint: d/dlc [1 - sigmoid(a (lc - K/2))]
    slope = (activation(K, K / 2 + h, a) - activation(K, K / 2 - h, a)) / (2 * h)
    assert slope == pytest.approx(-a / 4, rel=1e-6)
    # a = gain / K: one curve of the shadowed fraction lc / K, whatever K (the paper's "rate constant")
    assert activation(K, 0.3 * K, a) == pytest.approx(activation(100, 30, 0.1))


# ------------------------------------------------------------------------------------------ eq. (3)
def ramp_map(size: int = 400):
    """R, G encode the map column and row (half a level per pixel), B is flat: bilinear warps are exact."""
    u = np.arange(size, dtype=np.float32)
    rgb = np.zeros((size, size, 3), np.uint8)
    rgb[..., 0] = np.round(u[None, :] / 2)
    rgb[..., 1] = np.round(u[:, None] / 2)
    rgb[..., 2] = 128
    return orthomap_standin(rgb)


@pytest.mark.parametrize("yaw", [0.0, 0.7, -2.4])
def test_eq3_pair_points_land_on_the_rendered_ground_point(yaw: float) -> None:
    """The pixel the renderer shows at camera (u, v) comes from the map pixel the model projects it to."""
    m = ramp_map()
    renderer = CameraRenderer(m, CAMERA, Photometry.ideal())
    x, y = 100.3, 95.8
    frame = renderer.render((x, y, yaw, ALT_M), np.random.default_rng(0)).image
    model = IntensityPairsModel()
    model.reset(briefing_standin(m), np.random.default_rng(0))
    g = np.random.default_rng(1)
    uv = np.column_stack([g.integers(0, CAMERA.width_px, 200), g.integers(0, CAMERA.height_px, 200)])
    col, row = model.map_pixels(uv.astype(float), np.array([[x, y, yaw]]), ALT_M)
    seen = frame[uv[:, 1], uv[:, 0]].astype(float)
    np.testing.assert_allclose(2 * seen[:, 0], col[0], atol=1.6)      # 1 level = 2 px, plus rounding
    np.testing.assert_allclose(2 * seen[:, 1], row[0], atol=1.6)
    # and it is CameraModel.project_pixels (the same eq. (3)), only faster
    ref = CAMERA.project_pixels(m, uv, x, y, yaw, ALT_M)[0]
    np.testing.assert_allclose(np.column_stack([col[0], row[0]]), ref, atol=2e-3)   # float32


# ------------------------------------------------------------------------------------------ models
@pytest.fixture(scope="module")
def scene():
    m = textured_map(400, seed=1)
    truth = (100.0, 100.0, 0.4)
    frame = render_frame(m, *truth)
    return m, truth, frame


def _particles(truth, n: int = 300, spread: float = 15.0, seed: int = 0) -> np.ndarray:
    g = np.random.default_rng(seed)
    s = np.column_stack([truth[0] + g.normal(0, spread, n), truth[1] + g.normal(0, spread, n),
                         np.full(n, truth[2])])
    s[0] = truth
    return s


@pytest.mark.parametrize("name", ["intensity_pairs", "intensity_pairs_restoration", "intensity_pairs_shadow_aware"])
def test_true_pose_has_the_highest_likelihood(scene, name: str) -> None:
    m, truth, frame = scene
    model = make_model(name, {"n_pairs": 70})
    model.reset(briefing_standin(m), np.random.default_rng(0))
    states = _particles(truth)
    far = np.hypot(states[:, 0] - truth[0], states[:, 1] - truth[1]) > 3.0
    g = np.random.default_rng(5)
    wins = 0
    for _ in range(10):
        ll = model.log_likelihood(model.prepare(observation(frame, yaw=truth[2]), g), states, ALT_M)
        wins += ll[0] > ll[far].max()
    assert wins >= 9
    assert model.last_stats["K"] == 70


def test_binomial_gaussian_and_linear_mappings(scene) -> None:
    m, truth, frame = scene
    states = _particles(truth, n=50)
    out = {}
    for like in ("binomial", "gaussian", "linear"):
        model = IntensityPairsModel(build_config(IntensityPairsConfig, {"likelihood": like, "kappa": 0.7,
                                                                        "sigma": 0.2, "n_pairs": 40}))
        model.reset(briefing_standin(m), np.random.default_rng(0))
        prep = model.prepare(observation(frame, yaw=truth[2]), np.random.default_rng(3))
        out[like] = (model.similarity(prep, states, ALT_M), model.log_likelihood(prep, states, ALT_M))
    xi = out["binomial"][0]
    for like in out:                                # same pairs (same seed): same similarity
        np.testing.assert_allclose(out[like][0], xi)
    np.testing.assert_allclose(out["binomial"][1], 0.7 * 40 * 3 * xi)        # kappa * n * xi
    np.testing.assert_allclose(out["gaussian"][1], -0.5 * ((xi - 1.0) / 0.2) ** 2)
    np.testing.assert_allclose(out["linear"][1], np.log(xi))


def _shadowed(frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    occ = np.zeros(frame.shape[:2], np.uint8)
    occ[:, : frame.shape[1] // 2] = 255                                   # the left half in shadow
    return apply_shading(frame, occ, 1.0), occ > 127


def test_literal_activation_cancels_and_tempering_flattens(scene) -> None:
    """sigma_m(K, lc) is the same for every particle: multiplying by it changes no normalized weight.
    Tempering by it does: with half the pairs dropped the weights are flatter (larger ESS)."""
    m, truth, frame = scene
    shadowed, mask = _shadowed(frame)
    info = {"shadow_mask": mask}
    states = _particles(truth)
    W = {}
    for act in ("none", "multiply", "temper"):
        model = make_model("intensity_pairs_shadow_aware", {"activation": act, "detector": "oracle",
                                                            "activation_gain": 10.0})
        model.reset(briefing_standin(m), np.random.default_rng(0))
        prep = model.prepare(observation(shadowed, yaw=truth[2]), np.random.default_rng(7), info)
        W[act], _ = normalize_log_weights(model.log_likelihood(prep, states, ALT_M))
        lc, K = model.last_stats["shadow_pairs"], model.last_stats["K"]
        assert model.last_stats["activation"] == pytest.approx(activation(K, lc, 10.0 / K))
    assert 0 < lc < K
    np.testing.assert_allclose(W["multiply"], W["none"], rtol=1e-9, atol=1e-15)
    assert 1 / np.sum(W["temper"] ** 2) > 1 / np.sum(W["none"] ** 2)


def test_dropping_shadowed_pairs_restores_the_similarity(scene) -> None:
    """At the true pose, the pairs kept by eq. (6) agree better than all K pairs of the shadowed frame."""
    m, truth, frame = scene
    shadowed, mask = _shadowed(frame)
    xi = {}
    for name in ("intensity_pairs", "intensity_pairs_shadow_aware"):
        params = {"n_pairs": 400} if name == "intensity_pairs" else {"n_pairs": 400, "detector": "oracle"}
        model = make_model(name, params)
        model.reset(briefing_standin(m), np.random.default_rng(0))
        prep = model.prepare(observation(shadowed, yaw=truth[2]), np.random.default_rng(2), {"shadow_mask": mask})
        xi[name] = float(model.similarity(prep, np.array([truth]), ALT_M)[0])
    assert xi["intensity_pairs_shadow_aware"] > xi["intensity_pairs"] + 0.03


def test_measurement_config_errors() -> None:
    with pytest.raises(ConfigError, match="n_pairs"):
        make_model("intensity_pairs", {"n_pairs": 0})
    with pytest.raises(ConfigError, match="unknown key"):
        make_model("intensity_pairs", {"pairs": 10})
    with pytest.raises(ConfigError, match="shadow = 'drop'"):
        make_model("intensity_pairs", {"activation": "temper"})
    with pytest.raises(ConfigError, match="detector_params"):
        make_model("intensity_pairs_shadow_aware", {"detector_params": {"scale": 5.0}})
    with pytest.raises(ConfigError, match="unknown measurement model"):
        make_model("ssd-but-misspelled")


# ------------------------------------------------------------------------------------------ motion, estimate
def test_motion_model_moves_by_the_odometry() -> None:
    noise = briefing_standin(textured_map(50)).odometry_noise
    mm = OdometryMotionModel(noise, 0.25, state="xy", noise_scale=1.0)
    states = np.zeros((20000, 3))
    mm.prev_yaw_rad = 0.0
    mm.propagate(states, Observation(np.zeros((2, 2, 3), np.uint8), 10.0, 0.4, 0.1, ALT_M), np.random.default_rng(0))
    psi = mid_heading(0.0, 0.1, 0.4, 0.25)
    assert psi == pytest.approx(0.05)
    mean = states[:, :2].mean(axis=0)
    np.testing.assert_allclose(mean, 2.5 * np.array([math.cos(psi), math.sin(psi)]), atol=0.01)
    # spread: along-track speed noise * dt, across-track distance * heading noise / sqrt(2) and the lateral
    # speed's noise * dt
    std = states[:, :2].std(axis=0)
    assert std.max() == pytest.approx(max(0.1 * 0.25, math.hypot(2.5 * 0.02 / math.sqrt(2), 0.1 * 0.25)), rel=0.1)
    assert mid_heading(3.1, -3.1, 0.0, 0.25) == pytest.approx(-math.pi, abs=0.01) or \
        mid_heading(3.1, -3.1, 0.0, 0.25) == pytest.approx(math.pi, abs=0.01)


def test_mean_shift_finds_the_larger_of_two_clusters() -> None:
    g = np.random.default_rng(0)
    a = g.normal([0.0, 0.0], 2.0, (600, 2))
    b = g.normal([40.0, 10.0], 2.0, (400, 2))
    xy = np.vstack([a, b])
    W = np.full(1000, 1e-3)
    mean = weighted_mean(xy, W)
    assert np.hypot(*mean) > 10                                     # the mean lands between the clusters
    mode = mean_shift(xy, W, bandwidth_m=4.0, rng=g)
    assert np.hypot(*mode) < 1.0
    # weights, not counts, decide: make the smaller cluster heavier
    W2 = np.concatenate([np.full(600, 1.0), np.full(400, 2.0)])
    mode2 = mean_shift(xy, W2 / W2.sum(), bandwidth_m=4.0, rng=g)
    assert np.hypot(*(mode2 - [40, 10])) < 1.0
    cov = weighted_cov(a, np.full(600, 1 / 600))
    assert np.allclose(np.diag(cov), 4.0, rtol=0.2)


# ------------------------------------------------------------------------------------------ the filter
def fly(agent_names, m, *, start=(60.0, 80.0), yaw=0.3, speed=8.0, steps=30, prior_offset=(6.0, -5.0),
        prior_std=8.0, shadows=False, seed=0, overrides=None):
    """Agents in lockstep on a straight, noisy-odometry flight over the synthetic map; errors per agent."""
    br = briefing_standin(m, mean_xy_m=(start[0] + prior_offset[0], start[1] + prior_offset[1]),
                          std_xy_m=prior_std)
    agents = {n: make_agent(n, **(overrides or {}).get(n, {})) for n in agent_names}
    for a in agents.values():
        a.reset(br, seed=seed)
    g = np.random.default_rng(seed + 1000)
    p = np.array(start, float)
    errors = {n: [] for n in agents}
    for k in range(steps):
        if k > 0:
            p = p + speed * br.dt_s * np.array([math.cos(yaw), math.sin(yaw)])
        img = render_frame(m, p[0], p[1], yaw)
        if shadows:
            occ = np.zeros(img.shape[:2], np.uint8)
            occ[10:50, 20 + (k % 5) * 10: 70 + (k % 5) * 10] = 255
            img = apply_shading(img, occ, 0.9)
        obs = observation(img, speed + g.normal(0, 0.1), g.normal(0, 0.02), yaw + g.normal(0, 0.02))
        for n, a in agents.items():
            e = a.step(obs)
            errors[n].append(math.hypot(e.x_m - p[0], e.y_m - p[1]))
    return {n: np.array(v) for n, v in errors.items()}


def test_mcl_beats_dead_reckoning_with_shadows() -> None:
    """3 seeds, 30 steps. Dead reckoning keeps the prior's offset (|(6, -5)| = 7.8 m); a working filter ends
    within a few pixels (0.5 m each) of the truth. The margin (final error < 2 m and 1/3 of dead reckoning's
    RMSE) leaves room for a bad seed of the shadowed frames without passing a broken filter."""
    m = textured_map(400, seed=1)
    names = ["dead-reckoning", "mcl-conventional", "mcl-restoration", "mcl-shadow-aware"]
    small = {n: {"n_particles": 300} for n in names[1:]}
    for seed in range(3):
        e = fly(names, m, shadows=True, seed=seed, overrides=small)
        dr = float(np.sqrt(np.mean(e["dead-reckoning"] ** 2)))
        assert dr > 6.0
        for n in names[1:]:
            assert e[n][-5:].max() < 2.0, (n, seed, e[n])
            assert np.sqrt(np.mean(e[n] ** 2)) < dr / 3, (n, seed)


def test_injection_recovers_from_a_wrong_prior() -> None:
    """Prior 40 m off with 3 m spread: no particle is near the truth. Without injection the filter stays lost;
    with 5 % uniform injection per step it relocates within the flight."""
    m = textured_map(400, seed=1)
    common = {"n_particles": 400, "resample": "ess", "resampling": "systematic"}
    over = {"mcl-shadow-aware": {**common, "injection_fraction": 0.05, "estimator": "mean_shift"},
            "mcl-conventional": common}
    e = fly(["mcl-shadow-aware", "mcl-conventional"], m, prior_offset=(30.0, -27.0), prior_std=3.0, steps=40,
            overrides=over, start=(70.0, 60.0))
    assert e["mcl-conventional"][-1] > 10.0            # the control: no recovery without injection
    assert e["mcl-shadow-aware"][-5:].max() < 2.0


def test_uniform_start_converges_on_the_small_map() -> None:
    m = textured_map(400, seed=1)
    params = {"init": "uniform", "n_particles": 3000, "resample": "ess", "resampling": "systematic",
              "estimator": "mean_shift"}
    start = make_agent("mcl-conventional", **params).reset(briefing_standin(m), seed=0)
    assert start.std_m > 20.0 and start.status != "ok"          # it really starts from nowhere
    e = fly(["mcl-conventional"], m, steps=30, overrides={"mcl-conventional": params}, start=(70.0, 60.0))
    assert e["mcl-conventional"][-5:].max() < 2.0
