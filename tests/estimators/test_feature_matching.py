"""estimators/feature_matching.py: ORB fixes at RealMap-v2's defaults over a map coarse for the footprint (it used
to see a 125 x 83 px frame with 0-3 keypoints and never fix), and the paper's geometry is unchanged."""

from __future__ import annotations

import math

import cv2
import gymnasium as gym
import numpy as np

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.config import build_config
from aerial_loc_env.env import world_to_action
from aerial_loc_env.estimators.feature_matching import FeatureMatchingAgent
from aerial_loc_env.estimators.registry import make_agent


def _coarse_map(folder):
    """A 400 m procedural city at 0.30 m/px (a US orthophoto's 1 ft), as a plain PNG."""
    from aerial_loc_env.world.city import CityConfig, default_city

    city = default_city(build_config(CityConfig, {"seed": 3, "width_m": 400.0, "height_m": 400.0, "gsd_m": 0.3}))
    png = folder / "coarse.png"
    cv2.imwrite(str(png), np.ascontiguousarray(np.asarray(city.rgb)[..., ::-1]))
    return png


def test_upsampling_only_where_the_working_image_is_too_small():
    agent = FeatureMatchingAgent()
    agent.level_gsd = (0.5, 0.5)
    assert agent.upsampling((300, 200), 0.25) == 1.0              # the paper's 600 x 400 camera at 200 m
    agent.level_gsd = (0.3, 0.3)
    assert agent.upsampling((125, 83), 0.104) == 200 / 83         # RealMap's camera over a 0.3 m map
    assert agent.upsampling((125, 83), 0.25) == 1.0               # 1.2: below MIN_UPSAMPLING
    assert agent.upsampling((125, 83), 0.15) == 2.0               # never finer than the camera's own pixels


def test_orb_fixes_at_realmap_defaults_over_a_coarse_map(tmp_path):
    env = gym.make("AerialLoc/RealMap-v2", path=str(_coarse_map(tmp_path)), map={"gsd_m": 0.3},
                   **{"flight.duration_s": 10.0})
    obs, info = env.reset(seed=0)
    agent = make_agent("features-orb")
    agent.reset(env.unwrapped.briefing, seed=0)
    assert agent.work_gsd_m == 0.3                               # the map's sampling: 125 x 83 px frames
    statuses, errors, ups = [], [], []
    while True:
        est = agent.step(obs)
        statuses.append(est.status)
        errors.append(math.hypot(est.x_m - info["true_pose"][0], est.y_m - info["true_pose"][1]))
        ups.append(est.extras.get("upsampling"))
        obs, _, term, trunc, info = env.step(np.clip(world_to_action(env.unwrapped.briefing.orthomap, est.x_m,
                                                                     est.y_m), -1, 1))
        if term or trunc:
            break
    env.close()
    fixes = [s == "ok" for s in statuses]
    assert np.mean(fixes) > 0.3, statuses
    assert all(u and u > 2.0 for u, ok in zip(ups, fixes, strict=True) if ok)
    assert np.median([e for e, ok in zip(errors, fixes, strict=True) if ok]) < 1.0
