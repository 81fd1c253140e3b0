"""Benchmark-harness speed: whole episodes of the experiments as ``run_episode`` runs them (one render shared
by every agent of the grid), per episode on one core. Multiply by episodes / cores for an experiment's time:
Table 5 is 100 such episodes with its 12 configurations; the default comparison is 10 with its 7 agents.
"""

from __future__ import annotations

from collections.abc import Callable

from aerial_loc_env.perf import Benchmark


def _episode_setup(experiment: str) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.benchmark.grid import load_grid
        from aerial_loc_env.benchmark.runner import plan, run_episode

        tasks = plan(load_grid(experiment), set())
        it = iter(range(10**9))
        return lambda: run_episode(tasks[next(it) % len(tasks)])

    return setup


BENCHMARKS = [
    Benchmark("bench: Table 5 episode (240 frames rendered once, 12 MCL configurations)",
              _episode_setup("table5"), unit="episode", repeats=3),
    Benchmark("bench: default-comparison episode (240 frames, 7 agents)", _episode_setup("default"),
              unit="episode", repeats=3),
]
