"""Run a grid: each episode is rendered once and every agent of the grid runs on it in lockstep.

The unit of work is one (scenario, seed) episode with the agents that still lack a row for it, so that
resuming after an interruption re-renders only what is needed and never repeats a finished trial.

Every agent sees the same frames (read-only views: an agent that writes into its observation fails loudly
instead of corrupting its neighbours'). The env's early-failure termination is switched off for benchmark
episodes (it would depend on whichever agent's estimate is passed as the action), so every trial runs to the
end of the track; the action passed is the first agent's estimate, clipped to the map. Agents are reset with
the episode's seed, so a trial is fully determined by (agent spec, scenario spec, seed).
"""

from __future__ import annotations

import json
import math
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .. import __version__
from ..errors import ConfigError
from .grid import AgentEntry, Grid, ScenarioEntry
from .metrics import MetricConfig, trial_metrics
from .store import TrialStore, trial_key, write_summaries


@dataclass(frozen=True)
class EpisodeTask:
    """One episode to render and the agents (with their trial keys) to run on it."""

    scenario: ScenarioEntry
    seed: int
    agents: tuple[AgentEntry, ...]
    keys: tuple[str, ...]
    metric: MetricConfig
    agent_configs: tuple[dict, ...] = ()   # the resolved specs (stored in each row, so any row can be re-run)
    scenario_config: dict | None = None


# ----------------------------------------------------------------------------------------- spec resolution
def resolve_agent(entry: AgentEntry) -> dict[str, Any]:
    """The full agent configuration of ``entry`` (spec class + its [params] with the overrides on top).

    Building the agent validates the parameters, so a typo fails here, before any episode is rendered.
    """
    from ..estimators.registry import SHORT_NAMES, AgentSpec, build_agent, load_spec, merge_params

    dotted = ":" in entry.name and not entry.name.endswith(".toml")
    spec = AgentSpec(entry.name, entry.name) if dotted or entry.name in SHORT_NAMES else load_spec(entry.name)
    build_agent(spec, **entry.params)
    return {"name": entry.name, "class": spec.class_ref, "params": merge_params(spec.params, entry.params)}


def resolve_scenario(entry: ScenarioEntry) -> dict[str, Any]:
    """The full validated scenario spec of ``entry`` (every section with every default), as a plain dict,
    with the simulator's ``generators`` versions and the ``fingerprint`` of both (``env.fingerprint``)."""
    import aerial_loc_env  # noqa: F401  (registers the scenarios)

    from ..env import load_scenario
    from ..env.fingerprint import fingerprint, generator_versions

    out = load_scenario(entry.id, entry.overrides).to_dict()
    out.pop("description", None)
    # the generation of the simulator is part of the trial key: a resumed run never mixes generations
    versions = generator_versions()
    out["fingerprint"] = fingerprint(out, versions)
    out["generators"] = versions
    return out


def _jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, sort_keys=True, default=str))


# ----------------------------------------------------------------------------------------- one episode
_ENV_CACHE: dict[str, Any] = {}


def make_benchmark_env(scenario: ScenarioEntry, *, shadow_mask: bool = False) -> Any:
    """The env of ``scenario`` for benchmark episodes: failure termination off (every trial runs to the end);
    ``shadow_mask`` adds the ground-truth mask to ``info`` (oracles, plots). Cached per process."""
    import aerial_loc_env  # noqa: F401

    from ..env import AerialLocEnv, load_scenario

    overrides = dict(scenario.overrides)
    sc = load_scenario(scenario.id, overrides)
    if sc.episode.failure_error_m > 0.0:
        overrides["episode.failure_error_m"] = 0.0
    if shadow_mask and not sc.observation.info_shadow_mask:
        overrides["observation.info_shadow_mask"] = True
    cache_key = json.dumps({"id": scenario.id, "o": overrides}, sort_keys=True, default=str)
    env = _ENV_CACHE.get(cache_key)
    if env is None:
        if len(_ENV_CACHE) >= 4:
            _ENV_CACHE.pop(next(iter(_ENV_CACHE))).close()
        env = _ENV_CACHE[cache_key] = AerialLocEnv(load_scenario(scenario.id, overrides))
    return env


