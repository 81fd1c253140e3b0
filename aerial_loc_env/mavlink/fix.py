"""The sender's input: a pose fix, the thread-safe latest-value slot that holds it, and how a fix ages.

Why a slot and not a queue: the sender runs at its own steady rate whatever the estimator does, so it only
ever needs the newest fix; an estimator slower than the send rate makes the fix age, and ageing degrades what
is sent (accuracies grow, then the GPS fix is dropped), exactly as a real receiver losing lock would.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError

STATUSES = ("ok", "degraded", "dead_reckoning", "lost")


@dataclass(frozen=True)
class GeoOrigin:
    """The WGS84 point at the local frame's origin (what SET_GPS_GLOBAL_ORIGIN announces)."""

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float

    def __post_init__(self) -> None:
        ok = abs(self.lat_deg) <= 90.0 and abs(self.lon_deg) <= 180.0 and math.isfinite(self.alt_amsl_m)
        if not ok:
            raise ConfigError(f"GeoOrigin: out of range: {self}; need |lat|<=90, |lon|<=180, finite alt")


@dataclass(frozen=True)
class PoseFix:
    """One estimate in the units the bridge needs. Local position is ENU (world convention) about the origin.

    ``cov_en_m2`` = (var_east, cov_east_north, var_north) from the estimator's 2x2 covariance; ``v_std_m`` the
    vertical 1-sigma (the altitude comes from the baro/altimeter, so it is small but not zero).
    """

    time_s: float                               # the estimate's own time (simulation or sensor clock)
    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    east_m: float
    north_m: float
    up_m: float
    vel_enu_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    vel_up_valid: bool = False                  # vel_enu_mps[2] measured? (else GPS_INPUT flags it ignored)
    vel_horiz_valid: bool = True                # vel_enu_mps[:2] known? (else flagged ignored, speed_std_mps huge)
    yaw_rad: float | None = None                # ENU yaw, CCW from east (None: the estimator has none)
    cov_en_m2: tuple[float, float, float] = (1.0, 0.0, 1.0)
    v_std_m: float = 1.0
    yaw_std_rad: float | None = None
    speed_std_mps: float = 1.0
    status: str = "ok"
    withheld: bool = False                      # cut from the position feed (GPS_INPUT, VISION, ODOMETRY): no fix
    #                                             there; a low-rate external position estimate may still carry it

    def __post_init__(self) -> None:
        if self.status not in STATUSES:
            raise ConfigError(f"PoseFix.status = {self.status!r}; allowed: {', '.join(STATUSES)}")
        values = {"lat_deg": self.lat_deg, "lon_deg": self.lon_deg, "alt_amsl_m": self.alt_amsl_m,
                  "east_m": self.east_m, "north_m": self.north_m, "up_m": self.up_m, "v_std_m": self.v_std_m,
                  "speed_std_mps": self.speed_std_mps,
                  "yaw_rad": 0.0 if self.yaw_rad is None else self.yaw_rad,
                  "yaw_std_rad": 0.0 if self.yaw_std_rad is None else self.yaw_std_rad}
        values.update({f"vel_enu_mps[{i}]": v for i, v in enumerate(self.vel_enu_mps)})
        values.update({f"cov_en_m2[{i}]": v for i, v in enumerate(self.cov_en_m2)})
        bad = {k: v for k, v in values.items() if not math.isfinite(v)}
        if bad:   # caught here, in the publisher's thread, never as garbage on the wire
            raise ConfigError(f"PoseFix: non-finite {bad}; every field must be a finite number "
                              "(report an unusable estimate with status='lost')")
        if abs(self.lat_deg) > 90.0 or abs(self.lon_deg) > 180.0:
            raise ConfigError(f"PoseFix: lat_deg={self.lat_deg}, lon_deg={self.lon_deg} out of range")
        var_e, cov_en, var_n = self.cov_en_m2
        if not (var_e >= 0 and var_n >= 0 and cov_en * cov_en <= var_e * var_n * (1 + 1e-9) + 1e-12):
            raise ConfigError(f"PoseFix.cov_en_m2 = {self.cov_en_m2!r} is not a covariance "
                              "(need var >= 0 and |cov| <= sd_e * sd_n)")

    @property
    def h_std_m(self) -> float:
        """Horizontal accuracy as GNSS receivers report it: DRMS = sqrt(var_east + var_north)."""
        return math.sqrt(self.cov_en_m2[0] + self.cov_en_m2[2])


