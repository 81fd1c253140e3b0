"""Flight: tracks stay over valid map, follow eq. (1), are reproducible, crab through the wind; sensors carry
their noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.sensors.flight import (
    MAX_CROSSWIND_SHARE,
    AltimeterConfig,
    FlightConfig,
    _wrap,
    crab_heading,
    measure,
    sample_track,
    wrap_angle,
)
from aerial_loc_env.world.maps.region import FlyableRegion
from aerial_loc_env.world.wind import WindConfig


def _paper_region(clearance_m: float = 135.0, nodata=None) -> FlyableRegion:
    return FlyableRegion(1200.0, 1400.0, clearance_m, nodata=nodata)


def test_full_track_stays_inside_with_clearance():
    cfg = FlightConfig()
    region = _paper_region()
    for seed in range(5):
        track = sample_track(cfg, region, np.random.default_rng(seed))
        assert len(track) == cfg.steps + 1 == 241
        assert region.contains(track.x_m, track.y_m).all()
        x0, y0, x1, y1 = track.bounds_m()
        assert x0 >= 135.0 and y0 >= 135.0 and x1 <= 1200.0 - 135.0 and y1 <= 1400.0 - 135.0
        # constant speed: about 2.5 km in 60 s (process noise 0.2 m/s per step averages out)
        assert track.length_m == pytest.approx(2500.0, rel=0.01)
        max_rate = math.radians(cfg.turn_rate_deg_s) + 5 * math.radians(cfg.yaw_rate_noise_deg_s)
        assert np.all(np.abs(track.yaw_rate_radps) <= max_rate)
        assert np.all(np.abs(track.altitude_m - cfg.altitude_m) <= 3.0 * cfg.altitude_noise_m)


def test_track_follows_motion_model():
    cfg = FlightConfig()
    track = sample_track(cfg, _paper_region(), np.random.default_rng(3))
    dt = cfg.dt_s
    half = track.yaw_rad[:-1] + 0.5 * track.yaw_rate_radps[1:] * dt
    np.testing.assert_allclose(np.diff(track.x_m), track.speed_mps[1:] * dt * np.cos(half), atol=1e-9)
    np.testing.assert_allclose(np.diff(track.y_m), track.speed_mps[1:] * dt * np.sin(half), atol=1e-9)
    dyaw = wrap_angle(np.diff(track.yaw_rad) - track.yaw_rate_radps[1:] * dt)
    np.testing.assert_allclose(dyaw, 0.0, atol=1e-9)


def test_same_seed_same_track_other_seed_other_track():
    cfg, region = FlightConfig(), _paper_region()
    a = sample_track(cfg, region, np.random.default_rng(7))
    b = sample_track(cfg, region, np.random.default_rng(7))
    c = sample_track(cfg, region, np.random.default_rng(8))
    np.testing.assert_array_equal(a.x_m, b.x_m)
    np.testing.assert_array_equal(a.yaw_rad, b.yaw_rad)
    assert not np.allclose(a.x_m[:5], c.x_m[:5])


def test_nodata_is_avoided():
    # map 400 x 400 m at 1 m/px with the west half no-data: the vehicle must stay east of 200 m + clearance.
    nodata = np.zeros((400, 400), dtype=bool)
    nodata[:, :200] = True
    region = FlyableRegion(400.0, 400.0, 30.0, nodata=nodata)
    cfg = FlightConfig(altitude_m=50.0, speed_mps=5.0, duration_s=20.0, turn_rate_deg_s=30.0, min_leg_m=50.0)
    track = sample_track(cfg, region, np.random.default_rng(0))
    assert track.x_m.min() >= 230.0 - 1e-9
    assert region.contains(track.x_m, track.y_m).all()


def test_small_map_shortens_track_and_tiny_map_is_an_error():
    cfg = FlightConfig()  # 41.7 m/s: a 150 x 150 m flyable square cannot hold 60 s
    region = FlyableRegion(400.0, 400.0, 120.0)
    track = sample_track(cfg, region, np.random.default_rng(0))
    assert cfg.min_steps <= len(track) - 1 < cfg.steps
    assert region.contains(track.x_m, track.y_m).all()
    with pytest.raises(MapError, match="too small"):
        sample_track(cfg, FlyableRegion(200.0, 200.0, 120.0), np.random.default_rng(0))


def test_measurement_noise_statistics():
    cfg = FlightConfig(duration_s=600.0)
    track = sample_track(cfg, FlyableRegion(20000.0, 20000.0, 100.0), np.random.default_rng(1))
    n = len(track)
    assert n == cfg.steps + 1
    m = measure(track, np.random.default_rng(2), speed_std_mps=0.1, yaw_rate_std_radps=0.05,
                heading_std_rad=0.02, altitude_std_m=1.0)
    assert m.odometry.dtype == np.float32 and m.odometry.shape == (n, 3)
    np.testing.assert_allclose(m.odometry[0], [track.speed_mps[0], track.yaw_rate_radps[0], 0.0], rtol=1e-6)
    err_v = m.odometry[1:, 0] - track.speed_mps[1:]
    err_h = wrap_angle(m.yaw_rad.astype(np.float64) - track.yaw_rad)
    # sample std of n-1 = 2400 draws: relative standard error 1/sqrt(2 * 2400) ~ 1.4 %; allow 5 sigma.
    tol = 5.0 / math.sqrt(2 * (n - 1))
    assert np.std(err_v) == pytest.approx(0.1, rel=tol)
    assert np.std(err_h) == pytest.approx(0.02, rel=tol)
    assert abs(np.mean(err_v)) < 5 * 0.1 / math.sqrt(n - 1)
    assert np.all(np.abs(m.yaw_rad) <= np.float32(math.pi))


def test_flight_config_rejects_out_of_range():
    with pytest.raises(ConfigError, match="altitude_m"):
        build_config(FlightConfig, {"altitude_m": -5.0}, where="test")
    with pytest.raises(ConfigError, match="unknown key"):
        build_config(FlightConfig, {"altitude": 100.0}, where="test")


def test_duration_too_short_for_any_track_names_duration_not_the_map():
    with pytest.raises(ConfigError, match=r"duration_s.*min_steps") as err:
        build_config(FlightConfig, {"duration_s": 1.0, "rate_hz": 4.0, "min_steps": 8}, where="spec [flight]")
    assert "map too small" not in str(err.value)


@pytest.mark.parametrize("altimeter, field, allowed", [
    ({"bias_std_m": 500.0}, "bias_std_m = 500 m", r"bias_std_m in \[0, 33\.33\] m"),
    ({"bias_std_m": 30.0, "drift_std_m_per_sqrt_s": 2.0}, "bias_std_m = 30 m", r"bias_std_m in \[0, 29\.51\] m"),
    ({"drift_std_m_per_sqrt_s": 10.0}, r"drift_std_m_per_sqrt_s = 10 m/sqrt\(s\)",
     r"drift_std_m_per_sqrt_s in \[0, 4\.303\] m/sqrt\(s\)"),
])
def test_an_altimeter_error_too_large_for_the_altitude_names_the_field_and_its_range(altimeter, field, allowed):
    """3 sigma of the error at the end of the flight (bias and drift) must stay within half the altitude: at
    200 m for 60 s, sqrt(bias^2 + drift^2 60) <= 33.3 m."""
    flight = FlightConfig(altitude_m=200.0, duration_s=60.0)
    with pytest.raises(ConfigError, match=rf"^spec: altimeter\.{field} is too large for flight\.altitude_m = 200 m"
                                          rf".*allowed at this altitude: altimeter\.{allowed}"):
        AltimeterConfig(**altimeter).check_flight(flight, "spec")


def test_an_altimeter_error_within_half_the_altitude_is_accepted():
    flight = FlightConfig(altitude_m=200.0, duration_s=60.0)
    AltimeterConfig(bias_std_m=33.3).check_flight(flight, "spec")
    AltimeterConfig(bias_std_m=2.0, drift_std_m_per_sqrt_s=4.0).check_flight(flight, "spec")   # sqrt(4 + 960)


# ------------------------------------------------------------------------------------------------- wind, crab
def _crab_track(wind_e: float, wind_n: float, airspeed: float = 22.0):
    """A noise-free track through a steady wind over a large region (long straight legs)."""
    cfg = FlightConfig(speed_mps=airspeed, duration_s=120.0, speed_noise_mps=0.0, yaw_rate_noise_deg_s=0.0,
                       altitude_noise_m=0.0, min_leg_m=1500.0)
    wind = WindConfig(speed_range_mps=(math.hypot(wind_e, wind_n),) * 2,
                      from_deg_range=((math.degrees(math.atan2(-wind_e, -wind_n)) % 360.0),) * 2)
    field = wind.draw(np.random.default_rng(0), np.arange(cfg.steps + 1) * cfg.dt_s)
    np.testing.assert_allclose([field.east_mps[0], field.north_mps[0]], [wind_e, wind_n], atol=1e-12)
    return cfg, sample_track(cfg, FlyableRegion(8000.0, 8000.0, 100.0), np.random.default_rng(5), field)


def test_a_crab_of_known_wind_gives_the_expected_heading_track_difference_and_odometry():
    """5 m/s from the north at 22 m/s of airspeed: on straight legs the course points at the waypoint and the
    heading is the course minus asin(w_perp / v); the ground velocity is the air velocity plus the wind; the
    body-frame odometry is (v + w . forward, w . left), noise-free here."""
    w_e, w_n, v = 0.0, -5.0, 22.0
    cfg, track = _crab_track(w_e, w_n, v)
    dt = cfg.dt_s
    assert len(track) == cfg.steps + 1
    dx, dy = np.diff(track.x_m), np.diff(track.y_m)
    half = track.yaw_rad[:-1] + 0.5 * track.yaw_rate_radps[1:] * dt
    # the ground displacement: airspeed along the mid-step heading plus the wind, every step
    np.testing.assert_allclose(dx, v * dt * np.cos(half) + w_e * dt, atol=1e-9)
    np.testing.assert_allclose(dy, v * dt * np.sin(half) + w_n * dt, atol=1e-9)
    # on the straight legs (no turn commanded) the drift angle is the wind triangle's
    straight = np.abs(track.yaw_rate_radps[1:]) < 1e-9
    assert straight.sum() > 200
    course = np.arctan2(dy, dx)[straight]
    cross = w_n * np.cos(course) - w_e * np.sin(course)
    drift = wrap_angle(half[straight] - course)
    np.testing.assert_allclose(drift, -np.arcsin(cross / v), atol=1e-9)
    assert np.max(np.abs(drift)) > math.radians(10.0)       # the legs do cross the wind: up to 13 deg of crab
    # the body-frame ground velocity, and the odometry that measures it
    fwd = v + w_e * np.cos(half) + w_n * np.sin(half)
    left = w_n * np.cos(half) - w_e * np.sin(half)
    np.testing.assert_allclose(track.forward_mps[1:], fwd, atol=1e-12)
    np.testing.assert_allclose(track.lateral_mps[1:], left, atol=1e-12)
    np.testing.assert_allclose(np.hypot(track.forward_mps[1:], track.lateral_mps[1:]), np.hypot(dx, dy) / dt,
                               atol=1e-9)
    m = measure(track, np.random.default_rng(1), speed_std_mps=0.0, yaw_rate_std_radps=0.0, heading_std_rad=0.0,
                altitude_std_m=0.0)
    np.testing.assert_allclose(m.odometry[1:, 0], fwd, rtol=1e-6)
    np.testing.assert_allclose(m.odometry[1:, 2], left, rtol=1e-6, atol=1e-5)


def test_crab_heading_solves_the_wind_triangle():
    v = 22.0
    for course in (0.0, 0.7, -2.0, 3.0):
        for w_e, w_n in ((0.0, -5.0), (3.0, 4.0), (-8.0, 1.0)):
            h = crab_heading(course, w_e, w_n, v)
            ground = (v * math.cos(h) + w_e, v * math.sin(h) + w_n)
            # the ground velocity points along the course (no component across it, positive along it)
            assert -ground[0] * math.sin(course) + ground[1] * math.cos(course) == pytest.approx(0.0, abs=1e-9)
            assert ground[0] * math.cos(course) + ground[1] * math.sin(course) > 0.0
    assert crab_heading(0.4, 0.0, 0.0, v) == 0.4
    # a crosswind beyond the airspeed's reach: the crab is held at asin(MAX_CROSSWIND_SHARE)
    assert crab_heading(0.0, 0.0, -50.0, v) == pytest.approx(math.asin(MAX_CROSSWIND_SHARE))


def test_calm_air_leaves_the_track_as_it_was():
    """Without wind the body-frame velocity is (airspeed, 0) exactly, and an explicit calm field flies the same
    track as none."""
    cfg = FlightConfig()
    track = sample_track(cfg, _paper_region(), np.random.default_rng(3))
    assert np.array_equal(track.forward_mps, track.speed_mps) and not np.any(track.lateral_mps)
    calm = WindConfig().draw(np.random.default_rng(0), np.arange(cfg.steps + 1) * cfg.dt_s)
    again = sample_track(cfg, _paper_region(), np.random.default_rng(3), calm)
    for name in ("x_m", "y_m", "yaw_rad", "speed_mps", "forward_mps", "lateral_mps"):
        assert np.array_equal(getattr(track, name), getattr(again, name))


def test_the_integrations_scalar_wrap_and_region_lookup_equal_the_vectorized_ones():
    """``_fly`` integrates in Python floats: its angle wrap and point lookup give the NumPy functions' values bit for
    bit, at random points, on cell edges, at the wrap's edges, outside the map and for NaN."""
    rng = np.random.default_rng(3)
    nodata = np.zeros((300, 400), bool)
    nodata[100:140, 200:260] = True
    region = FlyableRegion(400.0, 300.0, 20.0, nodata=nodata, cell_m=2.5)
    xy = [*rng.uniform(-30.0, 430.0, (4000, 2)),
          *[(2.5 * i, 2.5 * j) for i in range(-1, 162, 7) for j in range(-1, 122, 5)],
          (0.0, 0.0), (-0.0, -0.0), (400.0, 150.0), (399.999999, 299.999999), (np.nan, 5.0), (5.0, np.inf)]
    got = [region.contains_point(float(x), float(y)) for x, y in xy]
    with np.errstate(invalid="ignore"):      # (NaN and inf cast to cell indices: outside)
        assert got == region.contains(*np.array(xy).T).tolist()
    assert 0 < sum(got) < len(got)
    angles = [*rng.uniform(-20.0, 20.0, 4000), 0.0, -0.0, math.pi, -math.pi, 3 * math.pi, -3 * math.pi, 1e9]
    for a in angles:
        assert _wrap(a) == float(wrap_angle(a)) and math.copysign(1.0, _wrap(a)) == math.copysign(1.0, wrap_angle(a))
