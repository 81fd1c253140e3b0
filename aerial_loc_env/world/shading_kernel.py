"""Shadow shading in one compiled pass (numba): ``rgb * lut[c, q] / 255`` per channel, q the quantized occlusion.

The OpenCV passes this replaces (quantize the float occlusion with ``cv2.convertScaleAbs``, three 1-channel
``cv2.LUT`` of it, ``cv2.merge``, ``cv2.multiply`` with scale 1/255) are reproduced bit for bit, measured
exhaustively (tests/test_render_kernel.py): the uint8 multiply is the exactly rounded ``a b / 255`` (never a tie),
here ``(p + (p >> 8)) >> 8`` with ``p = a b + 128``; the quantization is ``rint(|occ * 255|)`` in float32, saturated.
``sensors.frame_kernel`` uses the same two helpers for the frames' shading and vignetting.
"""

from __future__ import annotations

import numba as nb
import numpy as np

#: numba options of the project's kernels: cached compiles, no GIL, NumPy's error model, no bounds checks;
#: single-threaded on purpose (benchmarks are per core; users parallelize over environments and workers)
JIT = {"cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}


@nb.njit(inline="always", **JIT)
def mul255(a, b):
    """round(a b / 255) for a, b in [0, 255] (int32): ``cv2.multiply(a, b, scale=1/255)`` on uint8."""
    p = a * b + np.int32(128)
    return (p + (p >> np.int32(8))) >> np.int32(8)


@nb.njit(inline="always", **JIT)
def quantize(v):
    """The occlusion level of a float occlusion ``v``: ``cv2.convertScaleAbs(v, alpha=255)`` (int32)."""
    return min(np.int32(np.rint(np.abs(v * np.float32(255.0)))), np.int32(255))


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