def _read_only(obs: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {}
    for k, v in obs.items():
        view = np.asarray(v).view()
        view.flags.writeable = False
        out[k] = view
    return out


def run_episode(task: EpisodeTask) -> tuple[list[dict], list[dict]]:
    """Render one episode and run every agent of ``task`` on it.

    Returns (rows, failures): one row per agent that finished, one failure record per agent that raised
    (the others go on; a failure is not a finished trial, so a re-run tries it again).
    """
    from ..env import world_to_action
    from ..estimators.registry import make_agent

    agents = [make_agent(a.name, **a.params) for a in task.agents]
    n = len(agents)
    alive = [True] * n
    failures: list[dict] = []
    errors: list[list[float]] = [[] for _ in range(n)]
    step_times: list[list[float]] = [[] for _ in range(n)]
    # CPU seconds of this thread (the workers run one numeric thread each): unlike wall time, not inflated by
    # other load on the machine. thread_time, not process_time: that one costs 0.1-5 ms a call on some VMs.
    cpu_times = [0.0] * n
    env_cpu_s = 0.0
    shadow_pairs: list[list[float]] = [[] for _ in range(n)]
    t_s: list[float] = []
    shadow_fraction: list[float] = []

    def fail(i: int, stage: str, exc: BaseException) -> None:
        alive[i] = False
        failures.append({"key": task.keys[i], "agent": task.agents[i].display,
                         "scenario": task.scenario.display, "seed": task.seed, "stage": stage,
                         "error": f"{type(exc).__name__}: {exc}", "traceback": traceback.format_exc(limit=8)})

    oracle = any(getattr(a, "uses_ground_truth", False) for a in agents)
    try:
        env = make_benchmark_env(task.scenario, shadow_mask=oracle)
        obs, info = env.reset(seed=task.seed)
    except Exception as exc:  # noqa: BLE001 (a bad episode fails its trials, not the whole grid)
        for i in range(n):
            fail(i, "env reset", exc)
        return [], failures
    briefing = env.briefing
    for i, agent in enumerate(agents):
        try:
            agent.reset(briefing, seed=task.seed)
        except Exception as exc:  # noqa: BLE001 (one broken agent must not sink the others' trials)
            fail(i, "reset", exc)

    def step_all(obs: Mapping[str, np.ndarray], info: Mapping[str, Any]) -> np.ndarray:
        """Every live agent estimates on this frame; returns the action (the first agent's estimate)."""
        truth = info["true_pose"]
        t_s.append(float(info.get("time_s", len(t_s) * briefing.dt_s)))
        shadow_fraction.append(float(info.get("shadow_fraction", 0.0)))
        frame = _read_only(obs)
        action = None
        for i, agent in enumerate(agents):
            if not alive[i]:
                continue
            try:
                c0 = time.thread_time()
                t0 = time.perf_counter()
                est = agent.step(frame, info if getattr(agent, "uses_ground_truth", False) else None)
                step_times[i].append(time.perf_counter() - t0)
                cpu_times[i] += time.thread_time() - c0
            except Exception as exc:  # noqa: BLE001
                fail(i, f"step {len(t_s) - 1}", exc)
                continue
            errors[i].append(math.hypot(est.x_m - truth[0], est.y_m - truth[1]))
            stats = est.extras.get("stats", {}) if est.extras else {}
            k = stats.get("num_pairs", stats.get("K"))
            if "shadow_pairs" in stats and k:
                shadow_pairs[i].append(stats["shadow_pairs"] / k)
            if action is None:
                action = world_to_action(briefing.orthomap, est.x_m, est.y_m)
        if action is None:
            return np.zeros(2, np.float32)
        return np.clip(np.asarray(action, np.float32), -1.0, 1.0)

    done = False
    while any(alive):
        action = step_all(obs, info)  # the last frame is an observation too: agents estimate on it
        if done:
            break
        c0 = time.thread_time()
        try:
            obs, _reward, terminated, truncated, info = env.step(action)
        except Exception as exc:  # noqa: BLE001
            for i in range(n):
                if alive[i]:
                    fail(i, f"env step {len(t_s)}", exc)
            break
        env_cpu_s += time.thread_time() - c0
        done = terminated or truncated
    rows = []
    t_arr = np.asarray(t_s)
    for i, entry in enumerate(task.agents):
        if not alive[i]:
            continue
        m = trial_metrics(np.asarray(errors[i]), t_arr, np.asarray(step_times[i]), task.metric)
        rows.append({
            "key": task.keys[i],
            "agent": entry.display,
            "scenario": task.scenario.display,
            "seed": task.seed,
            "agent_spec": entry.spec(),
            "scenario_spec": task.scenario.spec(),
            "agent_config": task.agent_configs[i] if task.agent_configs else None,
            "scenario_config": task.scenario_config,
            "version": __version__,
            **m,
            "cpu_time_total_s": cpu_times[i],
            "episode_render_cpu_s": env_cpu_s,
            "shadow_pairs_normalized": float(np.mean(shadow_pairs[i])) if shadow_pairs[i] else float("nan"),
            "shadow_fraction_mean": float(np.mean(shadow_fraction)),
            "t_s": [round(x, 4) for x in t_s],
            "errors_m": [round(float(x), 4) for x in errors[i]],
            "shadow_pairs_series": [round(float(x), 4) for x in shadow_pairs[i]],
        })
    return rows, failures


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
                    tuple(res.agent_configs[ai] for ai in todo), res.scenario_configs[si]))
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
             progress: bool = True) -> list[dict]:
    """Run what is not done yet of ``grid`` into ``out_dir``; return all rows of this grid (in grid order).

    Finished trials are appended to ``out_dir/trials.jsonl`` as each episode ends; agents that raised are
    logged in ``failures.jsonl`` (and retried by a re-run). Raises ``ConfigError`` up front for a bad agent
    or scenario spec, before any rendering.
    """
    from .executors import get_executor

    store = TrialStore(out_dir)
    resolved = resolve_grid(grid)
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


# ----------------------------------------------------------------------------------------- recorded episodes
def record_episode(scenario: ScenarioEntry, seed: int, agent: AgentEntry) -> dict[str, Any]:
    """One agent on one episode, keeping what the track figure needs: the true and estimated tracks, the
    final particles and weights, the last frame's ground-truth shadow mask, pose and the env (for the map)."""
    from ..estimators.registry import make_agent

    env = make_benchmark_env(scenario, shadow_mask=True)
    obs, info = env.reset(seed=seed)
    ag = make_agent(agent.name, **agent.params)
    ag.reset(env.briefing, seed=seed)
    truth: list[np.ndarray] = []
    est_xy: list[tuple[float, float]] = []
    done = False
    while True:
        est = ag.step(_read_only(obs), info if getattr(ag, "uses_ground_truth", False) else None)
        truth.append(np.asarray(info["true_pose"], float))
        est_xy.append((est.x_m, est.y_m))
        if done:
            break
        obs, _r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        done = terminated or truncated
    extras = est.extras or {}
    return {"env": env, "truth": np.array(truth), "estimates": np.array(est_xy),
            "particles": extras.get("particles"), "weights": extras.get("weights"),
            "shadow_mask": info.get("shadow_mask"), "image": obs["image"], "info": info,
            "briefing": env.briefing}
