"""A trained SB3 policy as an agent of the common protocol, runnable in the benchmark beside the filters.

The spec names the model file; its recipe (observation design, image size, correction bound) is read from the
``training.json`` that ``aerial-loc train`` writes beside it, so the policy sees exactly what it saw in
training. ``predict`` is deterministic by default (evaluation).

Model paths: absolute, or relative to the ``aerial_loc_env`` package folder when the file is there (models
shipped as package data under ``aerial_loc_env/models/``, so a spec works from any working directory and from
an installed wheel), else relative to the current directory (e.g. ``runs/<recipe>/model.zip`` after training).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.env import action_to_world
from aerial_loc_env.errors import ConfigError, require_extra
from aerial_loc_env.estimators.protocol import Agent, Estimate, parse_observation, prior_estimate
from aerial_loc_env.learning.observations import LocalRegistration, square_image
from aerial_loc_env.learning.recipes import algo_class
from aerial_loc_env.learning.train import check_model_zip, load_training_meta
from aerial_loc_env.paths import find_model_file

_MODELS: dict[tuple[str, float], Any] = {}


@dataclass(frozen=True)
class LearnedParams:
    model: str = "models/ppo-local-registration/model.zip"   # a model saved by `aerial-loc train`
    deterministic: bool = True
    #: torch intra-op threads for predict (0 = leave torch's setting): one sample per step gains nothing from
    #: more, and on busy cores two threads make a step orders of magnitude slower by spin-waiting
    torch_threads: int = field(default=1, metadata=rng(0, 256))


def resolve_model_path(model: str) -> Path:
    """The model file: absolute, else under the package folder, else under the current directory."""
    return find_model_file(model, "learned agent: params.model", "train it with `aerial-loc train <recipe> --out "
                           "<folder>` and point params.model to <folder>/model.zip")


class LearnedAgent(Agent):
    """Runs a policy trained by ``aerial-loc train`` (see the module docstring)."""

    Params = LearnedParams

    def __init__(self, params: LearnedParams = LearnedParams()):
        self.params = params
        self.path = resolve_model_path(params.model)
        self.recipe, self.training = load_training_meta(self.path)
        self.model = self._model()
        self._core: LocalRegistration | None = None

    def _model(self) -> Any:
        """The SB3 model, loaded once per process (agents built for many episodes share it)."""
        key = (str(self.path), self.path.stat().st_mtime)
        if self.params.torch_threads > 0:
            require_extra("torch", "rl", "Learned policies").set_num_threads(self.params.torch_threads)
        if key not in _MODELS:
            check_model_zip(self.path, f"learned agent: params.model ({self.recipe.algo})")
            try:
                _MODELS[key] = algo_class(self.recipe.algo).load(str(self.path), device="cpu")
            except (ValueError, KeyError, OSError, RuntimeError) as exc:
                raise ConfigError(f"learned agent: cannot load the {self.recipe.algo} model '{self.path}': "
                                  f"{exc}") from exc
        return _MODELS[key]

    def reset(self, briefing: Any, *, seed: int | None = None) -> Estimate:
        self.briefing = briefing
        if self.recipe.observation == "local_registration":
            self._core = LocalRegistration(self.recipe.observation_params)
            self._core.reset(briefing)
        return prior_estimate(briefing)

    def policy_observation(self, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """What the policy sees for this env observation (advances the dead reckoning by one step). Frames
        that cannot come from the briefed scenario are refused, as by every agent (``parse_observation``)."""
        if not hasattr(self, "briefing"):
            raise ConfigError("LearnedAgent.step called before reset(briefing, seed=...)")
        parse_observation(observation, self.briefing, self.altitude_range_m(self.briefing), type(self).__name__)
        if self._core is not None:
            return self._core.observe(observation)
        p = self.recipe.observation_params
        return {"image": square_image(np.asarray(observation["image"]), p.image_px, p.grayscale)}

    def step(self, observation: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> Estimate:
        policy_obs = self.policy_observation(observation)
        action, _ = self.model.predict(policy_obs, deterministic=self.params.deterministic)
        if self._core is not None:
            x, y = self._core.correct(action)
            return Estimate(float(x), float(y), yaw_rad=float(self._core.yaw))
        x, y = action_to_world(self.briefing.orthomap, np.clip(np.asarray(action, dtype=float), -1.0, 1.0))
        return Estimate(float(x), float(y))
