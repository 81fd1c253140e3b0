"""Run a grid: resolve its specs, plan the episodes still to run, hand them to an executor, store the rows.

Each episode is rendered once and every agent of the grid runs on it in lockstep (``episodes.run_episode``);
a re-run plans only the trials without a row, so an interrupted run resumes where it stopped.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from aerial_loc_env.benchmark.episodes import EpisodeTask, run_episode
from aerial_loc_env.benchmark.executors import get_executor
from aerial_loc_env.benchmark.grid import AgentEntry, Grid, ScenarioEntry
from aerial_loc_env.benchmark.metrics import MetricConfig
from aerial_loc_env.benchmark.store import TrialStore, trial_key, write_summaries
from aerial_loc_env.errors import ConfigError


# ----------------------------------------------------------------------------------------- spec resolution
def resolve_agent(entry: AgentEntry) -> dict[str, Any]:
    """The full agent configuration of ``entry`` (spec class + its [params] with the overrides on top).

    Building the agent validates the parameters, so a typo fails here, before any episode is rendered.
    """
    from aerial_loc_env.estimators.registry import SHORT_NAMES, AgentSpec, build_agent, load_spec, merge_params

    dotted = ":" in entry.name and not entry.name.endswith(".toml")
    spec = AgentSpec(entry.name, entry.name) if dotted or entry.name in SHORT_NAMES else load_spec(entry.name)
    build_agent(spec, **entry.params)
    return {"name": entry.name, "class": spec.class_ref, "params": merge_params(spec.params, entry.params)}


def resolve_scenario(entry: ScenarioEntry) -> dict[str, Any]:
    """The full validated scenario spec of ``entry`` (every section with every default), as a plain dict,
    with the simulator's ``generators`` versions and the ``fingerprint`` of both (``env.fingerprint``)."""
    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.env import load_scenario
    from aerial_loc_env.env.fingerprint import fingerprint, generator_versions

    out = load_scenario(entry.id, entry.overrides).to_dict()
    out.pop("description", None)
    # the generation of the simulator is part of the trial key: a resumed run never mixes generations
    versions = generator_versions()
    out["fingerprint"] = fingerprint(out, versions)
    out["generators"] = versions
    return out


def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, sort_keys=True, default=str))


# ----------------------------------------------------------------------------------------- the grid
@dataclass(frozen=True)
class ResolvedGrid:
    """The grid's agents and scenarios resolved to full configs, and every trial's key."""

    agent_configs: tuple[dict, ...]
    scenario_configs: tuple[dict, ...]
    keys: Mapping[tuple[int, int, int], str]   # (scenario index, seed, agent index) -> trial key


def resolve_grid(grid: Grid) -> ResolvedGrid:
    """Resolve (and so validate) every agent and scenario of ``grid``. Trial keys come from the *resolved*
    configs: a changed spec file or default gives new trials instead of silently reusing stale rows, while a
    label or another spelling of the same parameters does not."""
    agents = tuple(_jsonable(resolve_agent(a)) for a in grid.agents)
    scenarios = tuple(_jsonable(resolve_scenario(s)) for s in grid.scenarios)
    keys = {(si, seed, ai): trial_key(agent, scenario, seed)
            for si, scenario in enumerate(scenarios) for seed in grid.seeds
            for ai, agent in enumerate(agents)}
    return ResolvedGrid(agents, scenarios, keys)


def plan(grid: Grid, done: set[str], resolved: ResolvedGrid | None = None) -> list[EpisodeTask]:
    """The episodes still to run, each with only the agents that lack a row."""
    res = resolve_grid(grid) if resolved is None else resolved
    metric = MetricConfig(converge_threshold_m=grid.converge_threshold_m,
                          diverge_threshold_m=grid.diverge_threshold_m)
    tasks = []
    for si, scenario in enumerate(grid.scenarios):
        for seed in grid.seeds:
            todo = [ai for ai in range(len(grid.agents)) if res.keys[si, seed, ai] not in done]
            if todo:
                tasks.append(EpisodeTask(
                    scenario, seed, tuple(grid.agents[ai] for ai in todo),
                    tuple(res.keys[si, seed, ai] for ai in todo), metric,
                    tuple(res.agent_configs[ai] for ai in todo), res.scenario_configs[si],
                    grid.detector_quality))
    return tasks


