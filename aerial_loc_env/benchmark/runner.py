"""Run a grid: each episode is rendered once and every agent of the grid runs on it in lockstep.

The unit of work is one (scenario, seed) episode with the agents that still lack a row for it, so that
resuming after an interruption re-renders only what is needed and never repeats a finished trial.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from .. import __version__
from .grid import AgentEntry, Grid, ScenarioEntry
from .metrics import MetricConfig, trial_metrics
from .store import TrialStore, trial_key, write_summaries


@dataclass(frozen=True)
class EpisodeTask:
    scenario: ScenarioEntry
    seed: int
    agents: tuple[AgentEntry, ...]
    metric: MetricConfig


def _horizontal_error(est, truth_xy: tuple[float, float]) -> float:
    return math.hypot(est.x_m - truth_xy[0], est.y_m - truth_xy[1])


def run_episode(task: EpisodeTask) -> list[dict]:
    """Render one episode and run every agent of ``task`` on it; one result row per agent."""
    import gymnasium as gym

    import aerial_loc_env  # noqa: F401  (registers the scenarios in a fresh worker)

    from ..env import world_to_action
    from ..estimators.registry import make_agent

    env = gym.make(task.scenario.id, **task.scenario.overrides)
    try:
        obs, info = env.reset(seed=task.seed)
        base = env.unwrapped
        briefing = base.briefing
        agents = [make_agent(a.name, **a.params) for a in task.agents]
        for agent in agents:
            agent.reset(briefing, seed=task.seed)
        n = len(agents)
        errors: list[list[float]] = [[] for _ in range(n)]
        step_times: list[list[float]] = [[] for _ in range(n)]
        shadow_pairs: list[list[float]] = [[] for _ in range(n)]
        t_s: list[float] = []
        shadow_fraction: list[float] = []
        while True:
            truth = info["true_pose"]
            t_s.append(float(info.get("time_s", len(t_s) * briefing.dt_s)))
            shadow_fraction.append(float(info.get("shadow_fraction", 0.0)))
            first_action = None
            for i, agent in enumerate(agents):
                agent_info = info if getattr(agent, "uses_ground_truth", False) else None
                t0 = time.perf_counter()
                est = agent.step(obs, agent_info)
                step_times[i].append(time.perf_counter() - t0)
                errors[i].append(_horizontal_error(est, (truth[0], truth[1])))
                stats = est.extras.get("stats", {}) if est.extras else {}
                if "shadow_pairs" in stats and stats.get("num_pairs"):
                    shadow_pairs[i].append(stats["shadow_pairs"] / stats["num_pairs"])
                if first_action is None:
                    first_action = world_to_action(base.briefing.orthomap, est.x_m, est.y_m)
            obs, _reward, terminated, truncated, info = env.step(first_action)
            if terminated or truncated:
                break
    finally:
        env.close()
    rows = []
    t_arr = np.asarray(t_s)
    for i, entry in enumerate(task.agents):
        m = trial_metrics(np.asarray(errors[i]), t_arr, np.asarray(step_times[i]), task.metric)
        rows.append({
            "key": trial_key(entry.spec(), task.scenario.spec(), task.seed),
            "agent": entry.display,
            "scenario": task.scenario.display,
            "seed": task.seed,
            "agent_spec": entry.spec(),
            "scenario_spec": task.scenario.spec(),
            "version": __version__,
            **m,
            "shadow_pairs_normalized": float(np.mean(shadow_pairs[i])) if shadow_pairs[i] else float("nan"),
            "shadow_fraction_mean": float(np.mean(shadow_fraction)),
            "t_s": [round(x, 4) for x in t_s],
            "errors_m": [round(float(x), 4) for x in errors[i]],
        })
    return rows


def plan(grid: Grid, done: set[str]) -> list[EpisodeTask]:
    """The episodes still to run, each with only the agents that lack a row."""
    metric = MetricConfig(converge_threshold_m=grid.converge_threshold_m)
    tasks = []
    for scenario in grid.scenarios:
        for seed in grid.seeds:
            todo = tuple(a for a in grid.agents if trial_key(a.spec(), scenario.spec(), seed) not in done)
            if todo:
                tasks.append(EpisodeTask(scenario, seed, todo, metric))
    return tasks


class Progress:
    """A one-line progress bar with ETA on stderr (quiet when not a terminal, except every 10 %)."""

    def __init__(self, total: int, label: str, stream=sys.stderr):
        self.total, self.label, self.stream = max(total, 1), label, stream
        self.done, self.t0, self._last_decile = 0, time.monotonic(), -1

    def update(self, n: int = 1) -> None:
        self.done += n
        elapsed = time.monotonic() - self.t0
        eta = elapsed / self.done * (self.total - self.done) if self.done else float("nan")
        frac = self.done / self.total
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        line = f"{self.label} [{bar}] {self.done}/{self.total} episodes, {elapsed:5.0f} s, ETA {eta:5.0f} s"
        if self.stream.isatty():
            self.stream.write("\r" + line + ("\n" if self.done >= self.total else ""))
        elif int(frac * 10) != self._last_decile or self.done >= self.total:
            self._last_decile = int(frac * 10)
            self.stream.write(line + "\n")
        self.stream.flush()


Executor = Callable[[Sequence[EpisodeTask], Callable[[list[dict]], None], int], None]


def run_grid(grid: Grid, out_dir: str, *, workers: int = 1, executor: str | Executor = "local",
             progress: bool = True) -> list[dict]:
    """Run what is not done yet of ``grid`` into ``out_dir``; return all rows of this grid."""
    from .executors import get_executor

    store = TrialStore(out_dir)
    tasks = plan(grid, store.done_keys())
    bar = Progress(len(tasks), grid.name) if progress and tasks else None

    def on_result(rows: list[dict]) -> None:
        for row in rows:
            store.append(row)
        if bar:
            bar.update()

    run = get_executor(executor) if isinstance(executor, str) else executor
    if tasks:
        run(tasks, on_result, workers)
    wanted = {trial_key(a.spec(), s.spec(), seed) for a in grid.agents for s in grid.scenarios for seed in grid.seeds}
    all_rows = store.rows()
    write_summaries(all_rows, store.out_dir)
    return [r for r in all_rows if r.get("key") in wanted]


def rows_by(rows: Iterable[dict], *keys: str) -> dict[tuple, list[dict]]:
    out: dict[tuple, list[dict]] = {}
    for r in rows:
        out.setdefault(tuple(r[k] for k in keys), []).append(r)
    return out
