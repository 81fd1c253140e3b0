"""The odometry motion model (``estimators/mcl/motion.py``): one normal draw moves the particles as one call per
noise term did, bit for bit."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from aerial_loc_env.estimators.mcl.motion import OdometryMotionModel, mid_heading, wrap
from aerial_loc_env.estimators.protocol import Observation


def _propagate_reference(m: OdometryMotionModel, states: np.ndarray, obs: Observation,
                         rng: np.random.Generator) -> np.ndarray:
    """One ``rng.normal`` call per noise term (the code before the single draw)."""
    n = states.shape[0]
    k, dt = m.noise_scale, m.dt_s
    v = obs.speed_mps + rng.normal(0.0, m.noise.speed_std_mps * k, n)
    if m.state == "xy":
        heading = mid_heading(m.prev_yaw_rad, obs.yaw_rad, obs.yaw_rate_radps, dt)
        psi = heading + rng.normal(0.0, m.noise.heading_std_rad * k / math.sqrt(2.0), n)
        yaw = wrap(obs.yaw_rad + rng.normal(0.0, m.noise.heading_std_rad * k, n))
    else:
        omega = obs.yaw_rate_radps + rng.normal(0.0, m.noise.yaw_rate_std_radps * k, n)
        psi = states[:, 2] + 0.5 * omega * dt
        yaw = wrap(states[:, 2] + omega * dt)
    lat = obs.lateral_mps + rng.normal(0.0, m.noise.lateral_std_mps * k, n)
    states[:, 0] += v * dt * np.cos(psi) - lat * dt * np.sin(psi)
    states[:, 1] += v * dt * np.sin(psi) + lat * dt * np.cos(psi)
    states[:, 2] = yaw
    if m.jitter_std_m > 0:
        states[:, :2] += rng.normal(0.0, m.jitter_std_m, (n, 2))
    m.prev_yaw_rad = obs.yaw_rad
    return states


@pytest.mark.parametrize("state", ["xy", "xyyaw"])
@pytest.mark.parametrize("jitter", [0.0, 0.5])
@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_one_normal_draw_moves_the_particles_as_one_call_per_term(state, jitter, scale):
    noise = SimpleNamespace(speed_std_mps=0.3, yaw_rate_std_radps=0.05, heading_std_rad=0.035, lateral_std_mps=0.2)
    new = OdometryMotionModel(noise, 0.25, state=state, noise_scale=scale, jitter_std_m=jitter)
    ref = OdometryMotionModel(noise, 0.25, state=state, noise_scale=scale, jitter_std_m=jitter)
    g = np.random.default_rng(2)
    s0 = np.column_stack([g.uniform(0, 500, 700), g.uniform(0, 500, 700), g.uniform(-np.pi, np.pi, 700)])
    a, b = s0.copy(), s0.copy()
    ra, rb = np.random.default_rng(11), np.random.default_rng(11)
    for t, yaw in enumerate((0.4, 3.13, -3.1405, 1e-17, -np.pi, 2.0)):   # headings across the wrap too
        obs = Observation(np.zeros((4, 4, 3), np.uint8), 12.0 + t, 0.02 * t - 0.05, yaw, 200.0, 1.5 - 0.7 * t)
        new.propagate(a, obs, ra)
        _propagate_reference(ref, b, obs, rb)
        np.testing.assert_array_equal(a, b)
    assert ra.random() == rb.random()        # the same number of draws: later draws are unchanged too


def test_mid_heading_gives_the_floats_of_numpys_wrap():
    """mid_heading wraps Python floats (no NumPy scalars): the same floats as ``float(wrap(...))`` of the
    expressions it computes, across the wrap and at its edges (+-pi, zeros of either sign, tiny and large
    angles)."""
    g = np.random.default_rng(4)
    angles = np.concatenate([g.uniform(-7.0, 7.0, 400), [np.pi, -np.pi, 0.0, -0.0, 1e-17, -1e-300,
                                                          np.nextafter(np.pi, 0), 3 * np.pi, -3 * np.pi, 1e6]])
    for prev in angles[::7]:
        for yaw in angles:
            expected = float(wrap(float(prev) + 0.5 * float(wrap(float(yaw) - float(prev)))))
            got = mid_heading(float(prev), float(yaw), 0.3, 0.25)
            assert got == expected and np.signbit(got) == np.signbit(expected), (prev, yaw)
    for yaw in angles:
        for rate in (-0.4, 0.0, 0.7):
            expected = float(wrap(float(yaw) - 0.5 * rate * 0.25))
            assert mid_heading(None, float(yaw), rate, 0.25) == expected