class Progress:
    """A one-line progress bar with ETA on stderr (on a non-terminal: a line every 10 % or 30 s)."""

    def __init__(self, total: int, label: str, stream: Any = None) -> None:
        self.total, self.label = max(total, 1), label
        self.stream = sys.stderr if stream is None else stream
        self.done, self.t0, self._last_decile, self._last_line = 0, time.monotonic(), -1, 0.0

    def update(self, n: int = 1) -> None:
        self.done += n
        elapsed = time.monotonic() - self.t0
        eta = elapsed / self.done * (self.total - self.done) if self.done else float("nan")
        frac = self.done / self.total
        bar = "#" * int(30 * frac) + "-" * (30 - int(30 * frac))
        line = f"{self.label} [{bar}] {self.done}/{self.total} episodes, {elapsed:5.0f} s, ETA {eta:5.0f} s"
        tty = getattr(self.stream, "isatty", lambda: False)()
        if tty:
            self.stream.write("\r" + line + ("\n" if self.done >= self.total else ""))
        elif (int(frac * 10) != self._last_decile or self.done >= self.total
              or elapsed - self._last_line >= 30):
            self._last_decile, self._last_line = int(frac * 10), elapsed
            self.stream.write(line + "\n")
        self.stream.flush()


Executor = Callable[[Sequence[EpisodeTask], Callable[[tuple[list[dict], list[dict]]], None], int], None]


def run_grid(grid: Grid, out_dir: str, *, workers: int = 1, executor: str | Executor = "local",
             progress: bool = True, add: bool = False) -> list[dict]:
    """Run what is not done yet of ``grid`` into ``out_dir``; return all rows of this grid (in grid order).

    Finished trials are appended to ``out_dir/trials.jsonl`` as each episode ends; agents that raised are
    logged in ``failures.jsonl`` (and retried by a re-run). Raises ``ConfigError`` up front for a bad agent
    or scenario spec, before any rendering; for a folder another run is using (it names that run's PID); and
    for a folder holding another experiment's results, unless ``add``.
    """
    store = TrialStore(out_dir)
    store.check(grid.name, add=add)       # a bad folder is refused before the specs are resolved
    resolved = resolve_grid(grid)
    with store.lock():
        store.claim(grid.name, add=add)
        return _run_locked(grid, store, resolved, workers, executor, progress)


def _run_locked(grid: Grid, store: TrialStore, resolved: ResolvedGrid, workers: int,
                executor: str | Executor, progress: bool) -> list[dict]:
    keys = resolved.keys
    tasks = plan(grid, store.done_keys(), resolved)
    bar = Progress(len(tasks), grid.name) if progress and tasks else None
    n_failed = 0

    def on_result(result: tuple[list[dict], list[dict]]) -> None:
        nonlocal n_failed
        rows, failures = result
        for row in rows:
            store.append(row)
        for failure in failures:
            store.append_failure(failure)
            n_failed += 1
            print(f"\n{grid.name}: {failure['agent']} on {failure['scenario']} seed {failure['seed']} "
                  f"failed at {failure['stage']}: {failure['error']}", file=sys.stderr)
        if bar:
            bar.update()

    run = get_executor(executor) if isinstance(executor, str) else executor
    if tasks:
        run(tasks, on_result, workers)
    order = {k: i for i, k in enumerate(sorted(keys, key=lambda t: (t[0], t[2], t[1])))}
    position = {keys[t]: order[t] for t in keys}
    rows = sorted((r for r in store.rows() if r.get("key") in position), key=lambda r: position[r["key"]])
    write_summaries(rows, store.out_dir)
    if n_failed:
        print(f"{grid.name}: {n_failed} trial(s) failed; see {store.failures_path}", file=sys.stderr)
    return rows


def rows_by(rows: Iterable[dict], *keys: str) -> dict[tuple, list[dict]]:
    out: dict[tuple, list[dict]] = {}
    for r in rows:
        out.setdefault(tuple(r[k] for k in keys), []).append(r)
    return out


def rerun_row(row: Mapping[str, Any]) -> dict:
    """Run the trial of a stored row again (same agent spec, scenario spec and seed): the same figures, apart
    from the wall-clock timing columns, as long as the package version and spec files are the same."""
    agent = AgentEntry(row["agent_spec"]["name"], dict(row["agent_spec"]["params"]), row["agent"])
    scenario = ScenarioEntry(row["scenario_spec"]["id"], dict(row["scenario_spec"]["overrides"]),
                             row["scenario"])
    grid = Grid(name="rerun", agents=(agent,), scenarios=(scenario,), seeds=(int(row["seed"]),))
    (task,) = plan(grid, set())
    rows, failures = run_episode(task)
    if failures:
        raise ConfigError(f"re-running trial {row['key']} failed: {failures[0]['error']}")
    return rows[0]
