"""Compiled loops of ``portable``: one scalar libm call per element, products summed in index order.

Why loops: NumPy's vectorized transcendental functions and OpenBLAS's products take a different code path on each
CPU (AVX-512, AVX2, NEON), and those paths round differently. A loop of libm calls, which LLVM cannot vectorize
without a vector math library, and a sum taken in index order (numba reassociates nothing without fastmath) give
the same floats on every CPU.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from aerial_loc_env.jit import JIT as _JIT


def _elementwise(f):
    """``kernel(x, out)``: ``out[i] = f(x[i])`` over flat arrays, ``f`` a ``math`` function given only arguments
    inside its domain (the caller's wrapper keeps NaN in and out; see ``_domain``)."""

    @nb.njit(**_JIT)
    def kernel(x, out):
        for i in range(x.size):
            out[i] = f(x[i])
    return kernel


@nb.njit(inline="always", **_JIT)
def _log_or_limit(v):
    return math.log(v) if v > 0 else (-np.inf if v == 0 else np.nan)


@nb.njit(inline="always", **_JIT)
def _log1p_or_limit(v):
    return math.log1p(v) if v > -1 else (-np.inf if v == -1 else np.nan)


@nb.njit(inline="always", **_JIT)
def _asin_or_nan(v):
    return math.asin(v) if -1 <= v <= 1 else np.nan


@nb.njit(inline="always", **_JIT)
def _atanh_or_limit(v):
    a = abs(v)
    return math.atanh(v) if a < 1 else (math.copysign(np.inf, v) if a == 1 else np.nan)


exp = _elementwise(math.exp)
log = _elementwise(_log_or_limit)
log1p = _elementwise(_log1p_or_limit)
arcsin = _elementwise(_asin_or_nan)
arctan = _elementwise(math.atan)
arctanh = _elementwise(_atanh_or_limit)
sinh = _elementwise(math.sinh)
cosh = _elementwise(math.cosh)
tan = _elementwise(math.tan)


@nb.njit(**_JIT)
def arctan2(y, x, out):
    for i in range(y.size):
        out[i] = math.atan2(y[i], x[i])


@nb.njit(**_JIT)
def power(x, p, out):
    for i in range(x.size):
        out[i] = x[i] ** p


_WIDE = 16     # columns of ``b`` from which ``matmul`` goes row by row


@nb.njit(**_JIT)
def matmul(a, b, out):
    """``out += a @ b`` for (m, k) and (k, n) (``out`` zeroed): each entry's products added in the order of k.
    Wide ``b`` (a convolution's columns): a row of ``b`` at a time into the row of ``out``, the loop over the
    independent entries vectorized and ``b`` read in its order; narrow ``b`` (a particle cloud's coordinates):
    entry by entry. The same floats either way."""
    m, k = a.shape
    n = b.shape[1]
    for i in range(m):
        row = out[i]
        if n >= _WIDE:
            for t in range(k):
                ait, bt = a[i, t], b[t]
                for j in range(n):
                    row[j] += ait * bt[j]
            continue
        for j in range(n):
            s = row[j]
            for t in range(k):
                s += a[i, t] * b[t, j]
            row[j] = s


@nb.njit(**_JIT)
def dot(a, b):
    """``a @ b`` of two 1-D float64 arrays, the products added in index order."""
    s = 0.0
    for t in range(a.shape[0]):
        s += a[t] * b[t]
    return s
