"""Env speed: steps per second on one core, resets included (one call = one whole episode).

Targets (issue 12, ratios to the floor, one bare map warp): the paper's 600 x 400 camera with cast shadows
<= 2.5x per step; the small learned-policy observation (64 x 64) <= 0.5x per step. Each call resets with a new
seed (track, sun, shadows over the track's region, noise bank) and steps to the end of the track, so the per-step
figure amortizes the reset.

A PaperShadows step is the frame (perf/render.py's baked path), the baked tiles the flight reaches (each map tile
read from memory, shaded in one compiled pass, the grid block resized under it), the reset amortized over the
track's steps (the noise bank's normal draws, the shadow sweep, the first frame's tiles) and the env's own
bookkeeping. The harness's untimed first call (a whole episode) compiles the kernels. The figures, and where a
step's time goes, are in docs/perf-log.md.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from aerial_loc_env.perf import Benchmark


def _episode_setup(scenario: str, **overrides) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
        from aerial_loc_env.env import AerialLocEnv

        env = AerialLocEnv(scenario, **overrides)
        action = np.zeros(2, np.float32)
        seeds = iter(range(10**9))

        def episode() -> int:
            env.reset(seed=next(seeds))
            n = 0
            while True:
                _, _, term, trunc, _ = env.step(action)
                n += 1
                if term or trunc:
                    return n

        return episode

    return setup


def _reset_setup(scenario: str) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
        from aerial_loc_env.env import AerialLocEnv

        env = AerialLocEnv(scenario)
        seeds = iter(range(10**9))
        return lambda: env.reset(seed=next(seeds))

    return setup


def _steps(scenario: str) -> int:
    from aerial_loc_env.env.scenarios import load_scenario

    return load_scenario(scenario).flight.steps


BENCHMARKS = [
    Benchmark(name="env episode PaperShadows 600x400 + cast shadows (per step)",
              setup=_episode_setup("AerialLoc/PaperShadows-v2"), target_ratio=2.5, unit="step", repeats=5,
              per_call_items=_steps("AerialLoc/PaperShadows-v2")),
    Benchmark(name="env episode Small 64x64 + cast shadows (per step)",
              setup=_episode_setup("AerialLoc/Small-v3"), target_ratio=0.5, unit="step", repeats=20,
              per_call_items=_steps("AerialLoc/Small-v3")),
    Benchmark(name="env reset PaperShadows (track, sun, shadows over the track box, frame 0)",
              setup=_reset_setup("AerialLoc/PaperShadows-v2"), target_ratio=None, unit="reset", repeats=10),
    Benchmark(name="env episode CloudShadows 600x400 (per step)",
              setup=_episode_setup("AerialLoc/CloudShadows-v2"), target_ratio=None, unit="step", repeats=5,
              per_call_items=_steps("AerialLoc/CloudShadows-v2")),
]
