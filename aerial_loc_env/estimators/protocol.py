"""The agent protocol: what every estimator (MCL, baselines, learned policies, oracles) implements.

An agent is reset with the environment's ``Briefing`` (everything it may know besides the observations)
and a seed, then gives one ``Estimate`` per observation. Optional extras (particles, weights, an uncertainty)
feed the renderer and the MAVLink sender's fix quality. Agents never see the simulator's state; the only
exception is a class (or instance) with ``uses_ground_truth = True``, to which the episode driver
(``estimators/episode.py``, the one oracle gate) also passes the env's ``info``.

A new agent is a subclass of ``Agent`` with an optional frozen-dataclass ``Params`` (built by
``aerial_loc_env.config.build_config`` from a spec's ``[params]`` table); see ``registry.py`` for the specs.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import numpy as np

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError

if TYPE_CHECKING:  # layer 3; imported for type hints only
    from aerial_loc_env.env.briefing import Briefing

STATUSES: tuple[str, ...] = ("ok", "degraded", "lost", "dead_reckoning")


@dataclass(frozen=True)
class Estimate:
    """One pose estimate in the world frame (metres, ENU yaw).

    ``cov_xy_m2`` is the 2x2 horizontal covariance (drives the MAVLink fix quality); ``extras`` carries
    optional per-agent data for rendering and reports, e.g. ``"particles"`` (N, 2|3) and ``"weights"`` (N,).
    """

    x_m: float
    y_m: float
    yaw_rad: float | None = None
    cov_xy_m2: np.ndarray | None = None
    status: str = "ok"
    extras: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.x_m) and math.isfinite(self.y_m)):
            raise ValueError(f"Estimate: position ({self.x_m!r}, {self.y_m!r}) must be finite")
        if self.status not in STATUSES:
            raise ValueError(f"Estimate: status {self.status!r} is not one of {', '.join(STATUSES)}")
        if self.cov_xy_m2 is not None and np.shape(self.cov_xy_m2) != (2, 2):
            raise ValueError(f"Estimate: cov_xy_m2 must have shape (2, 2), got {np.shape(self.cov_xy_m2)}")

    @property
    def xy_m(self) -> np.ndarray:
        return np.array([self.x_m, self.y_m])

    @property
    def std_m(self) -> float | None:
        """1-sigma horizontal uncertainty along the worst axis (sqrt of the largest eigenvalue), or None."""
        if self.cov_xy_m2 is None:
            return None
        return float(np.sqrt(max(np.linalg.eigvalsh(np.asarray(self.cov_xy_m2, dtype=float))[-1], 0.0)))


class Observation(NamedTuple):
    """The env's observation dict, unpacked and checked once (see ARCHITECTURE.md, observation table)."""

    image: np.ndarray          # (H, W, 3) uint8
    speed_mps: float           # measured forward speed (body-frame ground velocity) over the last step
    yaw_rate_radps: float      # measured yaw rate over the last step
    yaw_rad: float             # measured heading now
    altitude_m: float          # measured altitude above ground
    lateral_mps: float = 0.0   # measured lateral speed (body frame, positive to the left) over the last step


