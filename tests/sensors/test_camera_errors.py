"""Camera and sensor errors of real flights: gimbal jitter (Gauss-Markov), heading offset, barometric bias and drift,
auto-exposure, haze; off by default, and then the episodes are the ones without them, bit for bit."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest
from shared_helpers import check_env_silently

import aerial_loc_env  # noqa: F401  (registers the ids)
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.sensors.camera import ExposureConfig, GimbalConfig, HazeConfig, SceneExposure, gauss_markov
from aerial_loc_env.sensors.flight import AltimeterConfig

M = 4000   # independent series for the statistics


def episode(seed: int = 3, **overrides) -> tuple[list[dict], list[dict]]:
    env = gym.make("AerialLoc/Small-v3", flight={"duration_s": 2.0}, **overrides)
    obs, info = env.reset(seed=seed)
    observations, infos = [obs], [info]
    done = False
    while not done:
        obs, _, term, trunc, info = env.step(np.zeros(2, np.float32))
        observations.append(obs)
        infos.append(info)
        done = term or trunc
    env.close()
    return observations, infos


def same(a: list[dict], b: list[dict]) -> bool:
    return all(x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x) for x, y in zip(a, b, strict=True))


def test_sections_off_give_the_episodes_without_them_bit_for_bit():
    """All-zero sections draw nothing and change nothing, whatever their other (inactive) fields say."""
    plain, plain_info = episode()
    off, off_info = episode(gimbal={"correlation_time_s": 7.0}, altimeter={"bias_std_m": 0.0},
                            exposure={"target_luma": 60.0, "time_constant_s": 3.0},
                            haze={"airlight_rgb": [10.0, 20.0, 30.0]}, perspective={"march_steps": 5})
    assert same(plain, off)
    assert all(np.array_equal(a["true_pose"], b["true_pose"]) for a, b in zip(plain_info, off_info, strict=True))
    assert "gimbal_roll_pitch_rad" not in off_info[0] and "exposure_gain" not in off_info[0]
    on, _ = episode(gimbal={"roll_pitch_std_deg": 0.5})
    assert not same(plain, on)


@pytest.mark.parametrize(("sigma_deg", "tau_s"), [(0.3, 1.0), (0.5, 0.0), (0.2, 10.0)])
def test_gauss_markov_has_the_configured_sigma_and_correlation(sigma_deg, tau_s):
    """Stationary: every step is N(0, sigma^2); lag-1 correlation phi = exp(-dt / tau). Tolerances are 4 standard
    errors of the estimators over M independent series: sigma / sqrt(2 (M - 1)) and (1 - phi^2) / sqrt(M)."""
    sigma, dt = math.radians(sigma_deg), 0.25
    x = gauss_markov(np.random.default_rng(0), 30, sigma, dt, tau_s, size=(M,))
    phi = math.exp(-dt / tau_s) if tau_s > 0 else 0.0
    for k in (0, 29):
        assert x[k].std() == pytest.approx(sigma, abs=4 * sigma / math.sqrt(2 * (M - 1)))
    r = np.corrcoef(x[28], x[29])[0, 1]
    assert r == pytest.approx(phi, abs=4 * max(1 - phi * phi, 0.02) / math.sqrt(M))


def test_env_renders_the_jitter_and_reports_it_only_in_info():
    obs, infos = episode(gimbal={"roll_pitch_std_deg": 0.4, "correlation_time_s": 0.5})
    tilt = np.array([i["gimbal_roll_pitch_rad"] for i in infos])
    assert tilt.shape == (len(infos), 2) and np.all(np.abs(tilt) < math.radians(0.4) * 6) and np.any(tilt != 0)
    plain, _ = episode()
    assert not np.array_equal(obs[0]["image"], plain[0]["image"])
    again, again_info = episode(gimbal={"roll_pitch_std_deg": 0.4, "correlation_time_s": 0.5})
    assert same(obs, again)


def test_heading_offset_is_one_constant_per_episode():
    obs, infos = episode(gimbal={"heading_bias_std_deg": 5.0}, odometry={"heading_std_rad": 0.0})
    err = np.array([o["yaw"][0] - i["true_pose"][2] for o, i in zip(obs, infos, strict=True)])
    err = (err + math.pi) % (2 * math.pi) - math.pi
    assert np.ptp(err) < 1e-5 and 0.0 < abs(err[0]) < math.radians(30)


def test_baro_bias_and_drift_statistics():
    """Error at time t ~ N(0, bias^2 + drift^2 t); zero drift at the first frame. 4 standard errors."""
    cfg = AltimeterConfig(bias_std_m=2.0, drift_std_m_per_sqrt_s=0.3)
    t = np.arange(41) * 0.25
    rng = np.random.default_rng(1)
    err = np.array([cfg.draw_error(rng, t) for _ in range(M)])
    for k in (0, 40):
        sd = math.sqrt(4.0 + 0.09 * t[k])
        assert err[:, k].std() == pytest.approx(sd, abs=4 * sd / math.sqrt(2 * (M - 1)))
    steps = np.diff(err, axis=1)
    assert steps.std() == pytest.approx(0.3 * 0.5, rel=0.03)
    obs, infos = episode(altimeter={"bias_std_m": 3.0}, odometry={"altitude_std_m": 0.0})
    e = np.array([o["altitude"][0] - i["true_pose"][3] for o, i in zip(obs, infos, strict=True)])
    assert np.ptp(e) < 1e-3 and abs(e[0]) > 0.0


def test_auto_exposure_brightens_dark_scenes_with_the_configured_lag():
    ex = ExposureConfig(strength=1.0, target_luma=120.0, time_constant_s=0.5)
    se = SceneExposure(HazeConfig(), ex, dt_s=0.25)
    dark = np.full((40, 60, 3), 40, np.uint8)
    alpha = 1 - math.exp(-0.25 / 0.5)
    out = se(dark, 100.0)
    assert se.gain == pytest.approx(3.0) and out.mean() == pytest.approx(120.0, abs=0.5)   # first frame: setpoint
    bright = np.full((40, 60, 3), 200, np.uint8)
    gains = []
    for _ in range(3):
        se(bright, 100.0)
        gains.append(se.gain)
    expect, g = [], 3.0
    for _ in range(3):
        g += alpha * (0.6 - g)
        expect.append(g)
    assert gains == pytest.approx(expect)
    se.reset()
    assert se.gain is None


def test_haze_lowers_contrast_by_the_transmission_and_grows_with_altitude():
    haze = HazeConfig(extinction_per_km=0.5)
    se = SceneExposure(haze, ExposureConfig(), dt_s=0.25)
    img = np.zeros((2, 2, 3), np.uint8)
    img[1] = 200
    for alt in (100.0, 400.0):
        t = math.exp(-0.5 * alt / 1000)
        out = se(img, alt).astype(float)
        assert out[0, 0] == pytest.approx((1 - t) * np.array(haze.airlight_rgb), abs=0.51)
        assert out[1, 0, 0] - out[0, 0, 0] == pytest.approx(200 * t, abs=1.0)


def test_bad_camera_error_configs_are_clear_errors():
    with pytest.raises(ConfigError, match="roll_pitch_std_deg"):
        gym.make("AerialLoc/Small-v3", gimbal={"roll_pitch_std_deg": -1.0})
    with pytest.raises(ConfigError, match="gain_range"):
        gym.make("AerialLoc/Small-v3", exposure={"gain_range": [4.0, 0.5]})
    with pytest.raises(ConfigError, match="airlight_rgb"):
        gym.make("AerialLoc/Small-v3", haze={"airlight_rgb": [300.0, 0.0, 0.0]})
    assert GimbalConfig().draw_attitude(np.random.default_rng(0), 3, 0.25).shape == (3, 2)


ALL_ON = {"perspective": {"enabled": True}, "gimbal": {"roll_pitch_std_deg": 0.4, "heading_bias_std_deg": 2.0},
          "altimeter": {"bias_std_m": 2.0, "drift_std_m_per_sqrt_s": 0.2}, "exposure": {"strength": 0.8},
          "haze": {"extinction_per_km": 0.5}}


def test_checkers_pass_with_every_camera_error_on():
    check_env_silently("AerialLoc/Small-v3", **ALL_ON)


def test_every_camera_error_on_is_deterministic_and_pickles():
    import pickle

    a, ai = episode(**ALL_ON)
    b, bi = episode(**ALL_ON)
    assert same(a, b) and all(x["exposure_gain"] == y["exposure_gain"] for x, y in zip(ai, bi, strict=True))
    env = gym.make("AerialLoc/Small-v3", **ALL_ON)
    env.reset(seed=1)
    clone = pickle.loads(pickle.dumps(env.unwrapped))
    step = np.zeros(2, np.float32)
    assert np.array_equal(env.unwrapped.step(step)[0]["image"], clone.step(step)[0]["image"])
