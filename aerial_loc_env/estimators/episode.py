"""The episode driver: the one place that runs agents on an episode of the env.

It owns the time line, what agents are handed, and how they are measured, so that the benchmark, the episode
recorder, the evaluation script and the MAVLink scenario run all see the same thing:

- **time line** (the env's, docs/ARCHITECTURE.md): ``reset(seed)`` gives frame 0; every live agent estimates on
  every frame, the last one included; then the env steps with the first live agent's estimate of that frame
  (clipped to the map; zeros with no live agent) as the action, which scores it and gives the next frame. The
  last frame (``truncated``/``terminated``, or the one reached after ``max_steps`` steps) is estimated, then
  the episode ends. Agents are reset with the episode's seed.
- **frames**: agents get read-only views of the observation (an agent writing into its frame fails loudly
  instead of corrupting its neighbours' or the renderer's buffers).
- **oracle gate**: ``oracle_info`` decides what ``info`` an agent may see: the env's ground truth goes only to
  an agent (or measurement model) with ``uses_ground_truth = True``, for ablations; every other one gets None.
- **timing**: wall and thread-CPU seconds of every agent step, thread-CPU seconds of the env's reset/steps.
- **Agent.close**: ``EpisodeDriver.close`` (or leaving its ``with`` block) closes every agent once.

It is a generator of per-step records, so a streaming loop (MAVLink) consumes one record per frame; whatever
the caller does between two records (set an external pose, send a message) happens before the env steps.
"""

from __future__ import annotations

import math
import time
import traceback
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from aerial_loc_env.estimators.protocol import Agent, Estimate

if TYPE_CHECKING:  # layer 3; for type hints only
    from aerial_loc_env.env.briefing import Briefing


# ----------------------------------------------------------------------------------------- the oracle gate
def uses_ground_truth(obj: Any) -> bool:
    """True for an oracle: an agent or measurement model (class or instance) with ``uses_ground_truth``."""
    return bool(getattr(obj, "uses_ground_truth", False))


def oracle_info(obj: Any, info: Mapping[str, Any] | None) -> Mapping[str, Any] | None:
    """The ``info`` that ``obj`` may see: the env's ground truth for an oracle, None for everything else."""
    return info if uses_ground_truth(obj) else None


def needs_ground_truth(agents: Sequence[Any]) -> bool:
    """True when one of ``agents`` is an oracle: the env must then put what it reads (the shadow mask) in info."""
    return any(uses_ground_truth(a) for a in agents)