def parse_observation(observation: Mapping[str, np.ndarray], briefing: Briefing | None = None,
                      altitude_range_m: tuple[float, float] | None = None, agent: str | None = None) -> Observation:
    """Unpack ``observation`` (keys image/odometry/yaw/altitude) with a clear error for a malformed one, and,
    given the ``briefing`` the agent was reset with, for frames that come from another scenario (or from
    outside the agent's ``altitude_range_m``, default ``default_altitude_range_m``; ``agent``: its name, for the
    error)."""
    missing = [k for k in ("image", "odometry", "yaw", "altitude") if k not in observation]
    if missing:
        raise ConfigError(f"observation: missing key(s) {missing}; expected image, odometry, yaw, altitude")
    odo = np.asarray(observation["odometry"], dtype=np.float64).reshape(-1)
    if odo.shape != (3,):
        old = (" (a v1 observation: [forward_speed_mps, yaw_rate_radps]; the v2 ids append the lateral speed, "
               "positive to the left, so a crabbing vehicle's motion can be represented)") if odo.shape == (2,) else ""
        raise ConfigError("observation['odometry'] must hold [forward_speed_mps, yaw_rate_radps, lateral_speed_mps] "
                          f"(the v2 layout), got shape {odo.shape}{old}")
    yaw = float(np.asarray(observation["yaw"], dtype=np.float64).reshape(-1)[0])
    alt = float(np.asarray(observation["altitude"], dtype=np.float64).reshape(-1)[0])
    speed, rate, lateral = odo.tolist()
    if not (math.isfinite(speed) and math.isfinite(rate) and math.isfinite(lateral) and math.isfinite(yaw)
            and math.isfinite(alt) and alt > 0):
        raise ConfigError(f"observation: odometry {odo}, yaw {yaw}, altitude {alt} "
                          "must be finite (altitude > 0)")
    image = np.asarray(observation["image"])
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ConfigError(f"observation['image'] must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
    if briefing is not None:
        check_against_briefing(image, alt, briefing, altitude_range_m, agent)
    return Observation(image, speed, rate, yaw, alt, lateral)


#: measured altitude beyond this factor of the briefing's nominal altitude: not the briefed flight
ALTITUDE_MISMATCH_FACTOR = 2.0


def default_altitude_range_m(briefing: Briefing) -> tuple[float, float]:
    """The measured altitudes an agent built for the briefing's nominal altitude accepts: within a factor
    ``ALTITUDE_MISMATCH_FACTOR`` of it (beyond, the frames come from another flight than the briefed one)."""
    nominal = float(briefing.altitude_m)
    return nominal / ALTITUDE_MISMATCH_FACTOR, nominal * ALTITUDE_MISMATCH_FACTOR


def check_against_briefing(image: np.ndarray, altitude_m: float, briefing: Briefing,
                           altitude_range_m: tuple[float, float] | None = None, agent: str | None = None) -> None:
    """Refuse an observation that cannot come from the briefed scenario (image size, altitude outside
    ``altitude_range_m``, default ``default_altitude_range_m``), instead of estimating on with a camera model
    that does not describe the frames."""
    cam = briefing.camera
    h, w = image.shape[:2]
    reset_it = "reset it with env.unwrapped.briefing of the env that renders them"
    fix = f"the agent was reset with another scenario's briefing than the one producing the frames; {reset_it}"
    if (w, h) != (cam.width_px, cam.height_px):
        raise ConfigError(f"observation image is {w} x {h} px but the briefing's camera "
                          f"({briefing.scenario_id}) is {cam.width_px} x {cam.height_px} px: {fix}")
    lo, hi = altitude_range_m or default_altitude_range_m(briefing)
    if not lo <= altitude_m <= hi:
        raise ConfigError(f"observation altitude {altitude_m:.1f} m is outside the {lo:.1f}-{hi:.1f} m "
                          f"{agent or 'this agent'} estimates at (Agent.altitude_range_m; the briefing's nominal is "
                          f"{float(briefing.altitude_m):.1f} m, {briefing.scenario_id}): give it only frames within "
                          f"that range (`aerial-loc mavlink --follow` does), or, if they come from another scenario, "
                          f"{reset_it}")


class Agent(ABC):
    """Base class of all estimators: ``reset`` with the briefing, then one ``step`` per observation.

    Subclasses that take parameters declare ``Params`` (a frozen dataclass with ranges in field metadata) and
    accept an instance of it as their only constructor argument; ``from_params`` builds it from a spec.
    """

    Params: ClassVar[type | None] = None
    #: True for oracles (ablations only): the episode driver then passes the env's ``info`` to ``step``.
    uses_ground_truth: bool = False
    #: the spec name this agent was built from (set by the registry), for reports
    name: str = ""

    @classmethod
    def from_params(cls, params: Mapping[str, Any] | None = None, *, where: str | None = None) -> Agent:
        """Build the agent from a spec's ``[params]`` mapping, validated against ``cls.Params``."""
        where = where or cls.__name__
        if cls.Params is None:
            if params:
                raise ConfigError(f"{where}: {cls.__name__} takes no parameters, got {sorted(params)}")
            return cls()
        if not dataclasses.is_dataclass(cls.Params):
            raise ConfigError(f"{where}: {cls.__name__}.Params must be a dataclass")
        return cls(build_config(cls.Params, params or {}, where=where))

    @abstractmethod
    def reset(self, briefing: Briefing, *, seed: int | None = None) -> Estimate:
        """Start a new episode; return the estimate from the prior (before any observation)."""

    @abstractmethod
    def step(self, observation: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> Estimate:
        """Consume one observation; return the current estimate."""

    def close(self) -> None:  # noqa: B027 - optional hook, deliberately not abstract
        """Release resources (processes, files). The default has none."""

    def altitude_range_m(self, briefing: Briefing) -> tuple[float, float]:
        """The measured altitudes (m above ground) this agent estimates at with ``briefing``; ``step`` refuses
        observations outside. A flight that changes altitude (take-off, landing) feeds it frames only within
        (``aerial-loc mavlink --follow``). Default: ``default_altitude_range_m`` (agents whose measurement
        model is built for the nominal altitude)."""
        return default_altitude_range_m(briefing)


def prior_estimate(briefing: Briefing, status: str = "ok") -> Estimate:
    """The estimate an agent can give before any observation: the prior's mean (or the map centre)."""
    prior = briefing.prior
    m = briefing.orthomap
    if prior.kind == "gaussian" and prior.mean_xy_m is not None:
        std = float(prior.std_xy_m or 0.0)
        return Estimate(float(prior.mean_xy_m[0]), float(prior.mean_xy_m[1]),
                        cov_xy_m2=np.eye(2) * std ** 2, status=status)
    w, h = float(m.width_m), float(m.height_m)
    return Estimate(w / 2, h / 2, cov_xy_m2=np.diag([w ** 2 / 12, h ** 2 / 12]), status="lost")
