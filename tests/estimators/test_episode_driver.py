"""The episode driver (estimators/episode.py): time line, read-only frames, oracle gate, timing, failures,
Agent.close, streaming; and the benchmark rows it gives are those of the loop it replaced.

``tests/data/driver_benchmark_rows.json`` holds the rows the benchmark's own loop gave before the driver
(3 seeds x 3 agents on a 13-frame episode, timing columns left out) and a digest of the episodes' frames.
After a deliberate change of the world, the renderer or the agents, write it again with
``python tests/estimators/test_episode_driver.py``.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from aerial_loc_env.benchmark.episodes import make_benchmark_env, record_episode, run_episode
from aerial_loc_env.benchmark.grid import AgentEntry, ScenarioEntry, make_grid
from aerial_loc_env.benchmark.metrics import trial_metrics
from aerial_loc_env.benchmark.runner import plan
from aerial_loc_env.estimators.episode import EpisodeDriver, oracle_info, read_only
from aerial_loc_env.estimators.protocol import Agent, Estimate, prior_estimate

FIXTURE = Path(__file__).resolve().parents[1] / "data" / "driver_benchmark_rows.json"
AGENTS = [{"name": "mcl-shadow-aware", "params": {"n_particles": 150}, "label": "sa"},
          {"name": "dead-reckoning", "label": "dr"},
          {"name": "mcl-shadow-aware-oracle", "params": {"n_particles": 150}, "label": "oracle"}]
TINY = {"id": "AerialLoc/Small-v3", "overrides": {"flight.duration_s": 3.0}, "label": "tiny"}
SEEDS = [0, 1, 2]
#: what the episode loop produces (the metrics derived from it, the timing, the key and the configs may change
#: for other reasons: a new metric definition, a key recipe, new default fields)
COMPARED = ("agent", "scenario", "seed", "agent_spec", "scenario_spec", "steps", "t_s", "errors_m",
            "shadow_pairs_series", "shadow_pairs_normalized", "shadow_fraction_mean")
N_FRAMES = 13   # 3 s at 4 Hz: 12 steps, 13 frames


def _plain(value):
    """JSON values with NaN as None (NaN != NaN would fail any comparison)."""
    return json.loads(json.dumps(value, sort_keys=True),
                      parse_constant=lambda c: None if c == "NaN" else float(c))


def _comparable(rows: list[dict]) -> list[dict]:
    return _plain([{k: r[k] for k in COMPARED} for r in rows])


def _tasks():
    return plan(make_grid("driver-fixture", AGENTS, [TINY], seeds=SEEDS), set())


def _rows() -> list[dict]:
    rows = []
    for task in _tasks():
        r, failures = run_episode(task)
        assert not failures, failures
        rows += r
    return rows


def _frames_digest() -> str:
    """A digest of every frame, measurement and true pose of the fixture's episodes (a plain env loop)."""
    h = hashlib.sha256()
    env = make_benchmark_env(ScenarioEntry(TINY["id"], dict(TINY["overrides"]), TINY["label"]), shadow_mask=True)
    for seed in SEEDS:
        obs, info = env.reset(seed=seed)
        while True:
            for key in sorted(obs):
                h.update(np.ascontiguousarray(obs[key]).tobytes())
            h.update(np.asarray(info["true_pose"], np.float64).tobytes())
            h.update(np.ascontiguousarray(info["shadow_mask"]).tobytes())
            obs, _r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
            if terminated or truncated:
                h.update(np.ascontiguousarray(obs["image"]).tobytes())
                break
    return h.hexdigest()


