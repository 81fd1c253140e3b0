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

from aerial_loc_env.jit import JIT as _JIT
from aerial_loc_env.jit import fma32 as _fma32

#: what ``scan`` does with each particle's samples
SAMPLE, MOMENTS, HISTOGRAM, BRIEF = 0, 1, 2, 3


@njit(**_JIT)
def scan(planes, e, cols, rows, active, nch, mode, ref, shift, ref_bins, bins, scale, nlogn, tests, cam_bits,
         samples, stats):
    """Sample every active particle's view of the level and score it, in one pass over the particles.

    The level is ``planes`` (C, h, w) float32; particle n's view is channels 0 .. nch - 1 at the reduced-grid
    points (``cols[r, b]``, ``rows[r, b]``) (R, B) under its affine ``e[n]`` (N, 2, 3) float32, the coordinates
    ``e00 col + (e01 row + e02)`` in float32 as ``PatchSampler`` always made them, the value ``cv2.remap``'s
    (see the module's docstring). A block (one row of B points) whose neighbours are all inside the level takes
    the fast path: one vectorized loop for the coordinates (truncation is the floor there; the bounds are checked
    on the floats), then one for the loads and the fma chain (faster than the loads and the fma chain in two
    loops, and than one loop doing all with a branch per point). Other blocks, and particles not
    ``active`` in SAMPLE mode (footprints far off the level or not finite, never truncated unclamped), go point
    by point with the border.

    ``mode`` (inactive particles are skipped, except in SAMPLE mode):

    - SAMPLE: ``samples[n]`` (C, R, B) = the view (every particle; ``active`` False = the general path);
    - MOMENTS: ``stats[n, :4] = (sum d, sum d^2, sum (p - r)^2, sum d r)`` over channel 0 with ``d = p - shift``
      and ``ref`` (R, B) the camera's values, float64 (one accumulator per lane of a block: the loop vectorizes
      and the order is fixed); NaN where a sample is NaN (no-data). SSD's and NCC's statistics;
    - HISTOGRAM: the joint histogram of channel 0 quantized (``min(max(p scale, 0), bins - 1)`` truncated, as
      ``dense.quantize``) against ``ref_bins`` (R, B) in integer counts, through the ``c log c`` table ``nlogn``:
      ``stats[n, :2] = (sum over the joint cells, sum over the samples' marginal)``; NaN on a NaN sample;
    - BRIEF: ``stats[n, 0]`` = how many of the tests (T, 3) = (first point, second point, channel) (points as
      flat indices r B + b) disagree with ``cam_bits`` (T,) (a test's bit: first > second); -1 on a NaN sample.

    In numba a helper that takes arrays costs a call's argument handling, and a view made per row (``a[r]``)
    reference counting per sample, so the sampling is written out here once for every mode with plain 2-D/3-D
    indexing, and the general path runs after the fast loop, not inside it.
    """
    lh, lw = planes.shape[1], planes.shape[2]
    nr, nb = cols.shape
    flat = planes.reshape(planes.shape[0], lh * lw)
    view = np.empty((nch, nr, nb), np.float32)
    fa = np.empty(nb, np.float32)
    fb = np.empty(nb, np.float32)
    idx = np.empty(nb, np.uint32)
    slow = np.empty(nr, np.bool_)
    acc = np.zeros((4, nb))
    cell = np.empty(nb, np.int32)
    hist = np.zeros(max(bins * bins, 1), np.int32)
    top = np.float32(bins - 1)
    w, below = np.int32(lw), np.uint32(lw)
    umax, vmax = np.float32(lw - 1), np.float32(lh - 1)
    for n in range(e.shape[0]):
        if not active[n] and mode != SAMPLE:
            continue
        out = samples[n] if mode == SAMPLE else view
        e00, e01, e02 = e[n, 0, 0], e[n, 0, 1], e[n, 0, 2]
        e10, e11, e12 = e[n, 1, 0], e[n, 1, 1], e[n, 1, 2]
        n_slow = 0
        for r in range(nr):
            outside = np.int32(0)
            for j in range(nb):
                u = e00 * cols[r, j] + (e01 * rows[r, j] + e02)
                v = e10 * cols[r, j] + (e11 * rows[r, j] + e12)
                iu = np.int32(u)
                iv = np.int32(v)
                fa[j] = u - np.float32(iu)
                fb[j] = v - np.float32(iv)
                idx[j] = np.uint32(iv * w + iu)
                outside |= np.int32((u < 0) | (v < 0) | (u >= umax) | (v >= vmax))
            slow[r] = outside != 0 or not active[n]
            if slow[r]:
                n_slow += 1
                continue
            for ch in range(nch):
                for j in range(nb):
                    k = idx[j]
                    p00 = flat[ch, k]
                    p01 = flat[ch, k + np.uint32(1)]
                    p10 = flat[ch, k + below]
                    p11 = flat[ch, k + below + np.uint32(1)]
                    a = fa[j]
                    v0 = _fma32(a, p01 - p00, p00)
                    v1 = _fma32(a, p11 - p10, p10)
                    out[ch, r, j] = _fma32(fb[j], v1 - v0, v0)
        for r in range(nr if n_slow else 0):         # the general path, after the fast loop (kept out of it)
            if slow[r]:
                for ch in range(nch):
                    fill = np.float32(np.nan) if ch == 0 else np.float32(0.0)
                    for j in range(nb):
                        out[ch, r, j] = _bilinear(planes[ch], e00 * cols[r, j] + (e01 * rows[r, j] + e02),
                                                  e10 * cols[r, j] + (e11 * rows[r, j] + e12), fill)
        if mode == MOMENTS:
            acc[:] = 0.0
            a1, a2, ad, ar = acc[0], acc[1], acc[2], acc[3]
            for r in range(nr):
                for j in range(nb):
                    p = np.float64(view[0, r, j])
                    rv = np.float64(ref[r, j])
                    d = p - shift
                    a1[j] += d
                    a2[j] += d * d
                    ad[j] += (p - rv) * (p - rv)
                    ar[j] += d * rv
            for q in range(4):
                stats[n, q] = acc[q].sum()
        elif mode == HISTOGRAM:
            hist[:] = 0
            nan = np.float32(0.0)
            for r in range(nr):
                for j in range(nb):
                    p = view[0, r, j]
                    nan += p - p                            # NaN once any sample is NaN
                    t = p * scale
                    t = t if t > 0 else np.float32(0.0)     # (NaN -> 0: a defined cell; the particle is dropped)
                    t = t if t < top else top
                    cell[j] = np.int32(t) * bins + ref_bins[r, j]
                for j in range(nb):
                    hist[cell[j]] += 1
            sj = 0.0
            sp = 0.0
            for i in range(bins):
                row_count = 0
                for j in range(bins):
                    k = hist[i * bins + j]
                    row_count += k
                    sj += nlogn[k]
                sp += nlogn[row_count]
            stats[n, 0] = sj if nan == 0.0 else np.nan
            stats[n, 1] = sp if nan == 0.0 else np.nan
        elif mode == BRIEF:
            flat_view = view.reshape(nch, nr * nb)
            nan = np.float32(0.0)
            for ch in range(nch):
                for j in range(nr * nb):
                    nan += flat_view[ch, j] - flat_view[ch, j]
            disagree = 0
            for t in range(tests.shape[0]):
                ch = tests[t, 2]
                bit = flat_view[ch, tests[t, 0]] > flat_view[ch, tests[t, 1]]
                disagree += np.int64(bit != cam_bits[t])
            stats[n, 0] = disagree if nan == 0.0 else -1


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