@dataclass(frozen=True)
class FixPolicy:
    """How fix quality maps to what is sent, and how it degrades with age and estimator status."""

    stale_after_s: float = field(default=0.5, metadata=rng(0.0, 60.0, lo_open=True))
    lost_after_s: float = field(default=3.0, metadata=rng(0.0, 600.0, lo_open=True))
    stale_growth_mps: float = field(default=3.0, metadata=rng(0.0, 100.0))   # accuracy growth of a held fix
    degraded_factor: float = field(default=3.0, metadata=rng(1.0, 100.0))  # accuracy inflation if degraded
    satellites_ok: int = field(default=12, metadata=rng(0, 60))
    satellites_degraded: int = field(default=6, metadata=rng(0, 60))
    hdop_ref_m: float = field(default=2.0, metadata=rng(0.0, 100.0, lo_open=True))   # hdop = h_acc / hdop_ref
    jump_threshold_m: float = field(default=5.0, metadata=rng(0.0, 10_000.0, lo_open=True))
    jump_sigma: float = field(default=3.0, metadata=rng(0.0, 100.0))   # jump: > this many sigmas (and > m)
    quality_ref_m: float = field(default=5.0, metadata=rng(0.0, 1000.0, lo_open=True))  # ODOMETRY q=50

    def validate(self, where: str) -> None:
        if self.lost_after_s < self.stale_after_s:
            raise ConfigError(f"{where}: lost_after_s ({self.lost_after_s}) must be >= stale_after_s "
                              f"({self.stale_after_s})")


# GPS fix types of GPS_INPUT (GPS_FIX_TYPE)
FIX_NONE, FIX_3D = 1, 3
LOST_H_ACC_M = 9999.0


@dataclass(frozen=True)
class FixQuality:
    """What a fix is worth at send time: drives fix_type, satellites, dops, accuracies and covariances."""

    usable: bool
    fix_type: int
    satellites: int
    h_acc_m: float
    v_acc_m: float
    speed_acc_mps: float
    hdop: float
    vdop: float
    inflation: float           # multiplies the standard deviations of the covariance (>= 1)
    odometry_quality: int      # ODOMETRY.quality: -1 failed, 1..100


def assess(fix: PoseFix | None, age_s: float, policy: FixPolicy) -> FixQuality:
    """Quality of ``fix`` held ``age_s``: fresh/ok -> 3D fix; stale/degraded -> inflated; lost -> none."""
    if fix is None or fix.status == "lost" or fix.withheld or age_s > policy.lost_after_s:
        return FixQuality(False, FIX_NONE, 0, LOST_H_ACC_M, LOST_H_ACC_M, 99.0, 99.99, 99.99, math.inf, -1)
    factor = 1.0 if fix.status == "ok" else policy.degraded_factor
    growth_m = policy.stale_growth_mps * max(0.0, age_s - policy.stale_after_s)
    h_acc = math.hypot(fix.h_std_m * factor, growth_m)
    v_acc = math.hypot(fix.v_std_m * factor, growth_m)
    speed_acc = math.hypot(fix.speed_std_mps * factor, policy.stale_growth_mps if growth_m > 0 else 0.0)
    degraded = factor > 1.0 or growth_m > 0.0
    inflation = h_acc / fix.h_std_m if fix.h_std_m > 0 else factor
    quality = int(min(100, max(1, round(100.0 * policy.quality_ref_m / (policy.quality_ref_m + h_acc)))))
    return FixQuality(
        usable=True, fix_type=FIX_3D,
        satellites=policy.satellites_degraded if degraded else policy.satellites_ok,
        h_acc_m=h_acc, v_acc_m=v_acc, speed_acc_mps=speed_acc,
        hdop=min(99.99, max(0.5, h_acc / policy.hdop_ref_m)),
        vdop=min(99.99, max(0.5, v_acc / policy.hdop_ref_m)),
        inflation=max(1.0, inflation), odometry_quality=quality,
    )


@dataclass(frozen=True)
class SlotItem:
    """A fix as the sender reads it: with the slot's sequence number, reset counter and arrival time."""

    fix: PoseFix
    seq: int
    reset_counter: int
    received_mono_s: float


class FixSlot:
    """Thread-safe latest-value slot; detects jumps between consecutive fixes and counts them (reset_counter).

    A jump is a move that the previous fix's velocity does not explain by more than ``jump_threshold_m`` and
    more than ``jump_sigma`` combined standard deviations, or a recovery from 'lost': the consumers (EKFs)
    then reset their external-navigation state instead of rejecting the new position as an outlier.
    """

    def __init__(self, jump_threshold_m: float = 5.0, jump_sigma: float = 3.0,
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._item: SlotItem | None = None
        self._jump_threshold_m = jump_threshold_m
        self._jump_sigma = jump_sigma
        self._monotonic = monotonic
        self._reset_counter = 0

    def put(self, fix: PoseFix) -> SlotItem:
        with self._lock:
            prev = self._item
            if prev is not None and self._is_jump(prev.fix, fix):
                self._reset_counter = (self._reset_counter + 1) % 256
            item = SlotItem(fix, 0 if prev is None else prev.seq + 1, self._reset_counter, self._monotonic())
            self._item = item
            return item

    def _is_jump(self, prev: PoseFix, new: PoseFix) -> bool:
        if new.status == "lost":
            return False
        if prev.status == "lost":
            return True
        dt = max(0.0, new.time_s - prev.time_s)
        pred_e = prev.east_m + prev.vel_enu_mps[0] * dt
        pred_n = prev.north_m + prev.vel_enu_mps[1] * dt
        limit = max(self._jump_threshold_m, self._jump_sigma * math.hypot(prev.h_std_m, new.h_std_m))
        return math.hypot(new.east_m - pred_e, new.north_m - pred_n) > limit

    def get(self) -> SlotItem | None:
        with self._lock:
            return self._item
