"""Small generic wrappers over ``AerialLocEnv`` (policy-specific observation designs live in ``learning``).

- ``MetresAction``: act in world metres ``(x_m, y_m)`` instead of the normalized action (for estimators and
  scripts; converts with ``world_to_action``).
- ``EpisodeErrorStats``: at the end of an episode, ``info["episode_error"]`` holds the mean, RMSE, 95th
  percentile and final horizontal error (metres) of the episode's estimates: loggable with SB3's
  ``Monitor(env, info_keywords=("episode_error",))`` or read by scripts.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from aerial_loc_env.env.aerial_loc_env import world_to_action


class MetresAction(gym.ActionWrapper):
    """The action is the position estimate in world metres, ``Box([0, 0], [width_m, height_m])``."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        om = env.unwrapped.orthomap
        self.action_space = gym.spaces.Box(np.float32([0.0, 0.0]), np.float32([om.width_m, om.height_m]),
                                           dtype=np.float32)

    def action(self, action: Any) -> np.ndarray:
        a = np.asarray(action)
        if a.shape != (2,) or not np.issubdtype(a.dtype, np.floating):
            # let the env produce its clear error for the raw input
            return a
        return world_to_action(self.env.unwrapped.orthomap, a[0], a[1])


class EpisodeErrorStats(gym.Wrapper):
    """Collects each step's ``position_error_m``; adds ``info["episode_error"]`` when the episode ends."""

    def __init__(self, env: gym.Env) -> None:
        super().__init__(env)
        self._errors: list[float] = []

    def reset(self, **kwargs: Any):
        self._errors = []
        return self.env.reset(**kwargs)

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self._errors.append(float(info["position_error_m"]))
        if terminated or truncated:
            e = np.asarray(self._errors)
            info = {**info, "episode_error": {
                "mean_m": float(e.mean()), "rmse_m": float(np.sqrt(np.mean(e * e))),
                "p95_m": float(np.percentile(e, 95)), "final_m": float(e[-1]), "steps": int(e.size)}}
        return obs, reward, terminated, truncated, info
