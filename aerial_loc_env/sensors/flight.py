"""Flight: constant-airspeed, constant-altitude tracks that stay over valid map, and the vehicle's noisy sensors.

The motion model is the second reference's eq. (1) (Leung et al.) with the wind added: with airspeed ``v``
and yaw rate ``omega`` held over a step ``dt`` and the wind ``(w_e, w_n)`` (``world.wind``),

    x += v dt cos(yaw + omega dt / 2) + w_e dt;  y += v dt sin(yaw + omega dt / 2) + w_n dt;  yaw += omega dt,

so that in wind the ground track is the air velocity plus the wind and the vehicle crabs: its heading (where the
camera's top points) is not its course. Without wind ``v`` is the ground speed and this is eq. (1) unchanged.

The commanded yaw rate is piecewise constant: straight legs towards random waypoints joined by coordinated
turns at ``turn_rate_deg_s``. The guidance steers the COURSE to the waypoint: it solves the wind triangle for
the heading, ``heading = course - asin(w_perp / v)`` (``w_perp`` the wind's component to the left of the
course), and turns towards that heading. The applied airspeed and yaw rate carry small process noise, the
altitude a small jitter. A ``Track`` also records the true ground velocity in the body frame over each step
(forward along the mid-step heading, lateral positive to the left), what a flow sensor or the autopilot's
velocity estimate measures. Tracks are drawn by rejection sampling from the episode's generator until every pose
keeps the camera footprint plus a margin over valid map (``FlyableRegion``); on a map too small for a full
track the longest valid track found is used (never shorter than ``min_steps``), and a map too small for that is
a ``MapError``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.world.maps.region import FlyableRegion
from aerial_loc_env.world.wind import WindField

#: the largest crab the guidance commands: asin of this share of the airspeed (a gust beyond it is not held)
MAX_CROSSWIND_SHARE = 0.9


@dataclass(frozen=True)
class FlightConfig:
    """The [flight] section of a scenario. Defaults: the paper's simulation (Table 4, IV.A)."""

    altitude_m: float = field(default=200.0, metadata=rng(1.0, 5000.0, doc="nominal altitude above ground"))
    duration_s: float = field(default=60.0, metadata=rng(0.25, 3600.0, doc="episode length (track time)"))
    speed_mps: float = field(default=2500.0 / 60.0, metadata=rng(
        0.0, 200.0, lo_open=True, doc="airspeed; the ground speed without wind (2.5 km in 60 s)"))
    rate_hz: float = field(default=4.0, metadata=rng(0.1, 100.0, doc="camera rate"))
    turn_rate_deg_s: float = field(default=10.0, metadata=rng(0.0, 90.0, lo_open=True,
                                                               doc="yaw rate of coordinated turns"))
    min_leg_m: float = field(default=300.0, metadata=rng(0.0, 1e5,
                                                             doc="preferred distance to a new waypoint"))
    speed_noise_mps: float = field(default=0.2, metadata=rng(0.0, 10.0, doc="process noise of the airspeed"))
    yaw_rate_noise_deg_s: float = field(default=0.5, metadata=rng(0.0, 30.0,
                                                                     doc="process noise of the yaw rate"))
    altitude_noise_m: float = field(default=0.5, metadata=rng(0.0, 50.0,
                                                              doc="altitude jitter (1 sigma, clipped at 3)"))
    margin_m: float = field(default=45.0, metadata=rng(0.0, 1e4, doc="clearance beyond the footprint "
                                                                     "(room for particles: 3 x 15 m)"))
    min_steps: int = field(default=8, metadata=rng(1, 100000, doc="shortest acceptable track (steps)"))
    max_tries: int = field(default=40, metadata=rng(1, 10000, doc="rejection-sampling attempts"))

    def validate(self, where: str) -> None:
        if self.steps < self.min_steps:
            raise ConfigError(
                f"{where}: field 'duration_s' = {self.duration_s:g} s at rate_hz = {self.rate_hz:g} gives "
                f"{self.steps} step(s), fewer than min_steps = {self.min_steps} (the shortest track accepted); "
                f"lengthen duration_s to >= {self.min_steps / self.rate_hz:g} s or lower min_steps")

    @property
    def dt_s(self) -> float:
        return 1.0 / self.rate_hz

    @property
    def steps(self) -> int:
        """Number of env steps (scored frames) of a full-length track."""
        return max(1, int(round(self.duration_s * self.rate_hz)))


