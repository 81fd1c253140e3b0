"""The compiled pass of ``estimators/mcl/resampling.py``: the inverse-CDF lookup every scheme ends with."""

from __future__ import annotations

import numpy as np
from numba import njit

from aerial_loc_env.estimators.shadow_detection_kernels import _pairwise_sum
from aerial_loc_env.jit import JIT


@njit(**JIT)
def inverse_cdf_indices(W, su, out):
    """``out[j]`` = ``min(searchsorted(cdf, su[j], side="right"), N - 1)`` with ``cdf`` = ``np.cumsum(W)`` (its
    running sum, in order, as NumPy accumulates) and its last value set to 1: the NumPy expressions it replaces,
    without their three calls' fixed costs. ``W`` >= 0 (weights), so ``cdf`` is sorted. Each key's index is the
    first whose cdf exceeds it (compared as NumPy compares: a NaN key after every number); a key not below the
    previous one starts from the previous index and walks up (sorted keys, every scheme's: one pass over
    ``cdf``), any other is searched by bisection."""
    n = W.shape[0]
    cdf = np.empty(n)
    acc = 0.0
    for i in range(n):
        acc += W[i]
        cdf[i] = acc
    cdf[n - 1] = 1.0
    lo = 0
    prev = -np.inf
    for j in range(su.shape[0]):
        x = su[j]
        if x >= prev:                         # walk up from the previous key's index
            while lo < n and not (x < cdf[lo]):
                lo += 1
        else:
            lo, hi = 0, n
            while lo < hi:
                mid = (lo + hi) >> 1
                if x < cdf[mid]:
                    hi = mid
                else:
                    lo = mid + 1
        if x != x:                            # NaN: after every number
            lo = n
        prev = x
        out[j] = min(lo, n - 1)
    return out


@njit(**JIT)
def max_and_shift(log_w, out):
    """NumPy's ``np.max(log_w)`` (NaN if any is NaN) and, when it is finite, ``out`` = ``log_w - max`` (the
    subtraction NumPy does); ``out`` untouched otherwise."""
    m = -np.inf
    nan = False
    for i in range(log_w.shape[0]):
        x = log_w[i]
        if x != x:
            nan = True
        elif x > m:
            m = x
    if nan:
        return np.nan
    if np.isfinite(m):
        for i in range(log_w.shape[0]):
            out[i] = log_w[i] - m
    return m


@njit(**JIT)
def sum_and_divide(w, out):
    """``s = w.sum()`` (NumPy's pairwise float64 sum) and ``out`` = ``w / s``; returns ``s``."""
    s = _pairwise_sum(w, 0, w.shape[0])
    for i in range(w.shape[0]):
        out[i] = w[i] / s
    return s
