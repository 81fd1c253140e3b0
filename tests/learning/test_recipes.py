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


@pytest.mark.parametrize("table, kind", [
    ({}, "vector"),                                        # the default: the fastest (README, perf/vector.py)
    ({"vectorization": "dummy"}, "dummy"),
    ({"subproc": True, "n_envs": 4}, "subproc"),           # the older spelling still reads as before
    ({"subproc": True, "n_envs": 1}, "dummy"),
    ({"subproc": False, "n_envs": 4}, "dummy"),
    ({"subproc": True, "vectorization": "subproc"}, "subproc"),
])
def test_recipe_vectorization(table, kind):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.recipes import recipe_from_table

    assert recipe_from_table(table, "r.toml").vec_env == kind


@pytest.mark.parametrize("table, words", [
    ({"vectorization": "threads"}, ["r.toml [train]", "'vectorization' = 'threads'", "'vector', 'subproc', 'dummy'"]),
    ({"subproc": False, "vectorization": "vector"}, ["'subproc' = false", "'vectorization' = 'vector'", "disagree",
                                                      "keep only vectorization"]),
])
def test_bad_vectorization_is_a_clear_error(table, words):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.recipes import recipe_from_table

    with pytest.raises(ConfigError) as err:
        recipe_from_table(table, "r.toml")
    for w in words:
        assert w in str(err.value), (w, str(err.value))
