"""The typed configs (``config.build_config``): NumPy scalars are numbers of the field's type."""

from __future__ import annotations

import gymnasium as gym
import numpy as np

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.config import build_config
from aerial_loc_env.sensors.flight import FlightConfig


def test_numpy_scalars_are_numbers():
    cfg = build_config(FlightConfig, {"altitude_m": np.float32(120), "min_steps": np.int64(4)})
    assert cfg.altitude_m == 120.0 and type(cfg.altitude_m) is float
    assert cfg.min_steps == 4 and type(cfg.min_steps) is int
    env = gym.make("AerialLoc/Small-v1", altitude_m=np.float32(110.0))
    assert env.unwrapped.scenario.flight.altitude_m == 110.0
    env.close()
