"""Wind: the horizontal air motion an episode flies through (the ``[wind]`` section of a scenario).

The wind is a mean vector drawn per episode plus gusts. The mean speed is drawn uniformly from
``speed_range_mps`` and its direction uniformly from ``from_deg_range``: the direction the wind blows FROM, in
compass degrees clockwise from north (ArduPilot SITL's ``SIM_WIND_DIR`` and the meteorological convention), so
``from_deg = 270`` is a westerly wind that pushes the vehicle east. A range with lo > hi wraps through north.

Gusts: one first-order Gauss-Markov process per horizontal axis (east, north), independent, stationary with
standard deviation ``gust_std_mps`` and correlation time ``gust_tau_s``: autocorrelation
``R(tau) = sigma^2 exp(-|tau| / T)`` and two-sided power spectral density

    S(f) = 2 sigma^2 T / (1 + (2 pi f T)^2)      (m^2/s^2 per Hz, f in Hz, integrating to sigma^2),

i.e. the Dryden model's longitudinal form with ``T = L / V``. It is sampled exactly at the frame times:
``g_0 ~ N(0, sigma^2)``, ``g_{k+1} = a g_k + sigma sqrt(1 - a^2) n_k`` with ``a = exp(-dt / T)``.

Off (the default: speed range (0, 0), no gusts) the field is zero and draws nothing from the generator, so an
episode without wind is the episode it was before wind existed.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError

#: the generator version of the wind field (bumped whenever the field drawn for a seed changes)
GENERATOR_VERSION = 2
#: the strongest wind accepted: mean speed + 3 gust sigma at most this share of the airspeed (a crab of asin 0.6,
#: about 37 degrees; beyond, the vehicle barely makes way upwind and its guidance saturates)
MAX_WIND_SHARE = 0.6


@dataclass(frozen=True)
class WindConfig:
    """The [wind] section: mean wind drawn per episode, Gauss-Markov gusts (see the module docstring)."""

    speed_range_mps: tuple[float, float] = field(default=(0.0, 0.0), metadata=rng(
        0.0, 100.0, doc="mean wind speed, drawn uniformly per episode"))
    from_deg_range: tuple[float, float] = field(default=(0.0, 360.0), metadata=rng(
        0.0, 360.0, doc="direction the wind blows from, compass degrees clockwise from north (lo > hi wraps)"))
    gust_std_mps: float = field(default=0.0, metadata=rng(0.0, 50.0, doc="gust standard deviation per axis"))
    gust_tau_s: float = field(default=2.0, metadata=rng(0.0, 3600.0, lo_open=True,
                                                        doc="gust correlation time (Gauss-Markov)"))

    def validate(self, where: str) -> None:
        lo, hi = self.speed_range_mps
        if lo > hi:
            raise ConfigError(f"{where}: field 'speed_range_mps' = ({lo:g}, {hi:g}) must have lo <= hi "
                              "(the mean wind speed is drawn uniformly between them)")

    @property
    def enabled(self) -> bool:
        return self.speed_range_mps[1] > 0.0 or self.gust_std_mps > 0.0

    @property
    def strongest_mps(self) -> float:
        """The strongest wind the guidance has to hold against: the largest mean plus 3 gust sigma."""
        return float(self.speed_range_mps[1]) + 3.0 * float(self.gust_std_mps)

    def check_flight(self, airspeed_mps: float, where: str) -> None:
        """Refuse wind the vehicle cannot fly against: ``strongest_mps`` must stay within ``MAX_WIND_SHARE`` of
        the airspeed (``flight.speed_mps``)."""
        if not self.enabled or self.strongest_mps <= MAX_WIND_SHARE * airspeed_mps:
            return
        room = MAX_WIND_SHARE * airspeed_mps
        raise ConfigError(
            f"{where}: wind.speed_range_mps up to {self.speed_range_mps[1]:g} m/s plus 3 x wind.gust_std_mps "
            f"({3.0 * self.gust_std_mps:g} m/s) = {self.strongest_mps:g} m/s is too strong for flight.speed_mps = "
            f"{airspeed_mps:g} m/s (the airspeed): the wind must stay within {MAX_WIND_SHARE:.0%} of it "
            f"({room:.4g} m/s), else the vehicle cannot hold its course upwind; lower the wind (e.g. "
            f"wind.speed_range_mps up to {max(room - 3.0 * self.gust_std_mps, 0.0):.4g} m/s with these gusts) or "
            f"fly faster (flight.speed_mps >= {math.ceil(self.strongest_mps / MAX_WIND_SHARE * 10.0) / 10.0:g})")

    def draw(self, rng: np.random.Generator, t_s: np.ndarray) -> WindField:
        """The episode's wind at the frame times ``t_s`` (evenly spaced); draws nothing when off."""
        t = np.asarray(t_s, dtype=np.float64)
        if not self.enabled:
            return WindField(t, np.zeros(t.shape), np.zeros(t.shape), 0.0, 0.0)
        lo, hi = (float(v) for v in self.speed_range_mps)
        speed = lo + (hi - lo) * rng.random()
        f_lo, f_hi = (float(v) for v in self.from_deg_range)
        span = f_hi - f_lo if f_lo <= f_hi else f_hi + 360.0 - f_lo
        from_deg = (f_lo + span * rng.random()) % 360.0
        # blowing FROM compass bearing b (clockwise from north) -> velocity towards b + 180 deg; ENU: east = sin
        to = math.radians(from_deg)
        east = np.full(t.shape, -speed * math.sin(to))
        north = np.full(t.shape, -speed * math.cos(to))
        if self.gust_std_mps > 0.0 and t.size:
            east = east + self._gusts(rng, t)
            north = north + self._gusts(rng, t)
        return WindField(t, east, north, float(speed), float(from_deg))

    def _gusts(self, rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
        """One axis of the Gauss-Markov gust process, sampled exactly at ``t`` (stationary start)."""
        sigma = float(self.gust_std_mps)
        z = rng.standard_normal(t.size)
        out = np.empty(t.size)
        out[0] = sigma * z[0]
        a = portable.exp(-np.diff(t) / float(self.gust_tau_s))
        drive = sigma * np.sqrt(1.0 - a * a)
        for k in range(1, t.size):
            out[k] = a[k - 1] * out[k - 1] + drive[k - 1] * z[k]
        return out


@dataclass(frozen=True)
class WindField:
    """The episode's wind: ENU velocity (m/s, the air's motion over the ground) at each frame time, and the
    mean drawn (speed, direction it blows from in compass degrees)."""

    t_s: np.ndarray
    east_mps: np.ndarray
    north_mps: np.ndarray
    mean_speed_mps: float
    mean_from_deg: float

    @functools.cached_property
    def calm(self) -> bool:
        """No wind at any frame (asked at every step: computed once)."""
        return not (np.any(self.east_mps) or np.any(self.north_mps))

    def at(self, i: int) -> tuple[float, float]:
        """The wind (east, north) m/s at frame ``i``."""
        return float(self.east_mps[i]), float(self.north_mps[i])


__all__ = ["MAX_WIND_SHARE", "WindConfig", "WindField"]
