"""Observation designs that let a policy learn, as Gymnasium wrappers over ``AerialLocEnv``.

- ``local_registration``: the policy sees the camera image beside the database crop rendered at the
  dead-reckoned pose, at the same scale and heading (the briefing's camera model, so the same footprint and
  pixel grid), and outputs a bounded correction in metres in the vehicle's frame (forward, right). The
  estimate is ``dead-reckoned + correction`` and the next step's prediction starts from it. Nothing ties it to
  one map, so it can generalize to maps it never saw. With a zero correction it *is* dead reckoning: the
  prediction is ``estimators.dead_reckoning.DeadReckoningAgent``'s, step for step.
- ``map_memorization`` (PoseNet-style): the camera image alone; the action is the absolute position
  (the env's own action). It can only work on the one fixed map it was trained on.

The same ``LocalRegistration`` object drives the training wrapper and the deployed ``LearnedAgent``, so the
policy sees at test time exactly what it saw in training.

Rewards (training only; the env's own reward is ignored): ``"improvement"`` pays the error reduction the
correction achieved over the dead-reckoned prediction, minus ``error_weight`` times the remaining error (both
over ``scale_m`` of the recipe's ``[train.reward]``): the per-step signal is attributable to the action, and the
sum still rewards a low error all along. ``"error"`` is the env's ``-error / scale_m``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import cv2
import gymnasium as gym
import numpy as np

from aerial_loc_env.env import world_to_action
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.database import database_renderer
from aerial_loc_env.estimators.dead_reckoning import DeadReckoningAgent
from aerial_loc_env.estimators.protocol import parse_observation
from aerial_loc_env.learning.recipes import ObservationParams, RewardParams
from aerial_loc_env.sensors.camera import Pose
from aerial_loc_env.sensors.render import CameraRenderer


def square_image(image: np.ndarray, side: int, grayscale: bool) -> np.ndarray:
    """The policy's view of an RGB image: ``side`` x ``side`` (area resampling), optionally grey (H, W, 1)."""
    out = image if image.shape[:2] == (side, side) else cv2.resize(image, (side, side),
                                                                  interpolation=cv2.INTER_AREA)
    if grayscale:
        out = cv2.cvtColor(out, cv2.COLOR_RGB2GRAY)[..., None]
    return np.ascontiguousarray(out)


def image_space(params: ObservationParams) -> gym.spaces.Box:
    channels = 1 if params.grayscale else 3
    return gym.spaces.Box(0, 255, (params.image_px, params.image_px, channels), np.uint8)


