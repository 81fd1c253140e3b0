"""One benchmark episode: rendered once, every agent of the grid run on it in lockstep by the episode driver.

The unit of work is one (scenario, seed) episode with the agents that still lack a row for it, so that
resuming after an interruption re-renders only what is needed and never repeats a finished trial.

``aerial_loc_env.estimators.episode.EpisodeDriver`` owns the time line, the read-only frames, the oracle gate
and the timing; this module turns its records into trial rows. The env's early-failure termination is
switched off for benchmark episodes (it would depend on whichever agent's estimate is passed as the action),
so every trial runs to the end of the track. Agents are reset with the episode's seed, so a trial is fully
determined by (agent spec, scenario spec, seed).

With ``detector_quality`` (the grid's option) each frame's image shadow detection (``ShadowDetector``, default
config) is scored against the simulator's ground-truth mask, and each row of the episode gets the means over its
frames (``DETECTOR_COLUMNS``): how well shadows can be found from the image alone on that scenario.
"""

from __future__ import annotations

import json
import traceback
from dataclasses import dataclass
from typing import Any

import numpy as np

from aerial_loc_env.benchmark.grid import AgentEntry, ScenarioEntry
from aerial_loc_env.benchmark.metrics import MetricConfig, fix_rate, trial_metrics
from aerial_loc_env.version import __version__


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
    detector_quality: bool = False          # score the image shadow detector against the true masks


#: row columns of ``detector_quality``: ``mask_quality``'s figures (means over the episode's frames)
DETECTOR_COLUMNS = {"iou": "detector_iou", "precision": "detector_precision", "recall": "detector_recall",
                    "fraction_true": "shadow_fraction_true", "fraction_predicted": "shadow_fraction_detected"}


_ENV_CACHE: dict[str, Any] = {}


def make_benchmark_env(scenario: ScenarioEntry, *, shadow_mask: bool = False) -> Any:
    """The env of ``scenario`` for benchmark episodes: failure termination off (every trial runs to the end);
    ``shadow_mask`` adds the ground-truth mask to ``info`` (oracles, plots). Cached per process."""
    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.env import AerialLocEnv, load_scenario

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


def run_episode(task: EpisodeTask) -> tuple[list[dict], list[dict]]:
    """Render one episode and run every agent of ``task`` on it.

    Returns (rows, failures): one row per agent that finished, one failure record per agent that raised
    (the others go on; a failure is not a finished trial, so a re-run tries it again).
    """
    from aerial_loc_env.estimators.episode import EpisodeDriver, needs_ground_truth
    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.estimators.shadow_detection import ShadowDetector, mask_quality

    agents = [make_agent(a.name, **a.params) for a in task.agents]
    n = len(agents)

    def failure(i: int, stage: str, error: str, trace: str) -> dict:
        return {"key": task.keys[i], "agent": task.agents[i].display, "scenario": task.scenario.display,
                "seed": task.seed, "stage": stage, "error": error, "traceback": trace}

    try:
        env = make_benchmark_env(task.scenario, shadow_mask=needs_ground_truth(agents) or task.detector_quality)
    except Exception as exc:  # noqa: BLE001 (a bad episode fails its trials, not the whole grid)
        trace = traceback.format_exc(limit=8)
        return [], [failure(i, "env reset", f"{type(exc).__name__}: {exc}", trace) for i in range(n)]
    errors: list[list[float]] = [[] for _ in range(n)]
    step_times: list[list[float]] = [[] for _ in range(n)]
    # CPU seconds of this thread (the workers run one numeric thread each): unlike wall time, not inflated by
    # other load on the machine.
    cpu_times = [0.0] * n
    shadow_pairs: list[list[float]] = [[] for _ in range(n)]
    statuses: list[list[str]] = [[] for _ in range(n)]
    t_s: list[float] = []
    shadow_fraction: list[float] = []
    detector = ShadowDetector() if task.detector_quality else None
    quality: list[dict[str, float]] = []
    env_cpu_s = 0.0
    with EpisodeDriver(env, agents, isolate_failures=True) as driver:
        for rec in driver.episode(task.seed):
            t_s.append(rec.time_s)
            shadow_fraction.append(float(rec.info.get("shadow_fraction", 0.0)))
            env_cpu_s += rec.env_cpu_s
            if detector is not None:
                quality.append(mask_quality(detector.detect(rec.observation["image"]).full(), rec.info["shadow_mask"]))
            for i, est in enumerate(rec.estimates):
                if est is None:
                    continue
                errors[i].append(rec.error_m(i))
                statuses[i].append(est.status)
                step_times[i].append(rec.wall_s[i])
                cpu_times[i] += rec.cpu_s[i]
                stats = est.extras.get("stats", {}) if est.extras else {}
                k = stats.get("num_pairs", stats.get("K"))
                if "shadow_pairs" in stats and k:
                    shadow_pairs[i].append(stats["shadow_pairs"] / k)
    failures = [failure(f.agent, f.stage, f.error, f.traceback) for f in driver.failures]
    metric = task.metric.for_scenario(env.scenario)   # thresholds scaled with the scenario unless fixed
    rows = []
    t_arr = np.asarray(t_s)
    detector_columns = {column: float(np.mean([q[k] for q in quality])) if quality else float("nan")
                        for k, column in DETECTOR_COLUMNS.items()} if detector is not None else {}
    for i, entry in enumerate(task.agents):
        if not driver.alive[i]:
            continue
        m = trial_metrics(np.asarray(errors[i]), t_arr, np.asarray(step_times[i]), metric)
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
            "fix_rate": fix_rate(statuses[i]),
            "cpu_time_total_s": cpu_times[i],
            "episode_render_cpu_s": env_cpu_s,
            "shadow_pairs_normalized": float(np.mean(shadow_pairs[i])) if shadow_pairs[i] else float("nan"),
            "shadow_fraction_mean": float(np.mean(shadow_fraction)),
            **detector_columns,
            "t_s": [round(x, 4) for x in t_s],
            "errors_m": [round(float(x), 4) for x in errors[i]],
            "shadow_pairs_series": [round(float(x), 4) for x in shadow_pairs[i]],
        })
    return rows, failures


def record_episode(scenario: ScenarioEntry, seed: int, agent: AgentEntry) -> dict[str, Any]:
    """One agent on one episode, keeping what the track figure needs: the true and estimated tracks, the
    final particles and weights, the last frame's ground-truth shadow mask, pose and the env (for the map)."""
    from aerial_loc_env.estimators.episode import EpisodeDriver
    from aerial_loc_env.estimators.registry import make_agent

    env = make_benchmark_env(scenario, shadow_mask=True)
    with EpisodeDriver(env, [make_agent(agent.name, **agent.params)]) as driver:
        records = driver.run(seed)
    last = records[-1]
    extras = last.estimates[0].extras or {}
    return {"env": env, "truth": np.array([r.true_pose for r in records]),
            "estimates": np.array([(r.estimates[0].x_m, r.estimates[0].y_m) for r in records]),
            "particles": extras.get("particles"), "weights": extras.get("weights"),
            "shadow_mask": last.info.get("shadow_mask"), "image": np.array(last.observation["image"]),
            "info": last.info, "briefing": driver.briefing}
