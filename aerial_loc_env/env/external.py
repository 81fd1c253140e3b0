"""Drive an ``AerialLocEnv`` from an external pose stream (an autopilot's simulator, a flight log).

The env's own episodes fly a sampled track; a closed loop with an autopilot needs the camera rendered wherever
the *autopilot's* vehicle is. ``ExternalFlight`` does that with the env's own renderer, sensors and scenario:

- ``reset(first_pose, seed=...)`` draws the episode (sun, shadow strength, clouds, sensor noise) from the seed as
  the env does, sets the prior around the first pose (``episode.start = "tracking"``; uniform for global) and
  replaces the track-limited shadows by **shadows over the whole map** (one sweep per map and sun, cached), so
  they are valid wherever the vehicle goes;
- ``due(t_s)`` says whether a frame is due at stream time ``t_s`` (the scenario's camera rate,
  ``flight.rate_hz``): feed the stream at any rate, render only at the camera's;
- ``observe(pose)`` renders the frame at the pose and returns the env's observation: image, odometry derived
  from the stream (the displacement since the last frame in the body frame: forward and lateral speed, and the
  yaw rate, plus the scenario's odometry noise), measured heading and altitude (noisy). Ground truth is in
  ``info`` only, as in the env.

Estimators still see only observations and ``briefing`` (whose ``dt_s`` is the camera period). Poses are in
the world frame (ENU metres on the map, yaw CCW from east, altitude above ground, docs/ARCHITECTURE.md); use
``orthomap.latlon_to_world`` for a geographic stream.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from aerial_loc_env.env.briefing import Prior
from aerial_loc_env.errors import AerialLocError, MapError
from aerial_loc_env.sensors.flight import Measurements, Track, wrap_angle

_SHADOWS: OrderedDict[tuple, Any] = OrderedDict()   # whole-map shadow grids, a few suns per process
_SHADOWS_KEEP = 4


@dataclass(frozen=True)
class ExternalPose:
    """One pose of the stream: world metres (ENU), yaw CCW from east, altitude above ground, stream time."""

    x_m: float
    y_m: float
    yaw_rad: float
    altitude_m: float
    t_s: float

    def __post_init__(self) -> None:
        bad = {k: v for k, v in dataclasses.asdict(self).items() if not math.isfinite(v)}
        if bad:
            raise AerialLocError(f"ExternalPose: non-finite {bad}; every field must be a finite number")


def whole_map_shadows(env: Any) -> Any:
    """The episode sun's cast shadows over the whole map (a ``ShadowGrid``), swept once per map and sun."""
    from aerial_loc_env.world.shadows import ShadowGrid, sun_occlusion

    om, cfg, sun = env.orthomap, env.scenario.shadows, env._sun
    f = int(cfg.downsample)
    key = (env.world.key, f, repr(cfg), float(sun.azimuth_deg), float(sun.elevation_deg))
    if key not in _SHADOWS:
        gx, gy = om.gsd_x_m * f, om.gsd_y_m * f
        grid = sun_occlusion(env.world.coarse_dsm(f), gx, gy, sun, downsample=1, penumbra_scale=cfg.penumbra_scale,
                             antialias_px=cfg.antialias_px, azimuth_samples=cfg.penumbra_azimuth_samples)
        _SHADOWS[key] = ShadowGrid(grid.data, gx, gy, f)
        while len(_SHADOWS) > _SHADOWS_KEEP:
            _SHADOWS.popitem(last=False)
    _SHADOWS.move_to_end(key)
    return _SHADOWS[key]


