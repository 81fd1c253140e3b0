"""Training recipes (``learning/recipes.py``): SB3 hyperparameters and the scenario are validated with clear errors."""

from __future__ import annotations

import pytest

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.errors import ConfigError


@pytest.mark.parametrize("hyper, words", [
    ({"learning_rate": "fast"}, ["learning_rate", "'fast'", "number"]),
    ({"batch_size": 0}, ["batch_size", "0", ">= 1"]),
    ({"n_steps": 1.5}, ["n_steps", "integer"]),
    ({"gamma": 2.0}, ["gamma", "[0, 1]"]),
])
def test_sb3_hyperparameter_values_are_validated(hyper, words):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.recipes import recipe_from_table

    with pytest.raises(ConfigError) as err:
        recipe_from_table({"hyperparameters": hyper}, "r.toml")
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_recipe_scenario_that_does_not_exist():
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.recipes import recipe_from_table

    with pytest.raises(ConfigError, match=r"r\.toml.*scenario.*AerialLoc/Nope-v0.*registered"):
        recipe_from_table({"scenario": "AerialLoc/Nope-v0"}, "r.toml")
