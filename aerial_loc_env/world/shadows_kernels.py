"""The compiled passes of ``world/shadows.py``: the shadow sweep and the shading.

``sweep``: the running horizon of ``shadows._sweep`` (one slice at a time towards the sun), the NumPy per-slice
vector operations as one loop: the same float operations in the same order (maximum, subtract, compare; no fused
multiply-add), so the mask, margins and distances are bit-identical (the tests keep the NumPy sweep as the
reference).

``shade_rows``: shadow shading, ``rgb * lut[c, q] / 255`` per channel, q the quantized occlusion. It reproduces
the OpenCV passes it replaced (``cv2.convertScaleAbs`` quantization, three 1-channel ``cv2.LUT``, ``cv2.merge``,
``cv2.multiply`` with scale 1/255) bit for bit, checked exhaustively by the tests, through ``jit.mul255`` and
``jit.quantize``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from aerial_loc_env.jit import JIT, mul255, quantize


@nb.njit(inline="always", **JIT)
def _gain_row(f, g, cn, w_px, quantized, l0, l1, l2):
    """The row's per-channel gains ``g`` (cn W uint8) at the occlusion row ``f``: the level itself for alpha."""
    for x in range(w_px):
        q = np.int32(f[x]) if quantized else quantize(f[x])
        g[cn * x] = l0[q]
        g[cn * x + 1] = l1[q]
        g[cn * x + 2] = l2[q]
        if cn == 4:
            g[cn * x + 3] = q


@nb.njit(**JIT)
def shade_rows(src, occ, quantized, lut, out):
    """``out`` (H, cn W) uint8 = ``src`` (H, cn W) uint8 shaded by the (3, 256) uint8 gains ``lut`` at the
    occlusion ``occ`` (H, W): uint8 levels (``quantized``) or float in [0, 1]; a 4th channel (alpha) is scaled by
    the level itself. ``out`` may be ``src``; views with strided rows are fine. Per row: the gains by table
    lookups (scalar), then the multiply over the contiguous row (vectorized)."""
    h_px, w_px = occ.shape
    n = src.shape[1]
    cn = n // w_px
    l0, l1, l2 = lut[0], lut[1], lut[2]
    g = np.empty(n, np.uint8)
    for y in range(h_px):
        if cn == 4:
            _gain_row(occ[y], g, 4, w_px, quantized, l0, l1, l2)
        else:
            _gain_row(occ[y], g, 3, w_px, quantized, l0, l1, l2)
        s = src[y]
        o = out[y]
        for i in range(n):
            o[i] = mul255(np.int32(s[i]), np.int32(g[i]))


@nb.njit(**JIT)
def sweep(a, s, from_last, drop, step, soft, mask, margin, dist_out):
    """The sweep over the slices (rows) of ``a`` (float32 or float64) from the sun's side (``from_last``: the sun
    lies beyond the last row, which comes first); ``s`` the digital line's row offsets (integral floats); ``drop``,
    ``step`` in a's dtype. Writes ``mask`` (bool, ``a < horizon``) or, with ``soft``, ``margin`` (horizon - a) and
    ``dist_out`` (the distance to the occluder that set the horizon)."""
    n0, n1 = a.shape
    hor = np.full(n1, -np.inf, a.dtype)
    tmp = np.empty(n1, a.dtype)
    dist = np.full(n1, step, a.dtype)
    dtmp = np.empty(n1, a.dtype)
    prev = -1
    for k in range(n0):
        i = n0 - 1 - k if from_last else k
        if prev >= 0:
            row = a[prev]
            d = np.int64(s[prev] - s[i])   # the line through (i, j) passes (prev, j + d)
            if soft:
                for j in range(n1):   # a new maximum restarts the distance (0 + step is step exactly)
                    dtmp[j] = step if row[j] >= hor[j] else dist[j] + step
            for j in range(n1):
                tmp[j] = np.maximum(hor[j], row[j]) - drop
            if d == 0:
                hor, tmp = tmp, hor
                if soft:
                    dist, dtmp = dtmp, dist
            elif d == 1:
                hor[:n1 - 1] = tmp[1:]
                hor[n1 - 1] = -np.inf
                if soft:
                    dist[:n1 - 1] = dtmp[1:]
                    dist[n1 - 1] = step
            else:
                hor[1:] = tmp[:n1 - 1]
                hor[0] = -np.inf
                if soft:
                    dist[1:] = dtmp[:n1 - 1]
                    dist[0] = step
        ai = a[i]
        if soft:
            mi = margin[i]
            di = dist_out[i]
            for j in range(n1):
                mi[j] = hor[j] - ai[j]
                di[j] = dist[j]
        else:
            mk = mask[i]
            for j in range(n1):
                mk[j] = ai[j] < hor[j]
        prev = i
