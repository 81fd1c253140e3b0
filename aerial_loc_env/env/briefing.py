"""The briefing: everything an estimator may know besides the observations (docs/ARCHITECTURE.md).

The env builds one at ``reset`` and exposes it as ``env.unwrapped.briefing`` (or
``env.get_wrapper_attr("briefing")``). Nothing else of the simulator's state is meant for agents: the true
pose, the shadows and the sun live in ``info`` for scoring and oracles only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError

if TYPE_CHECKING:  # annotations only: agents import this module without pulling the world layer
    from aerial_loc_env.sensors.camera import CameraModel
    from aerial_loc_env.world.maps.orthomap import Orthomap

PRIOR_KINDS = ("gaussian", "uniform")


@dataclass(frozen=True)
class Prior:
    """The initial knowledge of the position: ``gaussian`` (tracking, the paper: N(mean, std^2 I)) or
    ``uniform`` over the map (global localization, the second reference)."""

    kind: str
    mean_xy_m: tuple[float, float] | None = None
    std_xy_m: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in PRIOR_KINDS:
            raise ConfigError(f"Prior: kind {self.kind!r} is not allowed; use one of {PRIOR_KINDS}")
        if self.kind == "gaussian":
            if self.mean_xy_m is None or self.std_xy_m is None or not self.std_xy_m > 0:
                raise ConfigError("Prior: a gaussian prior needs mean_xy_m and std_xy_m > 0")
        elif self.mean_xy_m is not None or self.std_xy_m is not None:
            raise ConfigError("Prior: a uniform prior has no mean_xy_m or std_xy_m")


@dataclass(frozen=True)
class OdometryNoise:
    """Noise (1 sigma) of the vehicle's own sensors. Forward speed and yaw rate: the second reference's figures
    for eq. (1) (10 cm/s, 5 deg/s); the lateral speed (the body-frame ground velocity across the heading, from a
    flow sensor or the autopilot's velocity estimate) as the forward one: such a sensor's error does not prefer
    an axis; heading and altitude: a compass/gimbal and a baro/lidar altimeter. This is also the [odometry]
    section of a scenario."""

    speed_std_mps: float = field(default=0.10, metadata=rng(0.0, 50.0))
    yaw_rate_std_radps: float = field(default=math.radians(5.0), metadata=rng(0.0, 10.0))
    heading_std_rad: float = field(default=math.radians(2.0), metadata=rng(0.0, math.pi))
    altitude_std_m: float = field(default=1.0, metadata=rng(0.0, 1000.0))
    lateral_std_mps: float = field(default=0.10, metadata=rng(0.0, 50.0))


@dataclass(frozen=True, eq=False)
class Briefing:
    """What an estimator may use: the database map, the observation's camera model, the prior, the camera
    period, the nominal altitude, the odometry noise model and the scenario id."""

    orthomap: Orthomap
    camera: CameraModel
    prior: Prior
    dt_s: float
    altitude_m: float
    odometry_noise: OdometryNoise
    scenario_id: str
