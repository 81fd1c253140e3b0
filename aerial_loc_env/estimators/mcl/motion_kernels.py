"""The compiled pass of ``estimators/mcl/motion.py``: the odometry motion model's per-particle update."""

from __future__ import annotations

import math

from numba import njit

from aerial_loc_env.jit import JIT


@njit(**JIT)
def _move(states, z, cos, sin, xy, speed, speed_std, dt, yaw, yaw_std, rate, rate_std, lateral, lateral_std, jitter):
    """``propagate``'s arithmetic per particle i, given its heading's ``cos``/``sin`` (N,): forward speed ``v =
    speed + speed_std z[i]``, lateral speed ``l = lateral + lateral_std z[M + i]`` (``M`` = 3N for ``xy``, 2N
    otherwise), ``x += v dt cos - l dt sin``, ``y += v dt sin + l dt cos``; the yaw ``wrap(yaw + yaw_std z[2N +
    i])`` (``xy``) or ``wrap(yaw_i + omega dt)``, ``omega = rate + rate_std z[N + i]``; then the jitter ``jitter
    z`` from the draws after the first M + N, two a particle. ``%`` is Python's float remainder, as NumPy's (fmod,
    then the divisor added when the signs differ)."""
    n = states.shape[0]
    pi, two_pi = math.pi, 2.0 * math.pi
    side = (3 if xy else 2) * n
    after = side + n
    for i in range(n):
        v = speed + speed_std * z[i]
        lat = lateral + lateral_std * z[side + i]
        states[i, 0] += v * dt * cos[i] - lat * dt * sin[i]
        states[i, 1] += v * dt * sin[i] + lat * dt * cos[i]
        if xy:
            states[i, 2] = (yaw + yaw_std * z[2 * n + i] + pi) % two_pi - pi
        else:
            states[i, 2] = (states[i, 2] + (rate + rate_std * z[n + i]) * dt + pi) % two_pi - pi
        if jitter > 0:
            states[i, 0] += jitter * z[after + 2 * i]
            states[i, 1] += jitter * z[after + 2 * i + 1]
