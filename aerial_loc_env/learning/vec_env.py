"""stable-baselines3's ``VecEnv`` over ``env.vector.EnvShards``: the training envs in lockstep over one process per
core, the learner's process stepping a block itself (``[train] vectorization = "vector"``).

SB3 takes its own VecEnv API, not Gymnasium's ``VectorEnv``: a finished episode resets in the same step, its last
observation in ``info["terminal_observation"]`` and ``info["TimeLimit.truncated"]`` set; ``seed(s)`` seeds the
next reset of sub-env ``i`` with ``s + i``. ``ShardVecEnv`` returns what SB3's ``SubprocVecEnv`` returns for the
same sub-envs, value for value and dtype for dtype (rewards float64, as its ``np.stack`` of Python floats), so a
recipe trains the same model with either; it only spreads the sub-envs over fewer processes.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from aerial_loc_env.env.vector import EnvShards
from aerial_loc_env.errors import require_extra

_vec = require_extra("stable_baselines3.common.vec_env", "rl", "Training")


def _step(env: gym.Env, put: Callable[[Any], None], action: Any) -> tuple:
    """SB3's step of one sub-env (as SubprocVecEnv's worker): done, terminal observation, reset in the step."""
    obs, reward, terminated, truncated, info = env.step(action)
    done = terminated or truncated
    info["TimeLimit.truncated"] = truncated and not terminated
    reset_info = None
    if done:
        info["terminal_observation"] = obs
        obs, reset_info = env.reset()
    put(obs)
    return reward, done, info, reset_info


def _step_shared(env: gym.Env, put: Any) -> tuple:
    """``_step`` with the sub-env's row of the shared actions (``EnvShards.actions``)."""
    return _step(env, put, put.action())


def _get_attr(env: gym.Env, put: Callable[[Any], None], name: str) -> Any:
    return env.get_wrapper_attr(name)


def _has_attr(env: gym.Env, put: Callable[[Any], None], name: str) -> bool:
    try:
        env.get_wrapper_attr(name)
    except AttributeError:
        return False
    return True


def _set_attr(env: gym.Env, put: Callable[[Any], None], name: str, value: Any) -> None:
    setattr(env, name, value)


def _env_method(env: gym.Env, put: Callable[[Any], None], name: str, args: tuple, kwargs: dict) -> Any:
    return env.get_wrapper_attr(name)(*args, **kwargs)


def _is_wrapped(env: gym.Env, put: Callable[[Any], None], wrapper_class: type) -> bool:
    from stable_baselines3.common.env_util import is_wrapped

    return is_wrapped(env, wrapper_class)


def _copy(views: Any) -> Any:
    if isinstance(views, dict):
        return {key: np.array(value, copy=True) for key, value in views.items()}
    if isinstance(views, tuple):
        return tuple(np.array(value, copy=True) for value in views)
    return np.array(views, copy=True)


class ShardVecEnv(_vec.VecEnv):
    """SB3 VecEnv of the sub-envs ``env_fns`` (see the module doc); ``processes``: how many processes step them,
    the learner's included (default: one per usable core, at most the number of sub-envs); ``start_method``:
    forkserver where available, as SB3's SubprocVecEnv (the learner's torch threads make fork unsafe)."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], processes: int | None = None,
                 start_method: str | None = None) -> None:
        import multiprocessing as mp

        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        self._shards = EnvShards(env_fns, processes, start_method=start_method, where="training envs")
        self._actions: Any = None
        super().__init__(len(env_fns), self._shards.observation_space, self._shards.action_space)

    @property
    def processes(self) -> int:
        """How many processes step the sub-envs (the learner's included)."""
        return self._shards.processes

    def _each(self, fn: Callable[..., Any], *args: Any, indices: Any = None) -> list[Any]:
        chosen = set(self._get_indices(indices))
        res = self._shards.run([("apply", fn, *args) if i in chosen else ("none",) for i in range(self.num_envs)])
        return [res[i] for i in sorted(chosen)]

    def reset(self) -> Any:
        infos = self._shards.run([("reset", self._seeds[i], self._options[i] or None)
                                  for i in range(self.num_envs)])
        self.reset_infos = list(infos)
        self._reset_seeds()
        self._reset_options()
        return _copy(self._shards.views)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = actions

    def step_wait(self) -> Any:
        actions, self._actions = self._actions, None
        if self._shards.share_actions(actions):
            commands = [("apply", _step_shared)] * self.num_envs
        else:
            commands = [("apply", _step, actions[i]) for i in range(self.num_envs)]
        results = self._shards.run(commands)
        rewards, dones, infos = [], [], []
        for i, (reward, done, info, reset_info) in enumerate(results):
            rewards.append(reward)
            dones.append(done)
            infos.append(info)
            if reset_info is not None:
                self.reset_infos[i] = reset_info
        return _copy(self._shards.views), np.stack(rewards), np.stack(dones), infos

    def close(self) -> None:
        self._shards.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        if self.render_mode != "rgb_array":
            return [None] * self.num_envs
        return self.env_method("render")

    def has_attr(self, attr_name: str) -> bool:
        return all(self._each(_has_attr, attr_name))

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return self._each(_get_attr, attr_name, indices=indices)

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        self._each(_set_attr, attr_name, value, indices=indices)

    def env_method(self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any) -> list[Any]:
        return self._each(_env_method, method_name, method_args, method_kwargs, indices=indices)

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: Any = None) -> list[bool]:
        return self._each(_is_wrapped, wrapper_class, indices=indices)