@dataclass(frozen=True)
class Track:
    """A true trajectory: ``n`` poses at the camera rate; ``speed_mps[i]`` (airspeed) and ``yaw_rate_radps[i]``
    are the true values applied over the step ending at pose ``i`` (index 0: the commanded values at the start);
    ``forward_mps[i]``/``lateral_mps[i]`` the true ground velocity over that step in the body frame (along the
    mid-step heading; lateral positive to the left): ``(speed_mps, 0)`` without wind."""

    t_s: np.ndarray
    x_m: np.ndarray
    y_m: np.ndarray
    yaw_rad: np.ndarray
    altitude_m: np.ndarray
    speed_mps: np.ndarray
    yaw_rate_radps: np.ndarray
    forward_mps: np.ndarray
    lateral_mps: np.ndarray

    def __len__(self) -> int:
        return int(self.x_m.shape[0])

    @property
    def length_m(self) -> float:
        return float(np.sum(np.hypot(np.diff(self.x_m), np.diff(self.y_m))))

    def bounds_m(self) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the vehicle positions."""
        return (float(self.x_m.min()), float(self.y_m.min()), float(self.x_m.max()), float(self.y_m.max()))


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap radians to [-pi, pi)."""
    return _wrap(np.asarray(a))


def _wrap(a: np.ndarray | float) -> np.ndarray | float:
    """``wrap_angle``'s formula on ``a`` as it is: a Python float stays one (the track's step-by-step integration
    avoids NumPy's per-call cost; Python's float ``%`` and NumPy's ``remainder`` both take ``fmod`` and add the
    divisor where the signs differ, so the values are the same)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def footprint_radius_m(footprint_w_m: float, footprint_h_m: float) -> float:
    """Half-diagonal of a footprint: the clearance that keeps it inside whatever the yaw."""
    return 0.5 * math.hypot(footprint_w_m, footprint_h_m)


def sample_track(config: FlightConfig, region: FlyableRegion, rng: np.random.Generator,
                 wind: WindField | None = None) -> Track:
    """Draw a track that stays in ``region`` (see the module doc); deterministic given ``rng``. ``wind``: the
    episode's wind at the frame times of a full track (``WindConfig.draw``); None is calm air."""
    best: Track | None = None
    for _ in range(config.max_tries):
        track = _fly(config, region, rng, wind)
        if best is None or len(track) > len(best):
            best = track
        if len(track) == config.steps + 1:
            break
    assert best is not None
    if len(best) - 1 < config.min_steps:
        raise region.too_small_error(
            f" (longest track found in {config.max_tries} tries: {len(best) - 1} steps, "
            f"flight.min_steps = {config.min_steps})")
    return best


def crab_heading(course_rad: float, wind_e_mps: float, wind_n_mps: float, airspeed_mps: float) -> float:
    """The heading that makes good ``course_rad`` through the wind (the wind triangle): ``course - asin(w_perp /
    v)``, ``w_perp`` the wind's component to the left of the course; the ratio is held within
    ``MAX_CROSSWIND_SHARE``. Calm air: exactly ``course_rad``."""
    cross = wind_n_mps * math.cos(course_rad) - wind_e_mps * math.sin(course_rad)
    ratio = cross / max(airspeed_mps, 1e-9)
    return course_rad - math.asin(max(-MAX_CROSSWIND_SHARE, min(MAX_CROSSWIND_SHARE, ratio)))


