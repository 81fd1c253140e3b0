"""The agent protocol (``estimators/protocol.py``): every agent kind refuses frames of another scenario than the
one whose briefing it was reset with, saying what differs."""

from __future__ import annotations

import gymnasium as gym
import pytest

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.registry import make_agent


@pytest.mark.parametrize("agent", ["template-ncc", "features-orb", "mcl-ssd"])
def test_agent_fed_another_scenarios_frames_says_what_differs(agent):
    a = gym.make("AerialLoc/Small-v3")
    b = gym.make("AerialLoc/Small-v3", observation={"width_px": 48, "height_px": 32})
    _, info = a.reset(seed=0)
    obs_b, _ = b.reset(seed=0)
    est = make_agent(agent, **({"n_particles": 50} if agent.startswith("mcl") else {}))
    est.reset(a.unwrapped.briefing, seed=0)
    with pytest.raises(ConfigError, match=r"48 x 32.*64 x 64"):
        est.step(obs_b)
    a.close()
    b.close()
