"""Wrappers: metres actions score like the normalized ones; episode error statistics match the step errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env import InvalidActionError
from aerial_loc_env.env.wrappers import EpisodeErrorStats, MetresAction


def test_metres_action_scores_the_given_position():
    env = MetresAction(gym.make("AerialLoc/Small-v3", duration_s=2.0))
    _, info = env.reset(seed=0)
    truth = info["true_pose"]
    _, _, _, _, info = env.step(np.array([truth[0] + 3.0, truth[1] + 4.0], np.float32))
    assert info["position_error_m"] == pytest.approx(5.0, abs=0.05)
    assert env.action_space.high == pytest.approx([env.unwrapped.orthomap.width_m,
                                                   env.unwrapped.orthomap.height_m])
    with pytest.raises(InvalidActionError):
        env.step(np.zeros(3, np.float32))


def test_episode_error_stats():
    env = EpisodeErrorStats(gym.make("AerialLoc/Small-v3", duration_s=2.0))
    env.reset(seed=1)
    errors, done, rng = [], False, np.random.default_rng(0)
    while not done:
        _, _, term, trunc, info = env.step(rng.uniform(-1, 1, 2).astype(np.float32))
        errors.append(info["position_error_m"])
        done = term or trunc
    stats = info["episode_error"]
    assert stats["steps"] == len(errors) == 8
    assert stats["mean_m"] == pytest.approx(np.mean(errors))
    assert stats["rmse_m"] == pytest.approx(np.sqrt(np.mean(np.square(errors))))
    assert stats["final_m"] == errors[-1]