def _fly(config: FlightConfig, region: FlyableRegion, rng: np.random.Generator,
         wind: WindField | None = None) -> Track:
    """One attempt: fly waypoint legs until the full duration or until the next pose leaves the region."""
    n = config.steps + 1
    dt = config.dt_s
    turn = math.radians(config.turn_rate_deg_s)
    yaw_noise = math.radians(config.yaw_rate_noise_deg_s)
    air = config.speed_mps
    we, wn = (np.zeros(n), np.zeros(n)) if wind is None else (wind.east_mps, wind.north_mps)
    if len(we) < n:
        raise ValueError(f"sample_track: the wind holds {len(we)} frame(s), the track {n}")
    start = region.sample(rng)[0]
    # waypoints keep a turn radius from the edge: the turn towards the next one then rarely leaves the region
    inset = air / max(turn, 1e-9)
    waypoint = _next_waypoint(region, rng, start, config.min_leg_m, inset)
    yaw = crab_heading(math.atan2(waypoint[1] - start[1], waypoint[0] - start[0]), float(we[0]), float(wn[0]), air)
    # noise drawn as a bank up front: the same rng draws whatever the track's fate.
    speed_noise = rng.normal(0.0, config.speed_noise_mps, n)
    rate_noise = rng.normal(0.0, yaw_noise, n)
    # altitude jitter clipped at 3 sigma: the clearance is computed for altitude + 3 sigma (footprint size)
    alt = config.altitude_m + np.clip(rng.normal(0.0, config.altitude_noise_m, n),
                                      -3.0 * config.altitude_noise_m, 3.0 * config.altitude_noise_m)
    # the step-by-step integration in Python floats (NumPy's float64 scalar arithmetic, the same IEEE operations,
    # costs several times more per operation): inputs as lists, the poses appended
    we_l, wn_l, speed_l, rate_l = we[:n].tolist(), wn[:n].tolist(), speed_noise.tolist(), rate_noise.tolist()
    x, y = float(start[0]), float(start[1])
    poses = [(x, y, yaw, air, 0.0, *_body_velocity(air, yaw, we_l[0], wn_l[0]))]
    reach = max(air * dt * 2.0, air / max(turn, 1e-9) * 0.5)
    for i in range(1, n):
        if math.hypot(waypoint[0] - x, waypoint[1] - y) < reach:
            waypoint = _next_waypoint(region, rng, (x, y), config.min_leg_m, inset)
        e_i, n_i = we_l[i], wn_l[i]      # the wind over the step ending at pose i
        heading = crab_heading(math.atan2(waypoint[1] - y, waypoint[0] - x), e_i, n_i, air)
        err = _wrap(heading - yaw)
        cmd = max(-turn, min(turn, err / dt))
        v = max(0.0, air + speed_l[i])
        w = cmd + rate_l[i]
        half = yaw + 0.5 * w * dt
        # calm air adds 0.0: the same floats as the track without wind
        x, y = x + v * dt * math.cos(half) + e_i * dt, y + v * dt * math.sin(half) + n_i * dt
        yaw = _wrap(yaw + w * dt)
        if not region.contains_point(x, y):
            break
        poses.append((x, y, yaw, v, w, *_body_velocity(v, half, e_i, n_i)))
    m = len(poses)
    xs, ys, yaws, speeds, rates, forwards, laterals = np.array(poses, dtype=np.float64).T
    return Track(t_s=np.arange(m) * dt, x_m=xs.copy(), y_m=ys.copy(), yaw_rad=yaws.copy(),
                 altitude_m=alt[:m].copy(), speed_mps=speeds.copy(), yaw_rate_radps=rates.copy(),
                 forward_mps=forwards.copy(), lateral_mps=laterals.copy())


