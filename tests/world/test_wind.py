"""Wind (world/wind.py): the convention of its direction, the gusts' statistics, calm air drawing nothing, and
the refusal of wind the vehicle cannot fly against."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.env.scenarios import load_scenario
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.world.wind import MAX_WIND_SHARE, WindConfig


def test_calm_air_draws_nothing_and_is_zero():
    rng = np.random.default_rng(4)
    state = rng.bit_generator.state
    field = WindConfig().draw(rng, np.arange(10) * 0.25)
    assert rng.bit_generator.state == state
    assert field.calm and not WindConfig().enabled
    assert field.east_mps.shape == (10,) and not field.east_mps.any() and not field.north_mps.any()


@pytest.mark.parametrize("from_deg, east, north", [(270.0, 1.0, 0.0), (0.0, 0.0, -1.0), (90.0, -1.0, 0.0),
                                                   (180.0, 0.0, 1.0)])
def test_the_direction_is_where_the_wind_blows_from_clockwise_from_north(from_deg, east, north):
    """SITL's SIM_WIND_DIR convention: a westerly (from 270) pushes the vehicle east."""
    cfg = WindConfig(speed_range_mps=(5.0, 5.0), from_deg_range=(from_deg, from_deg))
    field = cfg.draw(np.random.default_rng(0), np.arange(3) * 0.25)
    np.testing.assert_allclose(field.east_mps, 5.0 * east, atol=1e-12)
    np.testing.assert_allclose(field.north_mps, 5.0 * north, atol=1e-12)
    assert field.mean_speed_mps == 5.0 and field.mean_from_deg == pytest.approx(from_deg % 360.0)


def test_a_direction_range_across_north_wraps():
    cfg = WindConfig(speed_range_mps=(2.0, 2.0), from_deg_range=(350.0, 10.0))
    dirs = [cfg.draw(np.random.default_rng(s), np.zeros(1)).mean_from_deg for s in range(200)]
    assert all(d >= 350.0 or d <= 10.0 for d in dirs)
    assert any(d >= 350.0 for d in dirs) and any(d <= 10.0 for d in dirs)


def test_gusts_have_the_stated_variance_and_correlation_time():
    """The Gauss-Markov process: stationary std sigma, lag-k autocorrelation exp(-k dt / tau) (the spectrum
    2 sigma^2 tau / (1 + (2 pi f tau)^2)'s transform), independent axes, zero mean around the mean wind."""
    sigma, tau, dt, n = 1.5, 2.0, 0.25, 400_000
    cfg = WindConfig(speed_range_mps=(4.0, 4.0), from_deg_range=(270.0, 270.0), gust_std_mps=sigma, gust_tau_s=tau)
    field = cfg.draw(np.random.default_rng(1), np.arange(n) * dt)
    g = field.east_mps - 4.0
    # n / (2 tau / dt) = 25000 effectively independent samples: the variance's relative standard error is
    # about sqrt(2 / 25000) ~ 0.9 %, the mean's standard error sigma / sqrt(25000) ~ 0.01 m/s; 5 sigma each
    neff = n * dt / (2.0 * tau)
    assert np.std(g) == pytest.approx(sigma, rel=5.0 * math.sqrt(2.0 / neff) / 2.0)
    assert abs(np.mean(g)) < 5.0 * sigma / math.sqrt(neff)
    for lag in (1, 8):
        r = float(np.mean(g[lag:] * g[:-lag]) / np.var(g))
        assert r == pytest.approx(math.exp(-lag * dt / tau), abs=5.0 * math.sqrt(2.0 / neff))
    other = field.north_mps
    assert abs(float(np.corrcoef(g, other)[0, 1])) < 5.0 / math.sqrt(neff)


def test_the_same_generator_draws_the_same_wind():
    cfg = WindConfig(speed_range_mps=(3.0, 8.0), gust_std_mps=1.0)
    t = np.arange(50) * 0.25
    a, b = cfg.draw(np.random.default_rng(9), t), cfg.draw(np.random.default_rng(9), t)
    c = cfg.draw(np.random.default_rng(10), t)
    assert np.array_equal(a.east_mps, b.east_mps) and np.array_equal(a.north_mps, b.north_mps)
    assert not np.array_equal(a.east_mps, c.east_mps)


def test_wind_too_strong_for_the_airspeed_names_the_fields_and_the_fix():
    with pytest.raises(ConfigError, match=r"wind.speed_range_mps.*gust_std_mps.*flight.speed_mps = 22.*"
                                          r"flight.speed_mps >= "):
        load_scenario("PaperShadows", {"flight.speed_mps": 22.0, "wind.speed_range_mps": [10.0, 12.0],
                                       "wind.gust_std_mps": 1.0})
    # the limit itself is accepted: 8 + 3 x 1.5 = 12.5 <= 0.6 x 22 = 13.2
    sc = load_scenario("PaperShadows", {"flight.speed_mps": 22.0, "wind.speed_range_mps": [8.0, 8.0],
                                        "wind.gust_std_mps": 1.5})
    assert sc.wind.strongest_mps <= MAX_WIND_SHARE * 22.0


def test_bad_wind_fields_are_errors():
    with pytest.raises(ConfigError, match="speed_range_mps.*lo <= hi"):
        build_config(WindConfig, {"speed_range_mps": [5.0, 2.0]}, where="[wind]")
    with pytest.raises(ConfigError, match="gust_tau_s"):
        build_config(WindConfig, {"gust_tau_s": 0.0}, where="[wind]")
    with pytest.raises(ConfigError, match="from_deg_range"):
        build_config(WindConfig, {"from_deg_range": [0.0, 400.0]}, where="[wind]")
    with pytest.raises(ConfigError, match="unknown"):
        build_config(WindConfig, {"speed_mps": 5.0}, where="[wind]")