def _reference_rows(task) -> list[dict]:
    """The loop the benchmark ran before the driver, kept as the specification of the time line: every agent
    estimates on every frame (the last one too), the env steps on the first agent's estimate, clipped."""
    from aerial_loc_env.env import world_to_action
    from aerial_loc_env.estimators.registry import make_agent

    agents = [make_agent(a.name, **a.params) for a in task.agents]
    env = make_benchmark_env(task.scenario, shadow_mask=True)
    obs, info = env.reset(seed=task.seed)
    for agent in agents:
        agent.reset(env.briefing, seed=task.seed)
    errors = [[] for _ in agents]
    pairs = [[] for _ in agents]
    t_s, shade, done = [], [], False
    while True:
        t_s.append(info["time_s"])
        shade.append(info["shadow_fraction"])
        ests = [a.step(obs, info if a.uses_ground_truth else None) for a in agents]
        for i, est in enumerate(ests):
            errors[i].append(math.hypot(est.x_m - info["true_pose"][0], est.y_m - info["true_pose"][1]))
            stats = est.extras.get("stats", {})
            if "shadow_pairs" in stats and stats.get("num_pairs", stats.get("K")):
                pairs[i].append(stats["shadow_pairs"] / stats.get("num_pairs", stats.get("K")))
        if done:
            break
        action = np.clip(world_to_action(env.briefing.orthomap, ests[0].x_m, ests[0].y_m), -1, 1)
        obs, _r, terminated, truncated, info = env.step(np.asarray(action, np.float32))
        done = terminated or truncated
    out = []
    metric = task.metric.for_scenario(env.scenario)
    for i, entry in enumerate(task.agents):
        m = trial_metrics(np.asarray(errors[i]), np.asarray(t_s), np.zeros(len(t_s)), metric)
        out.append({"agent": entry.display, "seed": task.seed, "steps": m["steps"], "rmse_m": m["rmse_m"],
                    "final_error_m": m["final_error_m"], "time_to_converge_s": m["time_to_converge_s"],
                    "errors_m": [round(float(x), 4) for x in errors[i]], "t_s": [round(x, 4) for x in t_s],
                    "shadow_pairs_series": [round(float(x), 4) for x in pairs[i]],
                    "shadow_fraction_mean": float(np.mean(shade))})
    return out


def test_benchmark_rows_are_those_of_the_loop_before_the_driver():
    rows = _rows()
    assert len(rows) == 9 and all(r["steps"] == N_FRAMES for r in rows)
    reference = [r for task in _tasks() for r in _reference_rows(task)]
    assert _plain([{k: r[k] for k in ref} for r, ref in zip(rows, reference, strict=True)]) == _plain(reference)
    fixture = json.loads(FIXTURE.read_text())
    if fixture["frames_sha256"] == _frames_digest():
        assert _comparable(rows) == _comparable(fixture["rows"])
    else:  # the episodes themselves changed (world, renderer): the reference loop above is the check
        warnings.warn(f"{FIXTURE.name} was written for other frames; regenerate it: python {__file__}",
                      stacklevel=1)


# ------------------------------------------------------------------------------ the driver on its own
class Recorder(Agent):
    """Estimates the prior's mean shifted by a step counter; records what it was handed."""

    uses_ground_truth = False

    def __init__(self, fail_at: int | None = None, write: bool = False) -> None:
        self.fail_at, self.write = fail_at, write
        self.infos: list = []
        self.steps = 0
        self.closed = 0

    def reset(self, briefing, *, seed=None) -> Estimate:
        self.briefing, self.steps = briefing, 0
        return prior_estimate(briefing)

    def step(self, observation, info=None) -> Estimate:
        if self.write:
            observation["image"][0, 0, 0] = 7
        if self.fail_at is not None and self.steps == self.fail_at:
            raise RuntimeError("deliberate failure")
        self.infos.append(info)
        self.steps += 1
        m = self.briefing.orthomap
        return Estimate(m.width_m / 2 + self.steps, m.height_m / 2)

    def close(self) -> None:
        self.closed += 1


class Oracle(Recorder):
    uses_ground_truth = True


@pytest.fixture(scope="module")
def env():
    return make_benchmark_env(ScenarioEntry(TINY["id"], dict(TINY["overrides"]), TINY["label"]))


