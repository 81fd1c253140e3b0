"""The compiled pass of ``estimators/mcl/resampling.py``: the inverse-CDF lookup every scheme ends with."""

from __future__ import annotations

import numpy as np
from numba import njit

from aerial_loc_env.jit import JIT


@njit(**JIT)
def inverse_cdf_indices(W, su, out):
    """``out[j]`` = ``min(searchsorted(cdf, su[j], side="right"), N - 1)`` with ``cdf`` = ``np.cumsum(W)`` (its
    running sum, in order, as NumPy accumulates) and its last value set to 1: the NumPy expressions it replaces,
    without their three calls' fixed costs. The binary search compares as NumPy's does (a NaN in ``cdf`` sorts
    after every number), so any ``su`` gives NumPy's indices."""
    n = W.shape[0]
    cdf = np.empty(n)
    acc = 0.0
    for i in range(n):
        acc += W[i]
        cdf[i] = acc
    cdf[n - 1] = 1.0
    for j in range(su.shape[0]):
        x = su[j]
        lo, hi = 0, n
        while lo < hi:                        # the first index whose cdf is greater than x
            mid = (lo + hi) >> 1
            c = cdf[mid]
            if x < c or (c != c and x == x):
                hi = mid
            else:
                lo = mid + 1
        out[j] = min(lo, n - 1)
    return out