def read_only(observation: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Read-only views of an observation's arrays (no copy)."""
    out = {}
    for key, value in observation.items():
        view = np.asarray(value).view()
        view.flags.writeable = False
        out[key] = view
    return out


# ----------------------------------------------------------------------------------------- records
@dataclass(frozen=True)
class AgentFailure:
    """An agent that raised (or every live agent, when the env did): it takes no further part in the episode."""

    agent: int                 # index into the driver's agents
    stage: str                 # "reset", "step K", "env reset", "env step K", "close"
    error: str                 # "TypeError: message"
    traceback: str
    exception: BaseException = field(repr=False, compare=False)


@dataclass(frozen=True)
class StepRecord:
    """One frame of the episode and what every agent made of it."""

    step: int                                   # frame index: 0 is the frame ``reset`` returned
    time_s: float                               # the frame's time since the start of the episode
    observation: Mapping[str, np.ndarray]       # read-only views of the env's buffers: what the agents saw
                                                # (valid until the next record; copy what you keep)
    info: Mapping[str, Any]                     # the env's ground truth of this frame (for scoring only)
    estimates: tuple[Estimate | None, ...]      # per agent; None for an agent that failed, now or earlier
    wall_s: tuple[float, ...]                   # per agent: wall seconds of its step (NaN without one)
    cpu_s: tuple[float, ...]                    # per agent: thread-CPU seconds of its step (NaN without one)
    env_cpu_s: float                            # thread-CPU seconds of the env call that gave this frame
    last: bool                                  # the episode's last frame

    @property
    def true_pose(self) -> np.ndarray:
        """(x_m, y_m, yaw_rad, altitude_m) where the frame was taken."""
        return np.asarray(self.info["true_pose"], dtype=np.float64)

    def error_m(self, agent: int = 0) -> float | None:
        """Horizontal position error of ``agent``'s estimate on this frame (None without an estimate)."""
        est = self.estimates[agent]
        if est is None or "true_pose" not in self.info:
            return None
        truth = self.info["true_pose"]
        return math.hypot(est.x_m - truth[0], est.y_m - truth[1])


# ----------------------------------------------------------------------------------------- the driver
class EpisodeDriver:
    """Runs ``agents`` on episodes of ``env`` (an ``AerialLocEnv``, possibly wrapped).

    With ``isolate_failures`` an agent that raises is logged in ``failures`` and drops out while the others go
    on (a failing env fails every live agent and ends the episode); without it the exception propagates.
    Use as a context manager, or call ``close``: it closes every agent.
    """

    def __init__(self, env: Any, agents: Sequence[Agent], *, isolate_failures: bool = False) -> None:
        self.env = env
        self.agents = tuple(agents)
        self.isolate_failures = isolate_failures
        self.failures: list[AgentFailure] = []
        self.briefing: Briefing | None = None
        self._alive = [True] * len(self.agents)
        self._closed = False

    @property
    def alive(self) -> tuple[bool, ...]:
        return tuple(self._alive)

    def _fail(self, i: int, stage: str, exc: BaseException) -> None:
        if not self.isolate_failures:
            raise exc
        self._alive[i] = False
        self.failures.append(AgentFailure(i, stage, f"{type(exc).__name__}: {exc}",
                                          traceback.format_exc(limit=8), exc))

    def _fail_all(self, stage: str, exc: BaseException) -> None:
        for i in range(len(self.agents)):
            if self._alive[i]:
                self._fail(i, stage, exc)

    def episode(self, seed: int | None = None, *, max_steps: int | None = None) -> Iterator[StepRecord]:
        """Reset the env and the agents with ``seed``, then yield one record per frame (the last included).

        ``max_steps`` ends the episode after that many env steps (the frame reached is the last one).
        Agents that failed in an earlier episode stay out.
        """
        from aerial_loc_env.env import world_to_action

        env = self.env
        c0 = time.thread_time()
        try:
            obs, info = env.reset(seed=seed)
        except Exception as exc:  # noqa: BLE001 (isolated: fails the live agents; else re-raised)
            self._fail_all("env reset", exc)
            return
        env_cpu_s = time.thread_time() - c0
        briefing = self.briefing = env.unwrapped.briefing
        for i, agent in enumerate(self.agents):
            if self._alive[i]:
                try:
                    agent.reset(briefing, seed=seed)
                except Exception as exc:  # noqa: BLE001 (one broken agent must not sink the others)
                    self._fail(i, "reset", exc)
        n = len(self.agents)
        k, done = 0, False
        while True:
            frame = read_only(obs)
            estimates: list[Estimate | None] = [None] * n
            wall = [math.nan] * n
            cpu = [math.nan] * n
            for i, agent in enumerate(self.agents):
                if not self._alive[i]:
                    continue
                try:
                    c0 = time.thread_time()
                    t0 = time.perf_counter()
                    estimates[i] = agent.step(frame, oracle_info(agent, info))
                    wall[i] = time.perf_counter() - t0
                    cpu[i] = time.thread_time() - c0
                except Exception as exc:  # noqa: BLE001
                    self._fail(i, f"step {k}", exc)
            last = done or (max_steps is not None and k >= max_steps) or (n > 0 and not any(self._alive))
            yield StepRecord(k, float(info.get("time_s", k * briefing.dt_s)), frame, info, tuple(estimates),
                             tuple(wall), tuple(cpu), env_cpu_s, last)
            if last:
                return
            first = next((e for e in estimates if e is not None), None)
            action = (np.zeros(2, np.float32) if first is None else
                      np.clip(np.asarray(world_to_action(briefing.orthomap, first.x_m, first.y_m), np.float32),
                              -1.0, 1.0))
            c0 = time.thread_time()
            try:
                obs, _reward, terminated, truncated, info = env.step(action)
            except Exception as exc:  # noqa: BLE001
                self._fail_all(f"env step {k + 1}", exc)
                return
            env_cpu_s = time.thread_time() - c0
            k += 1
            done = bool(terminated or truncated)

    def run(self, seed: int | None = None, *, max_steps: int | None = None) -> list[StepRecord]:
        """The whole episode's records."""
        return list(self.episode(seed, max_steps=max_steps))

    def close(self) -> None:
        """Close every agent (once), even when one raises. With ``isolate_failures`` a failing close is logged
        as stage "close"; without it the first error is raised after all are closed."""
        if self._closed:
            return
        self._closed = True
        errors: list[BaseException] = []
        for i, agent in enumerate(self.agents):
            try:
                agent.close()
            except Exception as exc:  # noqa: BLE001
                if self.isolate_failures:
                    self._fail(i, "close", exc)
                else:
                    errors.append(exc)
        if errors:
            raise errors[0]

    def __enter__(self) -> EpisodeDriver:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
