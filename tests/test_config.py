"""The typed configs (``config.build_config``): NumPy scalars are numbers of the field's type; command-line
``KEY=VALUE`` overrides (``config.parse_assignments``)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.sensors.flight import FlightConfig


def test_numpy_scalars_are_numbers():
    cfg = build_config(FlightConfig, {"altitude_m": np.float32(120), "min_steps": np.int64(4)})
    assert cfg.altitude_m == 120.0 and type(cfg.altitude_m) is float
    assert cfg.min_steps == 4 and type(cfg.min_steps) is int
    env = gym.make("AerialLoc/Small-v3", altitude_m=np.float32(110.0))
    assert env.unwrapped.scenario.flight.altitude_m == 110.0
    env.close()


def test_command_line_assignments_are_read_as_json_where_they_parse():
    from aerial_loc_env.config import parse_assignments

    got = parse_assignments(["flight.altitude_m=150", "map.path=tile.tif", "shadows.database_sun_deg=[150, 50]",
                             "observation.info_shadow_mask=true"], where="gap: --set", example="a=1")
    assert got == {"flight.altitude_m": 150, "map.path": "tile.tif", "shadows.database_sun_deg": [150, 50],
                   "observation.info_shadow_mask": True}
    with pytest.raises(ConfigError, match=r"gap: --set 'altitude' must look like KEY=VALUE \(e.g. a=1\)"):
        parse_assignments(["altitude"], where="gap: --set", example="a=1")
