"""Compiled (numba) kernels of the learned measurement model (``learned.py``): the encoder's convolutions as
sums of shifted planes, and the correlation of the frame's embedding over the map's.

The convolutions work on planes (one channel per row of a 2-D array) laid out with a row pitch shared by the
input and the output, so that each tap of a kernel (and each phase of a strided one, ``learned.Encoder``) is one
offset into a flat plane and a layer is a list of (plane, offset, weight) terms summed into each output plane.
The inner loop reads three shifted input runs and updates four output channels with them, contiguous runs that
LLVM vectorizes with AVX2 as with AVX-512 (twelve fused multiply-adds a step for seven loads). The order of the
sums is the code's: the same on every CPU with FMA (libm's ``fmaf`` elsewhere: the same values, slower).

Conventions (``jit.JIT``), one thread, float32 arithmetic; the first call of a process compiles (cached on disk).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from aerial_loc_env.jit import JIT as _JIT
from aerial_loc_env.jit import fma32 as _fma32
from aerial_loc_env.jit import wide_vectors as _wide_vectors

#: output elements per block: four output runs and three input runs of it stay in the first-level cache
_BLOCK = 1024
#: output channels and terms per step of the inner loop (``conv_terms``' arrays are padded to multiples)
OUT_GROUP, TERM_GROUP = 4, 3


@njit(**_JIT)
def conv_terms(src, plane, offset, weight, bias, n, relu, out):
    """``out[o, j] = bias[o] + sum_t weight[o, t] * src[plane[t], j + offset[t]]`` for ``j < n``, then
    ``max(., 0)`` where ``relu``.

    ``src`` (planes, L) and ``out`` (O, >= n) float32 C-contiguous, ``L >= n + max(offset)``; ``weight`` (O, T)
    with O a multiple of ``OUT_GROUP`` and T of ``TERM_GROUP`` (padding terms have weight 0); terms are summed
    in their order, one fused multiply-add each."""
    _wide_vectors()
    n_out, n_terms = weight.shape
    zero = np.float32(0.0)
    for j0 in range(0, n, _BLOCK):
        m = min(_BLOCK, n - j0)
        for o in range(0, n_out, OUT_GROUP):
            o0 = out[o, j0:j0 + m]
            o1 = out[o + 1, j0:j0 + m]
            o2 = out[o + 2, j0:j0 + m]
            o3 = out[o + 3, j0:j0 + m]
            b0, b1, b2, b3 = bias[o], bias[o + 1], bias[o + 2], bias[o + 3]
            for j in range(m):
                o0[j] = b0
                o1[j] = b1
                o2[j] = b2
                o3[j] = b3
            for t in range(0, n_terms, TERM_GROUP):
                a0 = j0 + offset[t]
                a1 = j0 + offset[t + 1]
                a2 = j0 + offset[t + 2]
                xa = src[plane[t], a0:a0 + m]
                xb = src[plane[t + 1], a1:a1 + m]
                xc = src[plane[t + 2], a2:a2 + m]
                w0a, w0b, w0c = weight[o, t], weight[o, t + 1], weight[o, t + 2]
                w1a, w1b, w1c = weight[o + 1, t], weight[o + 1, t + 1], weight[o + 1, t + 2]
                w2a, w2b, w2c = weight[o + 2, t], weight[o + 2, t + 1], weight[o + 2, t + 2]
                w3a, w3b, w3c = weight[o + 3, t], weight[o + 3, t + 1], weight[o + 3, t + 2]
                for j in range(m):
                    a = xa[j]
                    b = xb[j]
                    c = xc[j]
                    o0[j] = _fma32(w0c, c, _fma32(w0b, b, _fma32(w0a, a, o0[j])))
                    o1[j] = _fma32(w1c, c, _fma32(w1b, b, _fma32(w1a, a, o1[j])))
                    o2[j] = _fma32(w2c, c, _fma32(w2b, b, _fma32(w2a, a, o2[j])))
                    o3[j] = _fma32(w3c, c, _fma32(w3b, b, _fma32(w3a, a, o3[j])))
            if relu:
                for j in range(m):
                    o0[j] = max(o0[j], zero)
                    o1[j] = max(o1[j], zero)
                    o2[j] = max(o2[j], zero)
                    o3[j] = max(o3[j], zero)


@njit(**_JIT)
def unit_cells(planes, channels, rows, cols, pitch, out):
    """``out[r, c, :]`` (rows, cols, channels) = the unit vector along the channels of ``planes[:channels, r
    pitch + c]`` (a zero vector stays zero: the norm is floored at 1e-6); the squares summed in channel order."""
    tiny = np.float32(1e-6)
    for r in range(rows):
        for c in range(cols):
            j = r * pitch + c
            s = np.float32(0.0)
            for k in range(channels):
                v = planes[k, j]
                s = _fma32(v, v, s)
            norm = max(np.sqrt(s), tiny)
            for k in range(channels):
                out[r, c, k] = planes[k, j] / norm


#: lanes of ``correlate_cells``' partial sums, and the template rows it adds in one pass
_LANES, _ROWS = 16, 4


@njit(**_JIT)
def correlate_cells(cells, template, first, stop, rows, cols, out):
    """``out[i]`` = the correlation (the sum over the template's cells and channels of their products) of
    ``template`` (h, w, C) placed with its cell (0, 0) on ``cells``' (H, W, C) cell (``rows[i]``, ``cols[i]``),
    both float32 C-contiguous; template row r is read over its columns ``first[r]`` to ``stop[r]`` only (its other
    cells are 0: outside the frame's footprint).

    The products are summed per template element across rows (a run of ``w C`` partial sums, vectorized along
    each row's run), then the partial sums folded ``_LANES`` at a time and the lanes added in turn: a fixed order,
    the same with any vector width."""
    _wide_vectors()
    th, tw, nc = template.shape
    width = cells.shape[1]
    run = tw * nc
    padded = -(-run // _LANES) * _LANES
    acc = np.zeros(padded, np.float32)
    tf = template.ravel()
    cf = cells.ravel()
    for i in range(rows.shape[0]):
        for j in range(padded):
            acc[j] = 0.0
        r = 0
        while r < th:
            g = min(_ROWS, th - r)
            lo, hi = tw, 0                       # the group's rows' columns (their union: zeros in between)
            for q in range(r, r + g):
                if stop[q] > first[q]:
                    lo = min(lo, first[q])
                    hi = max(hi, stop[q])
            if hi > lo:
                n = (hi - lo) * nc
                # unsigned indices: no negative-index wraparound in the loops, which then vectorize
                a0 = np.uint64(lo * nc)
                t0 = np.uint64(r * run + lo * nc)
                c0 = np.uint64(((rows[i] + r) * width + cols[i] + lo) * nc)
                if g == _ROWS:
                    t1, t2, t3 = t0 + np.uint64(run), t0 + np.uint64(2 * run), t0 + np.uint64(3 * run)
                    step = np.uint64(width * nc)
                    c1, c2, c3 = c0 + step, c0 + np.uint64(2) * step, c0 + np.uint64(3) * step
                    for j in range(n):
                        u = np.uint64(j)
                        acc[a0 + u] = _fma32(tf[t3 + u], cf[c3 + u], _fma32(tf[t2 + u], cf[c2 + u], _fma32(
                            tf[t1 + u], cf[c1 + u], _fma32(tf[t0 + u], cf[c0 + u], acc[a0 + u]))))
                else:
                    for q in range(g):
                        tq = t0 + np.uint64(q * run)
                        cq = c0 + np.uint64(q * width * nc)
                        for j in range(n):
                            u = np.uint64(j)
                            acc[a0 + u] = _fma32(tf[tq + u], cf[cq + u], acc[a0 + u])
            r += g
        for b in range(_LANES, padded, _LANES):
            for j in range(_LANES):
                acc[j] += acc[b + j]
        s = np.float32(0.0)
        for j in range(_LANES):
            s += acc[j]
        out[i] = s
