"""The motion models use the odometry's lateral speed: a crabbing vehicle is dead-reckoned where it goes (MCL's
particles, dead reckoning and its covariance, every agent built on them), not along its nose."""

from __future__ import annotations

import math
from types import SimpleNamespace

import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env  # noqa: F401
from aerial_loc_env.env.briefing import OdometryNoise, Prior
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.dead_reckoning import DeadReckoningAgent
from aerial_loc_env.estimators.episode import EpisodeDriver
from aerial_loc_env.estimators.mcl.motion import OdometryMotionModel
from aerial_loc_env.estimators.protocol import Observation, parse_observation

DT = 0.25
HEADING = 0.3                 # rad, held
FORWARD, LATERAL = 21.4, -5.0  # body frame, m/s: a crab to the right


def _obs(forward: float = FORWARD, lateral: float = LATERAL, yaw: float = HEADING) -> dict:
    return {"image": np.zeros((4, 4, 3), np.uint8), "odometry": np.array([forward, 0.0, lateral], np.float32),
            "yaw": np.array([yaw], np.float32), "altitude": np.array([100.0], np.float32)}


def _briefing(noise: OdometryNoise) -> SimpleNamespace:
    return SimpleNamespace(prior=Prior("gaussian", (500.0, 500.0), 5.0), dt_s=DT, odometry_noise=noise,
                           orthomap=None, camera=None, altitude_m=100.0, scenario_id="test")


def _truth(steps: int) -> np.ndarray:
    c, s = math.cos(HEADING), math.sin(HEADING)
    return np.array([500.0, 500.0]) + steps * DT * np.array([FORWARD * c - LATERAL * s, FORWARD * s + LATERAL * c])


def test_dead_reckoning_follows_a_crab_and_its_covariance_grows_across_the_body_too():
    noise = OdometryNoise(speed_std_mps=0.1, lateral_std_mps=0.3, heading_std_rad=0.0)
    dr = DeadReckoningAgent()
    dr.reset(_briefing(noise))
    steps = 80
    for _ in range(steps + 1):                               # the first frame is the start pose
        est = dr.step(_obs())
    # 20 s of a 5 m/s crab: 100 m to the right of the nose; float32 odometry keeps it to millimetres
    assert np.hypot(*(est.xy_m - _truth(steps))) < 0.01
    # the covariance: the prior's 25 m^2 plus, per step, each speed's noise along its own body axis
    c, s = math.cos(HEADING), math.sin(HEADING)
    rot = np.array([[c, -s], [s, c]])
    grown = rot @ np.diag([(0.1 * DT) ** 2, (0.3 * DT) ** 2]) @ rot.T * steps
    np.testing.assert_allclose(est.cov_xy_m2, 25.0 * np.eye(2) + grown, rtol=1e-5)


def test_the_mcl_motion_model_moves_particles_with_the_lateral_speed_and_its_noise():
    noise = OdometryNoise(speed_std_mps=0.0, yaw_rate_std_radps=0.0, heading_std_rad=0.0, lateral_std_mps=0.4)
    for state in ("xy", "xyyaw"):
        mm = OdometryMotionModel(noise, DT, state=state)
        states = np.zeros((40000, 3))
        states[:, :2] = 500.0
        states[:, 2] = HEADING
        mm.prev_yaw_rad = HEADING
        obs = parse_observation(_obs())
        mm.propagate(states, obs, np.random.default_rng(0))
        c, s = math.cos(HEADING), math.sin(HEADING)
        # the mean moves by the body-frame velocity rotated to the world, float32 odometry
        mean = states[:, :2].mean(axis=0)
        np.testing.assert_allclose(mean, _truth(1), atol=5 * 0.4 * DT / math.sqrt(40000) + 1e-5)
        # the spread lies along the body's left axis only, with the lateral noise's std
        d = states[:, :2] - mean
        across = d @ np.array([-s, c])
        along = d @ np.array([c, s])
        assert np.std(across) == pytest.approx(0.4 * DT, rel=5.0 / math.sqrt(2 * 40000))
        assert np.std(along) < 1e-9


def test_a_two_entry_odometry_names_the_v2_layout():
    obs = _obs()
    obs["odometry"] = np.array([FORWARD, 0.0], np.float32)
    with pytest.raises(ConfigError, match=r"lateral_speed_mps.*v2.*got shape \(2,\).*v1 observation"):
        parse_observation(obs)
    parsed = parse_observation(_obs())
    assert isinstance(parsed, Observation) and parsed.lateral_mps == LATERAL
    assert parsed.speed_mps == pytest.approx(FORWARD) and parsed.yaw_rate_radps == 0.0


class _NoLateral(gym.ObservationWrapper):
    """The odometry without its lateral term: the motion models as they were before it (the 'before' of a
    comparison)."""

    def observation(self, observation):
        odo = observation["odometry"].copy()
        odo[2] = 0.0
        return dict(observation, odometry=odo)


def _dr_drift_m(env: gym.Env, seed: int) -> float:
    """How far dead reckoning's error moves over an episode (its start error is the prior's draw)."""
    errs = []
    with EpisodeDriver(env, [DeadReckoningAgent()]) as driver:
        for rec in driver.episode(seed=seed):
            errs.append(np.asarray([rec.estimates[0].x_m, rec.estimates[0].y_m]) - rec.info["true_pose"][:2])
    return float(np.hypot(*(errs[-1] - errs[0])))


def test_dead_reckoning_in_a_steady_wind_drifts_only_by_the_noise_and_without_the_lateral_term_by_the_wind():
    """Small-v3 (20 m/s, 15 s) in 5 m/s of wind from the north: with the lateral speed the dead-reckoned error
    moves by the odometry noise alone (about 1 m over 60 steps); without it, by the crosswind over the flight."""
    wind = {"wind.speed_range_mps": [5.0, 5.0], "wind.from_deg_range": [0.0, 0.0]}
    with_lateral = [_dr_drift_m(gym.make("AerialLoc/Small-v3", **wind), s) for s in (0, 1)]
    without = [_dr_drift_m(_NoLateral(gym.make("AerialLoc/Small-v3", **wind)), s) for s in (0, 1)]
    assert max(with_lateral) < 4.0
    assert min(without) > 10.0