def test_time_line_action_oracle_gate_timing_and_close(env):
    plain, oracle = Recorder(), Oracle()
    with EpisodeDriver(env, [plain, oracle]) as driver:
        records = []
        for rec in driver.episode(seed=4):
            assert not rec.observation["image"].flags.writeable
            records.append((rec.step, rec.last, rec.time_s, rec.estimates, rec.wall_s, rec.cpu_s,
                            rec.info.get("estimate_xy_m"), rec.env_cpu_s))
    assert [r[0] for r in records] == list(range(N_FRAMES))
    assert [r[1] for r in records] == [False] * (N_FRAMES - 1) + [True]
    assert records[1][2] - records[0][2] == pytest.approx(env.briefing.dt_s)
    # the env scored the first agent's estimate of the previous frame
    for prev, cur in zip(records, records[1:], strict=False):
        assert cur[6] == pytest.approx([prev[3][0].x_m, prev[3][0].y_m])
    assert all(w > 0 and c >= 0 for r in records for w, c in zip(r[4], r[5], strict=True))
    assert all(r[7] > 0 for r in records)
    # the oracle gate: ground truth only for the oracle
    assert plain.infos == [None] * N_FRAMES
    assert all(i is not None and "true_pose" in i for i in oracle.infos) and len(oracle.infos) == N_FRAMES
    assert plain.closed == oracle.closed == 1
    driver.close()
    assert plain.closed == 1
    assert oracle_info(Oracle, {"a": 1}) == {"a": 1} and oracle_info(Recorder, {"a": 1}) is None


def test_failures_are_isolated_with_stages_or_raised(env):
    writer, failing, fine = Recorder(write=True), Recorder(fail_at=3), Recorder()
    with EpisodeDriver(env, [writer, failing, fine], isolate_failures=True) as driver:
        records = driver.run(seed=1)
    assert [(f.agent, f.stage) for f in driver.failures] == [(0, "step 0"), (1, "step 3")]
    assert "read-only" in driver.failures[0].error and "deliberate failure" in driver.failures[1].error
    assert driver.alive == (False, False, True)
    assert len(records) == N_FRAMES and all(r.estimates[2] is not None for r in records)
    assert records[3].estimates[1] is None and records[2].estimates[1] is not None
    # the action came from the first live agent: "fine" once the others failed
    assert records[5].info["estimate_xy_m"][0] == pytest.approx(records[4].estimates[2].x_m)
    with EpisodeDriver(env, [Recorder(fail_at=2)]) as driver, pytest.raises(RuntimeError, match="deliberate"):
        driver.run(seed=1)


def test_streaming_and_max_steps(env):
    """A consumer acts between records, before the env steps; max_steps ends the episode early."""
    seen = []
    with EpisodeDriver(env, [Recorder()]) as driver:
        gen = driver.episode(seed=2, max_steps=4)
        first = next(gen)
        seen.append(env._i)          # the env has not stepped past the frame just handed out
        rest = list(gen)
    assert first.step == 0 and seen == [0]
    assert [r.step for r in rest] == [1, 2, 3, 4] and rest[-1].last


def test_record_episode_uses_the_driver_time_line():
    rec = record_episode(ScenarioEntry(TINY["id"], dict(TINY["overrides"]), "tiny"), 1,
                         AgentEntry("dead-reckoning", {}, "dr"))
    assert rec["truth"].shape == (N_FRAMES, 4) and rec["estimates"].shape == (N_FRAMES, 2)
    assert rec["shadow_mask"] is not None and rec["image"].flags.writeable


def test_read_only_views_share_memory():
    a = np.zeros((2, 2, 3), np.uint8)
    view = read_only({"image": a})["image"]
    a[0, 0, 0] = 9
    assert view[0, 0, 0] == 9 and not view.flags.writeable and a.flags.writeable


if __name__ == "__main__":   # write the fixture again (after a deliberate change of world, renderer or agents)
    FIXTURE.parent.mkdir(exist_ok=True)
    FIXTURE.write_text(json.dumps({"frames_sha256": _frames_digest(), "rows": _comparable(_rows())},
                                  indent=1, sort_keys=True) + "\n")
    print(f"wrote {FIXTURE}", file=sys.stderr)
