"""Compiled (numba) kernels that sample database patches straight from a map level by each particle's affine and
score them in the same loop (issue 12): no coordinate maps, no stacked (N, h, w) samples in memory.

The bilinear sample is OpenCV's ``remap`` (``INTER_LINEAR``, ``BORDER_CONSTANT``) of a float32 level, reproduced
operation for operation: ``ix = floor(u)``, ``a = u - ix``, ``v0 = fma(a, p01 - p00, p00)``,
``v1 = fma(a, p11 - p10, p10)``, ``fma(b, v1 - v0, v0)``, and a neighbour outside the level reads the border
value (NaN in channel 0, 0 in the others: the Scalar ``(nan, 0, 0, 0)`` that ``borderValue=nan`` becomes). With
the coordinates computed as ``PatchSampler`` always computed them (float32 ``e00 col + (e01 row + e02)``) the
samples equal ``cv2.remap``'s bit for bit wherever OpenCV takes its fused-multiply-add vector path (OpenCV >= 4.11
on FMA hardware: every x86-64 since 2013 and ARMv8; measured equal on 1.7 M samples here). Elsewhere the
difference is the rounding of an unfused product: at most 3 float32 ulps of 256 (2^-13 = 1.2e-4 gray levels) a
sample, the tolerance tests/estimators/test_patches_kernels.py derives the models' tolerances from.

Conventions (``jit.JIT``): ``@njit(cache=True, nogil=True, error_model="numpy", boundscheck=False)``, one thread,
explicit float32 arithmetic; the first call of a process compiles (seconds, cached on disk after).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from aerial_loc_env.jit import BILINEAR_LANES as _LANES
from aerial_loc_env.jit import JIT as _JIT
from aerial_loc_env.jit import bilinear_f32x8 as _bilinear_f32x8
from aerial_loc_env.jit import fma32 as _fma32
from aerial_loc_env.jit import index32 as _index32

#: what ``scan`` does with each particle's samples
SAMPLE, MOMENTS, HISTOGRAM, BRIEF = 0, 1, 2, 3
#: copies of a particle's joint histogram, counted in turn and summed (integers: the same counts)
_HIST_COPIES = 4


@njit(**_JIT)
def scan(planes, e, cols, rows, active, nch, mode, ref, shift, ref_bins, bins, scale, nlogn, tests, cam_bits,
         samples, stats):
    """Sample every active particle's view of the level and score it, in one pass over the particles.

    The level is ``planes`` (C, h, w) float32; particle n's view is channels 0 .. nch - 1 at the reduced-grid
    points (``cols[r, b]``, ``rows[r, b]``) (R, B) under its affine ``e[n]`` (N, 2, 3) float32, the coordinates
    ``e00 col + (e01 row + e02)`` in float32 as ``PatchSampler`` always made them, the value ``cv2.remap``'s
    (see the module's docstring). A particle's R B coordinates are one vectorized loop (truncation is the floor
    where a point is inside; the bounds are checked on the floats, the flat indices in 32-bit arithmetic); when
    every point's neighbours are inside the level (the usual case) each channel is one pass of
    ``jit.bilinear_f32x8`` (two 64-bit loads a point, the fma chain on 8 points at once), else the rows whose points
    are all inside take that pass and the others, and particles not ``active`` in SAMPLE mode (footprints far off
    the level or not finite, never truncated unclamped), go point by point with the border.

    ``mode`` (inactive particles are skipped, except in SAMPLE mode):

    - SAMPLE: ``samples[n]`` (C, R, B) = the view (every particle; ``active`` False = the general path);
    - MOMENTS: ``stats[n, :4] = (sum d, sum d^2, sum (p - r)^2, sum d r)`` over channel 0 with ``d = p - shift``
      and ``ref`` (R, B) the camera's values, float64 (one accumulator per lane of a block: the loop vectorizes
      and the order is fixed); NaN where a sample is NaN (no-data). SSD's and NCC's statistics;
    - HISTOGRAM: the joint histogram of channel 0 quantized (``min(max(p scale, 0), bins - 1)`` truncated, as
      ``dense.quantize``) against ``ref_bins`` (R, B) in integer counts (kept in ``_HIST_COPIES`` copies that
      take the samples in turn, so that repeated cells do not wait on each other's increments), through the
      ``c log c`` table ``nlogn``: ``stats[n, :2] = (sum over the joint cells, sum over the samples' marginal)``;
      NaN on a NaN sample;
    - BRIEF: ``stats[n, 0]`` = how many of the tests (T, 3) = (first point, second point, channel) (points as
      flat indices r B + b) disagree with ``cam_bits`` (T,) (a test's bit: first > second); -1 on a NaN sample.

    A NaN sample is found by an OR over the samples (a vectorized loop), not by a float sum (a chain of dependent
    additions). In numba a view made per row (``a[r]``) costs reference counting per sample, so rows are offsets
    into flat arrays, and the general path runs after the fast pass, not inside it.
    """
    lh, lw = planes.shape[1], planes.shape[2]
    nr, nb = cols.shape
    npt = nr * nb
    flat = planes.reshape(planes.shape[0], lh * lw)
    cols_f, rows_f = cols.reshape(npt), rows.reshape(npt)
    view = np.empty((nch, npt), np.float32)
    fa = np.empty(npt, np.float32)
    fb = np.empty(npt, np.float32)
    idx = np.empty(npt, np.uint32)
    off = np.empty(npt, np.uint8)
    slow = np.empty(nr, np.bool_)
    acc = np.zeros((4, nb))
    cell = np.empty(npt, np.int32)
    ref_f = ref.reshape(ref.size)
    ref_bins_f = ref_bins.reshape(ref_bins.size)
    n_cells = max(bins * bins, 1)
    hist = np.zeros((_HIST_COPIES, n_cells), np.int32)
    top = np.float32(bins - 1)
    n_tests = tests.shape[0] if mode == BRIEF else 0
    first = np.empty(n_tests, np.uint32)         # each test's two samples in the flat view (channel-major)
    second = np.empty(n_tests, np.uint32)
    for t in range(n_tests):
        first[t] = np.uint32(tests[t, 2] * npt + tests[t, 0])
        second[t] = np.uint32(tests[t, 2] * npt + tests[t, 1])
    want = cam_bits[:n_tests]
    w, below = np.int32(lw), np.uint32(lw)
    umax, vmax = np.float32(lw - 1), np.float32(lh - 1)
    for n in range(e.shape[0]):
        if not active[n] and mode != SAMPLE:
            continue
        out = samples[n].reshape(nch, npt) if mode == SAMPLE else view
        e00, e01, e02 = e[n, 0, 0], e[n, 0, 1], e[n, 0, 2]
        e10, e11, e12 = e[n, 1, 0], e[n, 1, 1], e[n, 1, 2]
        outside = np.int32(0)
        for i in range(npt):
            u = e00 * cols_f[i] + (e01 * rows_f[i] + e02)
            v = e10 * cols_f[i] + (e11 * rows_f[i] + e12)
            iu = np.int32(u)
            iv = np.int32(v)
            fa[i] = u - np.float32(iu)
            fb[i] = v - np.float32(iv)
            idx[i] = np.uint32(_index32(iv, w, iu))
            out_i = np.int32((u < 0) | (v < 0) | (u >= umax) | (v >= vmax))
            off[i] = np.uint8(out_i)
            outside = np.int32(outside | out_i)   # (carried as int32: an int64 one halves the vector width)
        if outside == 0 and active[n]:      # every point inside (the usual case): one pass per channel
            for ch in range(nch):
                _sample(flat[ch], idx, below, fa, fb, out[ch], 0, npt)
        else:                               # rows with a point outside take the general path, after the others
            n_slow = 0
            for r in range(nr):
                o = r * nb
                row_out = np.uint8(0)
                for j in range(nb):
                    row_out |= off[o + j]
                slow[r] = row_out != 0 or not active[n]
                if slow[r]:
                    n_slow += 1
                else:
                    for ch in range(nch):
                        _sample(flat[ch], idx, below, fa, fb, out[ch], o, o + nb)
            for r in range(nr if n_slow else 0):
                if slow[r]:
                    o = r * nb
                    for ch in range(nch):
                        fill = np.float32(np.nan) if ch == 0 else np.float32(0.0)
                        for j in range(nb):
                            out[ch, o + j] = _bilinear(planes[ch], e00 * cols[r, j] + (e01 * rows[r, j] + e02),
                                                       e10 * cols[r, j] + (e11 * rows[r, j] + e12), fill)
        if mode == MOMENTS:
            acc[:] = 0.0
            a1, a2, ad, ar = acc[0], acc[1], acc[2], acc[3]
            for r in range(nr):
                o = r * nb
                for j in range(nb):
                    p = np.float64(view[0, o + j])
                    rv = np.float64(ref_f[o + j])
                    d = p - shift
                    a1[j] += d
                    a2[j] += d * d
                    ad[j] += (p - rv) * (p - rv)
                    ar[j] += d * rv
            for q in range(4):
                stats[n, q] = acc[q].sum()
        elif mode == HISTOGRAM:
            hist[:] = 0
            nan = False
            v0 = view[0]
            for i in range(npt):
                p = v0[i]
                z = p - p
                nan |= z != z                           # a NaN sample
                t = p * scale
                t = t if t > 0 else np.float32(0.0)     # (NaN -> 0: a defined cell; the particle is dropped)
                t = t if t < top else top
                cell[i] = np.int32(t) * bins + ref_bins_f[i]
            body = npt - npt % _HIST_COPIES
            for i in range(0, body, _HIST_COPIES):      # the counts in several copies: no chain of increments
                for c in range(_HIST_COPIES):           # of one cell waits on the last
                    hist[c, cell[i + c]] += 1
            for i in range(body, npt):
                hist[0, cell[i]] += 1
            sj = 0.0
            sp = 0.0
            for i in range(bins):
                row_count = 0
                for j in range(bins):
                    k = 0
                    for c in range(_HIST_COPIES):
                        k += hist[c, i * bins + j]
                    row_count += k
                    sj += nlogn[k]
                sp += nlogn[row_count]
            stats[n, 0] = np.nan if nan else sj
            stats[n, 1] = np.nan if nan else sp
        elif mode == BRIEF:
            values = view.reshape(nch * npt)
            nan = False
            for j in range(nch * npt):
                z = values[j] - values[j]
                nan |= z != z                           # a NaN (or infinite) sample
            disagree = 0
            for t in range(n_tests):
                bit = values[first[t]] > values[second[t]]
                disagree += np.int64(bit != want[t])
            stats[n, 0] = -1 if nan else disagree


@njit(inline="always", **_JIT)
def _sample(plane, idx, below, fa, fb, dst, start, end):
    """``dst[start:end]``: the points' bilinear samples of one channel ``plane`` (their neighbours all inside):
    ``jit.bilinear_f32x8`` 8 points at a time, the scalar chain for the rest (the same floats)."""
    j = start
    while j + _LANES <= end:
        _bilinear_f32x8(plane, idx, below, fa, fb, dst, j)
        j += _LANES
    for i in range(j, end):
        k = idx[i]
        p00 = plane[k]
        p01 = plane[k + np.uint32(1)]
        p10 = plane[k + below]
        p11 = plane[k + below + np.uint32(1)]
        a = fa[i]
        v0 = _fma32(a, p01 - p00, p00)
        v1 = _fma32(a, p11 - p10, p10)
        dst[i] = _fma32(fb[i], v1 - v0, v0)


@njit(**_JIT)
def _bilinear(plane, u, v, fill):
    """``cv2.remap`` INTER_LINEAR / BORDER_CONSTANT of one channel ``plane`` (h, w) float32 at the float32 point
    (u, v), the border value ``fill`` (NaN for channel 0, 0 for the others: OpenCV's Scalar (nan, 0, 0, 0)), the
    floor clamped to [-2, size + 1] (every point beyond is as far outside, and the conversion stays defined;
    NaN -> outside, as in OpenCV). The general path of ``scan``."""
    lh, lw = plane.shape
    cu = u if u > -2.0 else np.float32(-2.0)
    cu = cu if cu < lw + 1 else np.float32(lw + 1)
    cv = v if v > -2.0 else np.float32(-2.0)
    cv = cv if cv < lh + 1 else np.float32(lh + 1)
    ix = np.int32(cu)
    iy = np.int32(cv)
    ix -= np.int32(np.float32(ix) > cu)
    iy -= np.int32(np.float32(iy) > cv)
    if ix + 1 < 0 or ix >= lw or iy + 1 < 0 or iy >= lh:       # all four neighbours outside
        return fill
    a, b = u - np.float32(ix), v - np.float32(iy)
    x1, y1 = ix + 1, iy + 1
    in_x0, in_x1, in_y0, in_y1 = ix >= 0, x1 < lw, iy >= 0, y1 < lh
    p00 = plane[iy, ix] if in_x0 and in_y0 else fill
    p01 = plane[iy, x1] if in_x1 and in_y0 else fill
    p10 = plane[y1, ix] if in_x0 and in_y1 else fill
    p11 = plane[y1, x1] if in_x1 and in_y1 else fill
    v0 = _fma32(a, p01 - p00, p00)
    v1 = _fma32(a, p11 - p10, p10)
    return _fma32(b, v1 - v0, v0)