def _body_velocity(airspeed_mps: float, heading_rad: float, wind_e_mps: float,
                   wind_n_mps: float) -> tuple[float, float]:
    """The ground velocity (airspeed along ``heading_rad`` plus the wind) in the body frame: (forward, left)."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    return airspeed_mps + (wind_e_mps * c + wind_n_mps * s), wind_n_mps * c - wind_e_mps * s


def _next_waypoint(region: FlyableRegion, rng: np.random.Generator, here, min_leg_m: float,
                   inset_m: float) -> np.ndarray:
    """A random flyable point, preferably at least ``min_leg_m`` away (the farthest of a few candidates)."""
    cand = region.sample(rng, 8, inset_m)
    d = np.hypot(cand[:, 0] - here[0], cand[:, 1] - here[1])
    far = np.flatnonzero(d >= min_leg_m)
    return cand[far[0]] if far.size else cand[int(np.argmax(d))]


#: 3 sigma of the altimeter's error may reach this share of the flight altitude (``AltimeterConfig.check_flight``)
ALTIMETER_MAX_ERROR_SHARE = 0.5


@dataclass(frozen=True)
class AltimeterConfig:
    """The [altimeter] section: barometric altitude errors. All zero by default (only ``odometry.altitude_std_m``).

    The measured altitude carries a per-episode bias drawn from ``N(0, bias_std_m^2)`` (QNH, ground elevation
    unknown to the vehicle) plus a random-walk drift of ``drift_std_m_per_sqrt_s`` per square-root second
    (pressure changes, temperature), starting at zero at the first frame.
    """

    bias_std_m: float = field(default=0.0, metadata=rng(0.0, 500.0, doc="per-episode bias std"))
    drift_std_m_per_sqrt_s: float = field(default=0.0, metadata=rng(0.0, 10.0, doc="random-walk drift"))

    def check_flight(self, flight: FlightConfig, where: str) -> None:
        """Refuse errors too large for ``flight``'s altitude: 3 sigma of the error at the end of the flight
        (bias and drift together) must stay within ``ALTIMETER_MAX_ERROR_SHARE`` of the altitude. Beyond, the
        measured altitude is often clipped to 0 m or far from the truth, and agents refuse the frames naming
        the altitude, not this section."""
        limit_m = ALTIMETER_MAX_ERROR_SHARE * flight.altitude_m / 3.0     # the largest 1-sigma error
        drift_var = self.drift_std_m_per_sqrt_s ** 2 * flight.duration_s
        total_m = math.sqrt(self.bias_std_m ** 2 + drift_var)
        if total_m <= limit_m:
            return
        duration = f"flight.duration_s = {flight.duration_s:g} s"
        if self.bias_std_m > 0.0 and drift_var < limit_m ** 2:
            name, value, unit = "bias_std_m", self.bias_std_m, "m"
            high, given = math.sqrt(limit_m ** 2 - drift_var), \
                f"drift_std_m_per_sqrt_s = {self.drift_std_m_per_sqrt_s:g} over {duration}"
        else:
            name, value, unit = "drift_std_m_per_sqrt_s", self.drift_std_m_per_sqrt_s, "m/sqrt(s)"
            high = math.sqrt(max(limit_m ** 2 - self.bias_std_m ** 2, 0.0) / flight.duration_s)
            given = f"bias_std_m = {self.bias_std_m:g}, over {duration}"
        raise ConfigError(
            f"{where}: altimeter.{name} = {value:g} {unit} is too large for flight.altitude_m = "
            f"{flight.altitude_m:g} m: 3 sigma of the altimeter's error ({3.0 * total_m:.4g} m) must stay within "
            f"{ALTIMETER_MAX_ERROR_SHARE:.0%} of the altitude ({3.0 * limit_m:.4g} m), else measured altitudes "
            f"fall to 0 m or far from the truth; allowed at this altitude: altimeter.{name} in [0, {high:.4g}] "
            f"{unit} (with {given}); lower it, or fly at flight.altitude_m >= "
            f"{math.ceil(3.0 * total_m / ALTIMETER_MAX_ERROR_SHARE):g} m")

    def draw_error(self, rng: np.random.Generator, t_s: np.ndarray) -> np.ndarray:
        """The altitude error (m) at the frame times ``t_s``; zeros without a draw when off."""
        t = np.asarray(t_s, dtype=np.float64)
        err = np.zeros(t.shape)
        if self.bias_std_m > 0.0:
            err += rng.normal(0.0, self.bias_std_m)
        if self.drift_std_m_per_sqrt_s > 0.0 and t.size > 1:
            steps = rng.standard_normal(t.size - 1) * self.drift_std_m_per_sqrt_s * np.sqrt(np.diff(t))
            err[1:] += np.cumsum(steps)
        return err


@dataclass(frozen=True)
class Measurements:
    """What the vehicle's own sensors report at each pose of a track (float32, ready for observations)."""

    odometry: np.ndarray     # (n, 3) [forward m/s, yaw rate rad/s, lateral m/s] over the step ending at each pose
    yaw_rad: np.ndarray      # (n,) heading, wrapped to [-pi, pi)
    altitude_m: np.ndarray   # (n,) altitude above ground, >= 0


def measure(track: Track, rng: np.random.Generator, *, speed_std_mps: float, yaw_rate_std_radps: float,
            heading_std_rad: float, altitude_std_m: float) -> Measurements:
    """Noisy odometry, heading and altitude for every pose (one vectorized draw per episode).

    The odometry is the body-frame ground velocity (forward, lateral) and the yaw rate. Its lateral column is
    the true value here; ``add_lateral_noise`` draws its noise from a generator of its own, so that every other
    draw of an episode is the one it was when the odometry had no lateral term. At pose 0 the odometry is the
    commanded values, noise-free (nothing has been flown yet).
    """
    n = len(track)
    odo = np.stack([track.forward_mps + rng.normal(0.0, speed_std_mps, n),
                    track.yaw_rate_radps + rng.normal(0.0, yaw_rate_std_radps, n),
                    track.lateral_mps.astype(np.float64)], axis=1)
    odo[0, :2] = (track.forward_mps[0], track.yaw_rate_radps[0])
    yaw = wrap_angle(track.yaw_rad + rng.normal(0.0, heading_std_rad, n))
    alt = np.maximum(track.altitude_m + rng.normal(0.0, altitude_std_m, n), 0.0)
    return Measurements(odometry=odo.astype(np.float32),
                        yaw_rad=np.clip(yaw, -math.pi, math.pi).astype(np.float32),
                        altitude_m=alt.astype(np.float32))


def add_lateral_noise(meas: Measurements, track: Track, rng: np.random.Generator,
                      lateral_std_mps: float) -> Measurements:
    """``meas`` with the lateral speed's noise drawn (one vectorized draw; pose 0 stays noise-free)."""
    n = len(track)
    lateral = track.lateral_mps + rng.normal(0.0, lateral_std_mps, n)
    lateral[0] = track.lateral_mps[0]
    odo = meas.odometry.copy()
    odo[:, 2] = lateral.astype(np.float32)
    return Measurements(odometry=odo, yaw_rad=meas.yaw_rad, altitude_m=meas.altitude_m)
