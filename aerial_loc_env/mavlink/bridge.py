"""From the env's estimates (world ENU metres, ARCHITECTURE.md) to the sender's :class:`PoseFix`.

Why separate from the sender: the sender knows nothing of maps or agents. This layer owns the georeference
(``orthomap.world_to_latlon`` or any callable), the local origin, the altitude reference, and the velocity
that GPS_INPUT must always carry (estimators give positions; the velocity is their smoothed difference).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from aerial_loc_env.mavlink.fix import STATUSES, GeoOrigin, PoseFix

#: the velocity's accuracy never reported better than this (a GNSS receiver's floor; the filter's formula
#: would reach 0 for an estimator claiming a perfect position)
MIN_SPEED_STD_MPS = 0.1

WorldToLatLon = Callable[[float, float], tuple[float, float]]


class EstimateBridge:
    """Converts estimates into fixes: lat/lon from the map georeference, ENU about ``origin_xy_m``, velocity.

    ``ground_amsl_m`` is the terrain height of the map (the env's altitude is above ground); the local frame's
    origin is on the ground at ``origin_xy_m``, so ``up_m`` is the altitude above ground.
    """

    def __init__(self, world_to_latlon: WorldToLatLon, origin_xy_m: tuple[float, float], *,
                 ground_amsl_m: float = 0.0, default_std_m: float = 10.0, v_std_m: float = 0.5,
                 velocity_tau_s: float = 1.0, max_speed_mps: float = 60.0, max_gap_s: float = 2.0) -> None:
        self._to_latlon = world_to_latlon
        self.origin_xy_m = (float(origin_xy_m[0]), float(origin_xy_m[1]))
        self.ground_amsl_m = float(ground_amsl_m)
        self.default_std_m = default_std_m
        self.v_std_m = v_std_m
        self.velocity_tau_s = velocity_tau_s
        self.max_speed_mps = max_speed_mps   # faster than this is a jump (relocalization, new episode)
        self.max_gap_s = max_gap_s           # fixes further apart than this restart the velocity filter
        lat, lon = self._latlon(*self.origin_xy_m)
        self.origin = GeoOrigin(lat, lon, self.ground_amsl_m)
        self._prev: tuple[float, float, float] | None = None   # (time_s, x_m, y_m) of the last good fix
        self._vel = (0.0, 0.0)
        self._acc = (0.0, 0.0)             # the filtered velocity's rate of change (its lag under acceleration)
        self._vel_valid = False
        self._speed_std_mps = max_speed_mps

    @classmethod
    def from_orthomap(cls, orthomap: Any, origin_xy_m: tuple[float, float] | None = None,
                      **kwargs: Any) -> EstimateBridge:
        """Use the map's georeference; the origin defaults to the map centre."""
        if origin_xy_m is None:
            origin_xy_m = (orthomap.width_m / 2.0, orthomap.height_m / 2.0)
        return cls(orthomap.world_to_latlon, origin_xy_m, **kwargs)

    def _latlon(self, x_m: float, y_m: float) -> tuple[float, float]:
        lat, lon = self._to_latlon(x_m, y_m)
        return float(np.asarray(lat).reshape(-1)[0]), float(np.asarray(lon).reshape(-1)[0])

    def reset(self) -> None:
        self._prev, self._vel, self._acc, self._vel_valid = None, (0.0, 0.0), (0.0, 0.0), False

    def fix(self, estimate: Any, *, time_s: float, altitude_m: float,
            yaw_fallback_rad: float | None = None) -> PoseFix:
        """PoseFix of an ``Estimate`` (x_m, y_m, yaw_rad, cov_xy_m2, status) at ``time_s`` and height AGL."""
        x, y = float(estimate.x_m), float(estimate.y_m)
        status = getattr(estimate, "status", "ok")
        if status not in STATUSES:
            status = "degraded"
        cov = getattr(estimate, "cov_xy_m2", None)
        if not (math.isfinite(x) and math.isfinite(y)) or (cov is not None and not np.all(np.isfinite(cov))):
            # a broken estimate is a lost one (held at the last good position), never NaN on the wire
            status, cov = "lost", None
            x, y = self._prev[1:] if self._prev is not None else self.origin_xy_m
        if cov is None:
            cov_en = (self.default_std_m ** 2, 0.0, self.default_std_m ** 2)
        else:
            c = np.asarray(cov, dtype=np.float64).reshape(2, 2)
            cov_en = (float(c[0, 0]), float(0.5 * (c[0, 1] + c[1, 0])), float(c[1, 1]))
        vel_valid = self._velocity(time_s, x, y, status, cov_en)
        lat, lon = self._latlon(x, y)
        yaw = getattr(estimate, "yaw_rad", None)
        if yaw is None or not math.isfinite(yaw):
            yaw = yaw_fallback_rad
        if yaw is not None and not math.isfinite(yaw):
            yaw = None
        return PoseFix(
            time_s=float(time_s), lat_deg=lat, lon_deg=lon, alt_amsl_m=self.ground_amsl_m + float(altitude_m),
            east_m=x - self.origin_xy_m[0], north_m=y - self.origin_xy_m[1], up_m=float(altitude_m),
            vel_enu_mps=(self._vel[0], self._vel[1], 0.0), vel_horiz_valid=vel_valid,
            yaw_rad=None if yaw is None else float(yaw), cov_en_m2=cov_en, v_std_m=self.v_std_m,
            speed_std_mps=self._speed_std_mps if vel_valid else self.max_speed_mps, status=status)

    def _velocity(self, time_s: float, x: float, y: float, status: str, cov_en: tuple[float, float, float]) -> bool:
        """Update the velocity filter with a position; True when it holds a velocity (two good fixes in a row
        without a jump). The filter is a first-order low-pass (time constant ``velocity_tau_s``) of the position
        differences; its speed accuracy is what the estimator's own covariance makes of it, not a constant: the
        position noise (per axis, white: an upper bound for the positively correlated errors of a tracker)
        through the difference and the low-pass, ``(a / dt)^2 * 2 var / (2 - a)`` at gain ``a``, plus the
        filter's lag under acceleration, its time constant times the acceleration it measures."""
        if status == "lost":
            return self._vel_valid
        prev, self._prev = self._prev, (time_s, x, y)
        if prev is None or time_s <= prev[0]:
            return self._vel_valid
        dt = time_s - prev[0]
        if dt > self.max_gap_s:              # too long ago to say how the vehicle moves now: start again
            self._vel, self._acc, self._vel_valid = (0.0, 0.0), (0.0, 0.0), False
            return False
        raw = ((x - prev[1]) / dt, (y - prev[2]) / dt)
        if math.hypot(*raw) > self.max_speed_mps:
            self._vel, self._acc, self._vel_valid = (0.0, 0.0), (0.0, 0.0), False   # a jump: start again
            return False
        alpha = dt / (self.velocity_tau_s + dt)
        if not self._vel_valid:              # the first difference starts the filter
            new = raw
            noise_var = 2.0 * 0.5 * (cov_en[0] + cov_en[2]) / dt ** 2
        else:
            new = tuple(v + alpha * (r - v) for v, r in zip(self._vel, raw, strict=True))
            noise_var = (alpha / dt) ** 2 * 0.5 * (cov_en[0] + cov_en[2]) * 2.0 / (2.0 - alpha)
            acc = tuple((n - v) / dt for n, v in zip(new, self._vel, strict=True))
            self._acc = tuple(a + alpha * (r - a) for a, r in zip(self._acc, acc, strict=True))
        self._vel, self._vel_valid = new, True
        lag = self.velocity_tau_s * math.hypot(*self._acc)
        self._speed_std_mps = max(MIN_SPEED_STD_MPS, math.sqrt(noise_var + lag ** 2))
        return True
