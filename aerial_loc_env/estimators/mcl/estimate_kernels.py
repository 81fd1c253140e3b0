"""The compiled passes of ``estimators/mcl/estimate.py``: a particle cloud's weighted mean and covariance.

Each is ``portable.matmul``'s arithmetic on the NumPy expressions it replaced (``W @ xy``; ``(d * W[:, None]).T @ d``
with ``d = xy - c``): every sum starts at 0 and adds its products in particle order, each product rounded apart
(numba without fastmath fuses nothing), so the floats are the same (tests/estimators/test_estimate.py); one call
instead of the expression's temporaries and copies, on the cloud's (N, 2) view of its states as it is.
"""

from __future__ import annotations

import numba as nb

from aerial_loc_env.jit import JIT


@nb.njit(**JIT)
def weighted_mean(xy, W, out):
    """``out`` (2,) = ``W @ xy`` for positions ``xy`` (N, 2) and weights ``W`` (N,), float64."""
    for j in range(2):
        s = 0.0
        for t in range(W.shape[0]):
            s += W[t] * xy[t, j]
        out[j] = s


@nb.njit(**JIT)
def weighted_cov(xy, W, c, out):
    """``out`` (2, 2) = ``(d * W[:, None]).T @ d``, ``d = xy - c``: the weighted covariance of ``xy`` (N, 2) about
    ``c`` (2,), float64."""
    c0, c1 = c[0], c[1]
    s00 = s01 = s10 = s11 = 0.0
    for t in range(W.shape[0]):
        d0, d1, w = xy[t, 0] - c0, xy[t, 1] - c1, W[t]
        e0, e1 = d0 * w, d1 * w
        s00 += e0 * d0
        s01 += e0 * d1
        s10 += e1 * d0
        s11 += e1 * d1
    out[0, 0], out[0, 1], out[1, 0], out[1, 1] = s00, s01, s10, s11
