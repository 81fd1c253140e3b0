"""Flight: tracks stay over valid map, follow eq. (1), are reproducible; sensors carry their noise."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.sensors.flight import AltimeterConfig, FlightConfig, measure, sample_track, wrap_angle
from aerial_loc_env.world.maps.region import FlyableRegion


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
    assert m.odometry.dtype == np.float32 and m.odometry.shape == (n, 2)
    np.testing.assert_allclose(m.odometry[0], [track.speed_mps[0], track.yaw_rate_radps[0]], rtol=1e-6)
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