class LocalRegistration:
    """Dead reckoning plus learned corrections: the state a local-registration policy needs."""

    def __init__(self, params: ObservationParams):
        self.params = params
        self.observation_space = gym.spaces.Dict({"image": image_space(params), "map": image_space(params)})
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self._renderer: CameraRenderer | None = None
        self._dr = DeadReckoningAgent()
        self.predicted = np.zeros(2)
        self.yaw = 0.0
        self.altitude = 1.0

    @property
    def xy(self) -> np.ndarray:
        """The current estimate (metres)."""
        return self._dr.xy.copy()

    def reset(self, briefing: Any, start_xy_m: tuple[float, float] | None = None) -> None:
        """Start from the prior's mean (or ``start_xy_m``: the training curriculum's own start)."""
        if briefing.prior.kind != "gaussian":
            raise ConfigError(f"local_registration: scenario {briefing.scenario_id} has a "
                              f"{briefing.prior.kind} prior; this observation design tracks from a "
                              "gaussian prior (episode.start = 'tracking'); use map_memorization for "
                              "global localization")
        self.briefing = briefing
        self._renderer = database_renderer(briefing.orthomap, briefing.camera, strict=False)   # (or by window)
        self._dr.reset(briefing)
        if start_xy_m is not None:
            self._dr.anchor(start_xy_m)

    def observe(self, observation: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Predict with the odometry (dead reckoning from the last estimate), then build the policy's view of
        the camera and of the database there."""
        if self._renderer is None:
            raise ConfigError("LocalRegistration.observe called before reset(briefing)")
        self._dr.step(observation)
        obs = parse_observation(observation)
        self.yaw, self.altitude = obs.yaw_rad, obs.altitude_m
        self.predicted = self._dr.xy.copy()
        side, gray = self.params.image_px, self.params.grayscale
        pose = Pose(float(self.predicted[0]), float(self.predicted[1]), self.yaw, self.altitude)
        crop = self._renderer.database_patch(pose)
        return {"image": square_image(obs.image, side, gray), "map": square_image(crop, side, gray)}

    def correct(self, action: np.ndarray) -> np.ndarray:
        """Apply the policy's correction (forward, right) in [-1, 1] x max_correction_m; return the estimate
        (kept on the map)."""
        a = np.clip(np.asarray(action, dtype=float).reshape(2), -1.0, 1.0) * self.params.max_correction_m
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        xy = self.predicted + a[0] * np.array([c, s]) + a[1] * np.array([s, -c])
        m = self.briefing.orthomap
        self._dr.anchor(np.clip(xy, [0.0, 0.0], [m.width_m, m.height_m]))
        return self._dr.xy.copy()


class LocalRegistrationWrapper(gym.Wrapper):
    """Training wrapper around a tracking scenario (see the module docstring for the reward).

    ``info`` gains ``registration_error_m`` (after the correction) and ``dead_reckoning_error_m`` (of the
    plain dead-reckoning agent on the same episode); at the episode's end also ``episode_rmse_m`` and
    ``dead_reckoning_rmse_m``, so that Monitor files and evaluations compare the two. ``start_std_m``, if > 0,
    replaces the prior's error by the policy's own draw around the truth (a curriculum; training only).
    """

    def __init__(self, env: gym.Env, params: ObservationParams | None = None,
                 reward: RewardParams | None = None, start_std_m: float = 0.0):
        super().__init__(env)
        self.core = LocalRegistration(params or ObservationParams())
        self.observation_space = self.core.observation_space
        self.action_space = self.core.action_space
        self.reward = reward or RewardParams()
        self.start_std_m = start_std_m
        self._dr = DeadReckoningAgent()
        self._truth = np.zeros(2)
        self._rng = np.random.default_rng(0)
        self._sq: list[float] = []
        self._sq_dr: list[float] = []

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        if seed is not None:
            self._rng = np.random.default_rng([seed, 7])
        briefing = self.env.unwrapped.briefing
        self._truth = np.asarray(info["true_pose"][:2], dtype=float)
        start = None
        if self.start_std_m > 0.0:
            start = tuple(self._truth + self._rng.normal(0.0, self.start_std_m, 2))
        self.core.reset(briefing, start)
        self._dr.reset(briefing)
        if start is not None:
            self._dr.anchor(start)
        self._dr.step(obs)
        self._sq, self._sq_dr = [], []
        return self.core.observe(obs), info

    def step(self, action):
        before = float(np.hypot(*(self.core.predicted - self._truth)))
        xy = self.core.correct(action)
        error = float(np.hypot(*(xy - self._truth)))
        dr_error = float(np.hypot(*(self._dr.xy - self._truth)))
        self._sq.append(error ** 2)
        self._sq_dr.append(dr_error ** 2)
        env_action = world_to_action(self.env.unwrapped.briefing.orthomap, xy[0], xy[1])
        obs, _r, terminated, truncated, info = self.env.step(np.clip(env_action, -1.0, 1.0))
        info = dict(info, registration_error_m=error, dead_reckoning_error_m=dr_error)
        self._truth = np.asarray(info["true_pose"][:2], dtype=float)
        self._dr.step(obs)
        policy_obs = self.core.observe(obs)
        if terminated or truncated:
            info["episode_rmse_m"] = math.sqrt(float(np.mean(self._sq)))
            info["dead_reckoning_rmse_m"] = math.sqrt(float(np.mean(self._sq_dr)))
        rw = self.reward
        if rw.kind == "improvement":
            reward = (before - error - rw.error_weight * error) / rw.scale_m
        else:
            reward = -error / rw.scale_m
        return policy_obs, float(reward), terminated, truncated, info


class MapMemorizationWrapper(gym.ObservationWrapper):
    """PoseNet-style: only the camera image, resized; the action is the env's absolute-position action."""

    def __init__(self, env: gym.Env, params: ObservationParams | None = None):
        super().__init__(env)
        self.params = params or ObservationParams()
        self.observation_space = gym.spaces.Dict({"image": image_space(self.params)})

    def observation(self, observation: Mapping[str, Any]) -> dict[str, np.ndarray]:
        return {"image": square_image(np.asarray(observation["image"]), self.params.image_px,
                                      self.params.grayscale)}


OBSERVATION_WRAPPERS = {"local_registration": LocalRegistrationWrapper,
                        "map_memorization": MapMemorizationWrapper}


def wrap(env: gym.Env, observation: str, params: ObservationParams, reward: RewardParams | None = None,
         start_std_m: float = 0.0) -> gym.Env:
    """The training wrapper of an observation design (names in ``OBSERVATION_WRAPPERS``)."""
    if observation == "local_registration":
        return LocalRegistrationWrapper(env, params, reward, start_std_m)
    if observation == "map_memorization":
        return MapMemorizationWrapper(env, params)
    raise ConfigError(f"unknown observation design {observation!r}; "
                      f"use one of {sorted(OBSERVATION_WRAPPERS)}")


__all__ = ["LocalRegistration", "LocalRegistrationWrapper", "MapMemorizationWrapper", "RewardParams",
           "square_image", "wrap"]