class ExternalFlight:
    """The env rendered at an external pose stream; see the module docstring.

    ``env``: an ``AerialLocEnv`` (or a wrapper of one). The env is not stepped: ``reset``/``observe`` replace
    ``env.reset``/``env.step`` for as long as the stream lasts; ``env.unwrapped.briefing`` is this flight's.
    """

    def __init__(self, env: Any) -> None:
        self.env = env.unwrapped
        self.briefing = None
        self.frames = 0
        self._last: ExternalPose | None = None
        self._next_due_s = -math.inf

    @property
    def period_s(self) -> float:
        """The camera period (the scenario's ``flight.rate_hz``)."""
        return float(self.env.scenario.flight.dt_s)

    def reset(self, first: ExternalPose, *, seed: int | None = None) -> tuple[dict, dict]:
        """Start a flight at ``first``: the episode's random draws from ``seed``, the prior around ``first``,
        whole-map shadows; returns the first frame's (observation, info)."""
        u = self.env
        u.reset(seed=seed)                    # sun, strength, clouds, noise seed, sensor errors: from the seed
        sc, rng = u.scenario, u.np_random
        if u._occlusion is not None:          # the track's box of shadows -> the whole map's
            from aerial_loc_env.world.shadows import ShadowGrid

            u._occlusion = [whole_map_shadows(u) if isinstance(s, ShadowGrid) else s for s in u._occlusion]
        if sc.episode.start == "tracking":
            std = sc.episode.prior_std_m
            mean = (first.x_m + rng.normal(0.0, std), first.y_m + rng.normal(0.0, std))
            u._prior = Prior("gaussian", (float(mean[0]), float(mean[1])), float(std))
        else:
            u._prior = Prior("uniform")
        u.briefing = dataclasses.replace(u.briefing, prior=u._prior)   # altitude: the scenario's nominal
        self.briefing = u.briefing
        self._gimbal = u._attitude
        self._lateral_rng = u.lateral_rng()
        self.frames = 0
        self._last = None
        self._next_due_s = -math.inf
        return self.observe(first)

    def due(self, t_s: float) -> bool:
        """Whether the camera takes a frame at stream time ``t_s`` (the first frame is always due)."""
        return t_s >= self._next_due_s - 1e-9

    def footprint_inside(self, pose: ExternalPose) -> bool:
        """Whether the camera's footprint at ``pose`` lies on the map (where a frame can be rendered)."""
        om = self.env.orthomap
        corners = self.env.camera.footprint_corners_m(pose.x_m, pose.y_m, pose.yaw_rad, pose.altitude_m)
        return bool(np.all((corners[:, 0] >= 0) & (corners[:, 0] <= om.width_m)
                           & (corners[:, 1] >= 0) & (corners[:, 1] <= om.height_m)))

    def observe(self, pose: ExternalPose) -> tuple[dict, dict]:
        """Render the frame at ``pose``; returns (observation, info) as ``env.step`` would (no reward)."""
        u = self.env
        if self.briefing is None:
            raise AerialLocError("ExternalFlight: call reset(first_pose) before observe()")
        if not pose.altitude_m > 0.0:
            raise AerialLocError(f"ExternalFlight: altitude_m = {pose.altitude_m} m: the camera needs the vehicle "
                                 "above the ground (render only once airborne)")
        if not self.footprint_inside(pose):
            om = u.orthomap
            raise MapError(f"ExternalFlight: the camera footprint at ({pose.x_m:.0f}, {pose.y_m:.0f}) m, "
                           f"{pose.altitude_m:.0f} m above ground leaves the map '{om.name}' "
                           f"({om.width_m:.0f} m x {om.height_m:.0f} m): keep the flight over the map")
        sc, rng = u.scenario, u.np_random
        last = self._last
        if last is None or pose.t_s <= last.t_s:
            forward, lateral, yaw_rate = 0.0, 0.0, 0.0
        else:
            dt = pose.t_s - last.t_s
            # the body-frame ground velocity: the displacement on the mid-step heading's forward and left axes
            # (the motion models' heading), so a crabbing plane or a copter moving sideways is measured as it moves
            yaw_rate = float(wrap_angle(pose.yaw_rad - last.yaw_rad)) / dt
            mid = last.yaw_rad + 0.5 * yaw_rate * dt
            dx, dy = pose.x_m - last.x_m, pose.y_m - last.y_m
            forward = (dx * math.cos(mid) + dy * math.sin(mid)) / dt
            lateral = (dy * math.cos(mid) - dx * math.sin(mid)) / dt
        on = sc.odometry
        noise = rng.normal(0.0, 1.0, 4) * (on.speed_std_mps, on.yaw_rate_std_radps, on.heading_std_rad,
                                            on.altitude_std_m)
        lateral_noise = self._lateral_rng.normal(0.0, on.lateral_std_mps)   # its own stream, as in the env
        odo = (forward, yaw_rate, lateral) if last is None else \
            (forward + noise[0], yaw_rate + noise[1], lateral + lateral_noise)
        u._track = Track(*(np.array([v], dtype=np.float64) for v in (
            pose.t_s, pose.x_m, pose.y_m, pose.yaw_rad, pose.altitude_m, math.hypot(forward, lateral), yaw_rate,
            forward, lateral)))
        u._meas = Measurements(
            odometry=np.array([odo], dtype=np.float32),
            yaw_rad=np.array([np.clip(wrap_angle(pose.yaw_rad + noise[2]), -math.pi, math.pi)], dtype=np.float32),
            altitude_m=np.array([max(0.0, pose.altitude_m + noise[3])], dtype=np.float32))
        if self._gimbal is not None:           # the gimbal's jitter series, one row per frame
            row = min(self.frames, len(self._gimbal) - 1)
            u._attitude = self._gimbal[row:row + 1]
        u._i = 0
        obs, info = u._observe(0)
        info["step"] = self.frames
        self.frames += 1
        self._last = pose
        nxt = self._next_due_s + self.period_s      # absolute deadlines: no drift; a late frame skips ahead
        self._next_due_s = nxt if pose.t_s < nxt else pose.t_s + self.period_s
        return obs, info


__all__ = ["ExternalFlight", "ExternalPose", "whole_map_shadows"]
