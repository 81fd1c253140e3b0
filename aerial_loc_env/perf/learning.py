"""Learned-policy speed on one core: what bounds a training run's steps per second.

- the local-registration training env (Small-v3, 64 px camera + database crop at the dead-reckoned pose),
  one call = one whole episode (reset amortized), figures per step;
- the PPO policy's (recipe defaults: correlation CNN) deterministic ``predict`` on one observation (the
  deployed agent's cost per step);
- one PPO gradient step on a 256-sample minibatch of image pairs (the update's cost, per sample).

A training run's rate is roughly 1 / (env step / n_envs-in-parallel + n_epochs x update per sample).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aerial_loc_env.perf import Benchmark

BATCH = 256


def _episode_steps() -> int:
    from aerial_loc_env.env.scenarios import load_scenario

    return load_scenario("AerialLoc/Small-v3").flight.steps


def _wrapped_env():
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.learning.observations import LocalRegistrationWrapper
    from aerial_loc_env.learning.recipes import ObservationParams

    return LocalRegistrationWrapper(gym.make("AerialLoc/Small-v3"), ObservationParams(image_px=64))


def _episode_setup() -> Callable[[], object]:
    env = _wrapped_env()
    seeds = iter(range(10**9))
    action = np.zeros(2, np.float32)

    def episode() -> int:
        env.reset(seed=next(seeds))
        while True:
            _, _, term, trunc, _ = env.step(action)
            if term or trunc:
                return 0

    return episode


def _model():
    import torch

    from aerial_loc_env.learning.recipes import recipe_from_table
    from aerial_loc_env.learning.train import policy_kwargs

    torch.set_num_threads(1)
    from stable_baselines3 import PPO

    recipe = recipe_from_table({"hyperparameters": {"n_steps": BATCH, "batch_size": BATCH}}, "perf")
    env = _wrapped_env()
    return PPO("MultiInputPolicy", env, policy_kwargs=policy_kwargs(recipe), n_steps=BATCH, batch_size=BATCH,
               seed=0, device="cpu"), env


def _predict_setup() -> Callable[[], object]:
    model, env = _model()
    obs, _ = env.reset(seed=0)
    return lambda: model.predict(obs, deterministic=True)


def _update_setup() -> Callable[[], object]:
    import torch

    model, env = _model()
    obs, _ = env.reset(seed=0)
    batch = {k: np.repeat(v[None], BATCH, axis=0) for k, v in obs.items()}
    tensors, _ = model.policy.obs_to_tensor(batch)
    actions = torch.zeros((BATCH, 2))
    opt = model.policy.optimizer

    def update() -> None:
        values, log_prob, entropy = model.policy.evaluate_actions(tensors, actions)
        loss = -log_prob.mean() + values.pow(2).mean() - 0.0 * entropy.mean()
        opt.zero_grad()
        loss.backward()
        opt.step()

    return update


BENCHMARKS = [
    Benchmark(name="learning: local-registration env Small-v3 64 px (per step, resets amortized)",
              setup=_episode_setup, unit="step", repeats=5, per_call_items=_episode_steps()),
    Benchmark(name="learning: PPO correlation-CNN predict, one 64 px pair", setup=_predict_setup, unit="step",
              repeats=50),
    Benchmark(name=f"learning: PPO correlation-CNN gradient step, {BATCH} pairs of 64 px (per sample)",
              setup=_update_setup, unit="sample", repeats=5, per_call_items=BATCH),
]
