"""Vectorized env throughput on ``AerialLoc/Small-v3``: one env alone, then N = 2 and 4 sub-envs in Gymnasium's
``sync`` and ``async`` modes and in the ``vector_entry_point`` mode (``env/vector.py``), each as steps per second
by the wall clock (the work of the async and vector_entry_point modes runs in other processes) and as its rate over
one env's, a call of the one env timed after each call of the row (the target: the fastest at least 1.5x one env on
2 cores).

The training rows time the shipped recipe's envs (``ppo-local-registration``: Small-v3 behind the local-registration
observation, 64 px) through stable-baselines3's VecEnv API, one env alone and N = 4 in each of the recipes'
vectorizations (``learning.recipes.VECTORIZATIONS``): what a training run's env steps cost.

The vector_entry_point env also runs N = 8 and 16: its lockstep's fixed cost per tick (the commands, the batching,
the copies in the caller) spreads over more sub-envs per process, as with the 8-16 envs a training run steps.

A call runs ``TICKS`` lockstep steps of the vector env (zero actions; next-step autoreset, so a tick of a sub-env
whose episode ended is its reset); one env runs the same schedule (a step, or a reset after its episode's end),
so every row counts the same work per item. The vector envs use their defaults (vector_entry_point: one process
per usable core, at most N). These rows need the machine's other cores idle; their figures are in
docs/perf-log.md and the README ("Vectorized environments").
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aerial_loc_env.perf import Benchmark

SCENARIO = "AerialLoc/Small-v3"
TICKS = 60          # lockstep steps per call (one Small-v3 episode)
ONE_ENV = "vector: one env Small-v3 (per step)"


def _one_env_setup() -> Callable[[], object]:
    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.env import AerialLocEnv

    env = AerialLocEnv(SCENARIO)
    env.reset(seed=0)
    action = np.zeros(2, np.float32)
    done = [False]

    def ticks() -> None:
        for _ in range(TICKS):
            if done[0]:
                env.reset()
                done[0] = False
            else:
                _, _, term, trunc, _ = env.step(action)
                done[0] = term or trunc

    return ticks


def _vector_setup(mode: str, num_envs: int) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        import gymnasium as gym

        import aerial_loc_env.env  # noqa: F401  (registers the scenarios)

        envs = gym.make_vec(SCENARIO, num_envs=num_envs, vectorization_mode=mode)
        envs.reset(seed=0)
        actions = np.zeros((num_envs, 2), np.float32)

        def ticks() -> None:
            for _ in range(TICKS):
                envs.step(actions)

        return ticks

    return setup


def _row(mode: str, num_envs: int) -> Benchmark:
    return Benchmark(name=f"vector: {mode} N={num_envs} Small-v3 (per sub-env step)",
                     setup=_vector_setup(mode, num_envs), unit="step", repeats=15,
                     per_call_items=TICKS * num_envs, clock="wall", baseline=ONE_ENV,
                     baseline_target=1.5 if mode == "vector_entry_point" else None)


def _training_recipe(vectorization: str | None, n_envs: int):
    import dataclasses

    from aerial_loc_env.estimators.registry import load_spec
    from aerial_loc_env.learning.train import recipe_of

    recipe = recipe_of(load_spec(TRAINING_SPEC))
    return dataclasses.replace(recipe, vectorization=vectorization, subproc=None, n_envs=n_envs)


def _one_training_env_setup() -> Callable[[], object]:
    from aerial_loc_env.learning.train import make_env

    env = make_env(_training_recipe(None, 1))
    env.reset(seed=0)
    action = np.zeros(2, np.float32)

    def steps() -> None:
        for _ in range(TICKS):
            _, _, term, trunc, _ = env.step(action)
            if term or trunc:
                env.reset()

    return steps


def _training_setup(vectorization: str, n_envs: int) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.learning.train import _vec_env

        envs = _vec_env(_training_recipe(vectorization, n_envs), None)
        envs.reset()
        actions = np.zeros((n_envs, 2), np.float32)

        def steps() -> None:
            for _ in range(TICKS):
                envs.step(actions)

        return steps

    return setup


#: the training rows: the shipped recipe's envs (local registration, 64 px) through SB3's VecEnv API
TRAINING_SPEC = "ppo-local-registration"
ONE_TRAINING_ENV = "vector: one training env ppo-local-registration (per step)"

BENCHMARKS = [
    Benchmark(name=ONE_ENV, setup=_one_env_setup, unit="step", repeats=15, per_call_items=TICKS, clock="wall"),
    *[_row(mode, n) for mode in ("sync", "async") for n in (2, 4)],
    *[_row("vector_entry_point", n) for n in (2, 4, 8, 16)],
    Benchmark(name=ONE_TRAINING_ENV, setup=_one_training_env_setup, unit="step", repeats=10, per_call_items=TICKS,
              clock="wall"),
    *[Benchmark(name=f"vector: training envs {kind} N=4 (per sub-env step)", setup=_training_setup(kind, 4),
                unit="step", repeats=10, per_call_items=TICKS * 4, clock="wall", baseline=ONE_TRAINING_ENV)
      for kind in ("dummy", "subproc", "vector")],
]
