"""Clocks for the bridge: GPS week time, a monotonic wall clock, a simulator's clock, and a drift-free schedule.

Why its own module: GPS_INPUT carries GPS time (week, ms of week) while every other message wants a timestamp
that never jumps backwards; both come from one monotonic anchor so an NTP step cannot disturb the stream.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from aerial_loc_env.errors import ConfigError

GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06T00:00:00Z as a Unix time
GPS_LEAP_SECONDS = 18            # GPS - UTC since 2017-01-01 (no leap second announced since)
SECONDS_PER_WEEK = 7 * 86_400
SIGNING_EPOCH_UNIX_S = 1_420_070_400  # 2015-01-01T00:00:00Z: origin of MAVLink 2 signing time (10 microsecond units)


def gps_week_ms(unix_s: float, leap_s: int = GPS_LEAP_SECONDS) -> tuple[int, int]:
    """(GPS week, milliseconds of week) of a UTC Unix time; GPS time runs ``leap_s`` ahead of UTC."""
    gps_s = unix_s - GPS_EPOCH_UNIX_S + leap_s
    if gps_s < 0:
        raise ConfigError(f"unix time {unix_s!r} is before the GPS epoch 1980-01-06")
    week, rem_s = divmod(gps_s, SECONDS_PER_WEEK)
    ms = int(math.floor(rem_s * 1000.0 + 1e-6))
    if ms >= SECONDS_PER_WEEK * 1000:  # rounding at the very end of a week
        week, ms = week + 1, 0
    return int(week), ms


def gps_to_unix_s(week: int, ms_of_week: int, leap_s: int = GPS_LEAP_SECONDS) -> float:
    """Inverse of :func:`gps_week_ms` (to the millisecond)."""
    return GPS_EPOCH_UNIX_S + week * SECONDS_PER_WEEK + ms_of_week / 1000.0 - leap_s


def signing_timestamp(unix_s: float) -> int:
    """MAVLink 2 signing timestamp: 10-microsecond units since 2015-01-01 UTC."""
    return int((unix_s - SIGNING_EPOCH_UNIX_S) * 100_000)


@dataclass
class MonotonicClock:
    """Unix time that advances with ``time.monotonic`` from one anchor, so it never steps backwards."""

    monotonic: Callable[[], float] = time.monotonic
    anchor_unix_s: float = field(default_factory=time.time)
    anchor_mono_s: float = field(default=math.nan)

    def __post_init__(self) -> None:
        if math.isnan(self.anchor_mono_s):
            self.anchor_mono_s = self.monotonic()

    def unix_s(self, mono_s: float | None = None) -> float:
        """Unix time of monotonic instant ``mono_s`` (now if None)."""
        mono = self.monotonic() if mono_s is None else mono_s
        return self.anchor_unix_s + (mono - self.anchor_mono_s)

    def unix_us(self, mono_s: float | None = None) -> int:
        return int(self.unix_s(mono_s) * 1e6)


class SimClock:
    """Unix time that runs on a simulator's clock (SITL's boot time, SYSTEM_TIME.time_boot_ms), for follow mode.

    Why: an autopilot corrects every offboard timestamp (GPS_INPUT's week time, VISION_POSITION_ESTIMATE's
    usec) against its own clock, assuming both run at the same rate. SITL at ``--speedup 2`` runs twice as fast
    as the wall clock, so wall-clock stamps fell behind until ArduPilot clamped them at its jitter limit (2 s for
    a MAVLink GPS): the EKF fused each fix as that much older. Here the clock runs at ``rate`` (the nominal
    speedup) from the least delayed of the last ``window`` observations (sim seconds, monotonic arrival): a
    message can only arrive late, never early, so the one that gives the latest time is the truest, as in
    ArduPilot's own jitter correction; older ones drop out, so a simulator that falls behind its speedup is
    followed within a window. Before the first observation it runs at ``rate`` from its creation, and the first
    one joins on without a jump. It never steps backwards (it holds until the simulator catches up).
    """

    def __init__(self, rate: float = 1.0, monotonic: Callable[[], float] = time.monotonic,
                 anchor_unix_s: float | None = None, window: int = 20) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise ConfigError(f"SimClock: rate must be a finite number > 0 (the simulator's speedup), got {rate!r}")
        self.rate, self.monotonic = float(rate), monotonic
        self.anchor_unix_s = time.time() if anchor_unix_s is None else float(anchor_unix_s)
        self._mono0 = monotonic()
        self._offsets: collections.deque[float] = collections.deque(maxlen=window)  # sim s - rate x arrival
        self._to_elapsed_s = 0.0     # sim s -> seconds since this clock's anchor (set at the first observation)
        self._last_s = 0.0

    @property
    def synced(self) -> bool:
        """True once the simulator's time has been observed."""
        return bool(self._offsets)

    def observe(self, sim_s: float, mono_s: float | None = None) -> None:
        """The simulator's clock read ``sim_s`` when its message arrived at monotonic instant ``mono_s``."""
        mono = self.monotonic() if mono_s is None else mono_s
        if not self._offsets:
            self._to_elapsed_s = self.elapsed_s(mono) - sim_s
        self._offsets.append(float(sim_s) - self.rate * mono)

    def elapsed_s(self, mono_s: float | None = None) -> float:
        """Simulator seconds since this clock's anchor at monotonic instant ``mono_s`` (now if None)."""
        mono = self.monotonic() if mono_s is None else mono_s
        if not self._offsets:
            t = (mono - self._mono0) * self.rate
        else:
            t = self._to_elapsed_s + self.rate * mono + max(self._offsets)
        self._last_s = max(self._last_s, t)
        return self._last_s

    def sim_s(self, mono_s: float | None = None) -> float:
        """The simulator's own time (its boot seconds once observed) at monotonic instant ``mono_s``."""
        return self.elapsed_s(mono_s) - self._to_elapsed_s

    def unix_s(self, mono_s: float | None = None) -> float:
        return self.anchor_unix_s + self.elapsed_s(mono_s)

    def unix_us(self, mono_s: float | None = None) -> int:
        return int(self.unix_s(mono_s) * 1e6)

    def sim_at_s(self, mono_s: float) -> float:
        """The simulator's time at monotonic instant ``mono_s`` as the observations place it, without the
        never-backwards hold of ``sim_s`` (which would date a past instant at the latest time read): for stamping
        an arrival, e.g. a truth sample's. Needs ``synced``."""
        return self.rate * mono_s + max(self._offsets)

    def unix_of_sim_s(self, sim_s: float) -> float:
        """The Unix stamp this clock gives the simulator's instant ``sim_s`` (its boot seconds): how a past
        instant, e.g. a frame's capture, is stamped on the clock the messages run on. Pure (no clamping)."""
        return self.anchor_unix_s + self._to_elapsed_s + float(sim_s)


class Schedule:
    """Absolute deadlines ``t0 + k / rate``: no drift accumulates, late ticks are skipped, never bunched."""

    def __init__(self, rate_hz: float, start_s: float) -> None:
        if not rate_hz > 0:
            raise ConfigError(f"Schedule: rate_hz must be > 0, got {rate_hz!r}")
        self.period_s = 1.0 / rate_hz
        self.start_s = start_s
        self.index = 0
        self.skipped = 0

    @property
    def deadline_s(self) -> float:
        return self.start_s + self.index * self.period_s

    def due(self, now_s: float) -> bool:
        return now_s >= self.deadline_s

    def advance(self, now_s: float) -> None:
        """Move to the next deadline after ``now_s``; ticks missed by more than a period count as skipped."""
        self.index += 1
        behind = int((now_s - self.deadline_s) // self.period_s) + 1 if now_s >= self.deadline_s else 0
        if behind > 0:
            self.skipped += behind
            self.index += behind
