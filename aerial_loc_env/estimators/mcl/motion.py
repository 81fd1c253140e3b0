"""The motion model p(x_t | x_{t-1}, u_t) from the odometry and its noise (second reference, eq. (1), with the
body-frame lateral speed added so that a crabbing vehicle's motion is represented).

Over a step ``dt`` with forward speed ``v``, lateral speed ``l`` (positive to the left) and yaw rate ``omega``::

    x += (v cos(psi_mid) - l sin(psi_mid)) dt;  y += (v sin(psi_mid) + l cos(psi_mid)) dt;  yaw += omega dt,

    psi_mid = yaw + omega dt / 2.

Without wind ``l`` is zero (up to its noise) and this is eq. (1).

Two state layouts (``states`` is always (N, 3) = [x_m, y_m, yaw_rad], so that the measurement models see one
layout):

- ``"xy"`` (the primary paper: the gimbal/compass heading is measured): ``psi_mid`` is the circular mean of the
  previous and current measured headings (their noises average down by sqrt 2 and the yaw rate's noise cancels),
  and each particle carries the measured heading plus its own compass-noise draw, so that the measurement
  weights the heading hypotheses too;
- ``"xyyaw"``: the yaw is a state propagated with the noisy yaw rate (eq. (1)); the measured heading then enters
  as a compass factor of the likelihood (``compass_log_likelihood``).

Noise per particle: speed ``N(v, s_v^2)``, lateral speed ``N(l, s_l^2)``, heading ``N(psi, s_psi^2)`` (or yaw
rate ``N(omega, s_w^2)``), all scaled by ``noise_scale``, plus an isotropic roughening ``jitter_std_m`` that keeps
the cloud from collapsing onto a few copies when it is resampled every step (the odometry noise alone moves
particles by ~0.1 m a step).
"""

from __future__ import annotations

import math

import numpy as np

from aerial_loc_env.env.briefing import OdometryNoise
from aerial_loc_env.estimators.mcl.motion_kernels import _move
from aerial_loc_env.estimators.protocol import Observation


def wrap(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap radians to [-pi, pi)."""
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


def _wrap_float(a: float) -> float:
    """``wrap`` of one float without NumPy's scalar overhead: Python's float remainder is NumPy's (fmod, then the
    divisor added when the signs differ), so the same float."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def mid_heading(prev_yaw_rad: float | None, yaw_rad: float, yaw_rate_radps: float, dt_s: float) -> float:
    """The heading over the last step: mean of the two measured headings, or yaw - omega dt / 2 at the start."""
    if prev_yaw_rad is None:
        return _wrap_float(float(yaw_rad) - 0.5 * yaw_rate_radps * dt_s)
    return _wrap_float(float(prev_yaw_rad) + 0.5 * _wrap_float(float(yaw_rad) - float(prev_yaw_rad)))


class OdometryMotionModel:
    """Propagates (N, 3) particle states by the measured odometry with per-particle noise, vectorized."""

    def __init__(self, noise: OdometryNoise, dt_s: float, *, state: str = "xy", noise_scale: float = 1.0,
                 jitter_std_m: float = 0.0) -> None:
        if state not in ("xy", "xyyaw"):
            raise ValueError(f"motion: state must be 'xy' or 'xyyaw', got {state!r}")
        self.noise, self.dt_s, self.state = noise, float(dt_s), state
        self.noise_scale, self.jitter_std_m = float(noise_scale), float(jitter_std_m)
        self.prev_yaw_rad: float | None = None

    def reset(self) -> None:
        self.prev_yaw_rad = None

    def init_yaw(self, n: int, yaw_rad: float | None, rng: np.random.Generator) -> np.ndarray:
        """Initial yaw column: the measured heading with compass noise, or uniform when none is known."""
        if yaw_rad is None:
            return rng.uniform(-math.pi, math.pi, n)
        return wrap(yaw_rad + rng.normal(0.0, self.noise.heading_std_rad * self.noise_scale, n))

    def propagate(self, states: np.ndarray, obs: Observation, rng: np.random.Generator) -> np.ndarray:
        """Move every particle over the last step (in place; also returned).

        All the step's normal draws come from ONE ``standard_normal`` call, scaled per use: the same numbers,
        in the same order, as one ``rng.normal(0, std, n)`` call per noise term (``normal`` is
        ``0 + std * z`` over the same stream), without the fixed cost of five calls on N = 700 (order: forward
        speed, heading or yaw rate, the yaw (``"xy"``), the lateral speed, the jitter). The headings' cos and sin
        are NumPy's; the rest is one compiled pass (``_move``: the same float operations, in the same
        order, as the NumPy expressions it replaced, tests/estimators/test_motion.py).
        """
        n = states.shape[0]
        k, dt = self.noise_scale, self.dt_s
        xy = self.state == "xy"
        m = 4 if xy else 3                                    # draws per particle before the jitter
        z = rng.standard_normal((m + 2 if self.jitter_std_m > 0 else m) * n)
        if xy:
            heading = mid_heading(self.prev_yaw_rad, obs.yaw_rad, obs.yaw_rate_radps, dt)
            psi = heading + self.noise.heading_std_rad * k / math.sqrt(2.0) * z[n:2 * n]
        else:
            omega = obs.yaw_rate_radps + self.noise.yaw_rate_std_radps * k * z[n:2 * n]
            psi = states[:, 2] + 0.5 * omega * dt
        _move(states, z, np.cos(psi), np.sin(psi), xy, obs.speed_mps, self.noise.speed_std_mps * k, dt,
              obs.yaw_rad, self.noise.heading_std_rad * k, obs.yaw_rate_radps, self.noise.yaw_rate_std_radps * k,
              obs.lateral_mps, self.noise.lateral_std_mps * k, self.jitter_std_m)
        self.prev_yaw_rad = obs.yaw_rad
        return states

    def compass_log_likelihood(self, states: np.ndarray, yaw_rad: float) -> np.ndarray:
        """The measured heading as a Gaussian factor on the yaw state (``"xyyaw"`` only; 0 for ``"xy"``)."""
        if self.state == "xy":
            return np.zeros(states.shape[0])
        s = max(self.noise.heading_std_rad, 1e-3)
        d = wrap(states[:, 2] - yaw_rad)
        return -0.5 * (d / s) ** 2


