"""The camera frame's per-pixel finish in one compiled pass (numba): shading, tone, gains, vignetting, noise.

``finish`` turns the warped map (RGBA or RGB uint8) into the final uint8 RGB frame, row by row, each row
through both stages while it sits in L1:

1. scene: the shadow mask (from the baked alpha, or from a float occlusion, which is also shaded here), then the
   frame's composed tone LUT (gamma and the white-balance/exposure gains, one byte table per channel);
2. sensor: vignetting and signal-dependent noise read from the episode's int16 bank at the frame's offset, added
   with saturation.

Every step is the arithmetic of the OpenCV passes it replaces, reproduced bit for bit (tests/test_render_kernel.py
keeps those passes as the reference and compares exactly); what each pass computes, measured exhaustively:

- the uint8 multiply with scale 1/255 (shading, vignetting) and the occlusion's quantization: see
  ``world.kernels``, whose two helpers this pass uses;
- ``cv2.transform`` with a diagonal float32 matrix on uint8 is ``rint(v * g)`` in float32, saturated: a byte
  function per channel, so gamma and gains compose into one table per frame (``CameraRenderer`` builds it by
  running the two OpenCV operations over the 256 levels);
- ``cv2.multiply(S, Z, scale=2**-19)`` on int16 is ``rint(float32(S Z) * 2**-19)`` (the product rounded to
  float32 first, then the exact power-of-two scale);
- the int16 sigma LUT ``rint(256 sqrt(r**2 + g v))`` (float64) is computed here instead of read (a gather per
  element costs more than the whole rest of the sensor stage): in float32 where that reproduces all 256 levels
  (checked per renderer with this module's own arithmetic, ``sigma_mode``), else in float64, which is the
  LUT's own arithmetic.

Loops run over 2-D row slices with explicit narrow casts so that LLVM vectorizes them; single-threaded on
purpose (benchmarks are per core; users parallelize over environments). The first call of a process compiles
(about 2 s) unless numba's cache (``cache=True``, next to this file or in numba's user cache) already holds it.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..world.kernels import JIT as _JIT
from ..world.kernels import mul255 as _mul255
from ..world.kernels import quantize as _quantize

#: ``occ_mode`` of ``finish``: where the shadows come from
OCC_NONE, OCC_ALPHA, OCC_FLOAT = 0, 1, 2
#: ``sigma_mode`` of ``finish``: how the noise sigma is obtained from the level (``NOISE_OFF``: no noise)
SIGMA_F32, SIGMA_F64, NOISE_OFF = 0, 1, 2

_NOISE_SCALE = np.float32(2.0 ** -19)  # 2**-(sigma bits 8 + noise bank bits 11)


@nb.njit(inline="always", **_JIT)
def _sigma(h, mode, a32, b32, a64, b64):
    """rint(256 sigma(h)) as float32: float32 ``sqrt(a32 + b32 h)`` (a32 = 65536 r**2, b32 = 65536 g) or the LUT's
    float64 ``256 sqrt(a64 + b64 h)`` (a64 = r**2, b64 = g)."""
    if mode == SIGMA_F32:
        return np.rint(np.sqrt(a32 + b32 * np.float32(h)))
    return np.float32(np.rint(np.sqrt(a64 + b64 * np.float64(h)) * 256.0))


@nb.njit(inline="always", **_JIT)
def _noise(sig, z):
    """The noise in DN, ``rint(float32(S Z) 2**-19)`` for S = ``sig`` (float32, integral) and the int16 draw ``z``."""
    return np.int32(np.rint(sig * np.float32(z) * _NOISE_SCALE))


@nb.njit(**_JIT)
def sigma_levels(mode, a32, b32, a64, b64):
    """The 256 sigma values ``finish`` uses (to check them against the renderer's LUT)."""
    out = np.empty(256, np.int32)
    for h in range(256):
        out[h] = np.int32(_sigma(np.int32(h), mode, a32, b32, a64, b64))
    return out


@nb.njit(inline="always", **_JIT)
def _scene_row(s, o, m, f, cn, w_px, occ_mode, l0, l1, l2, s0, s1, s2, lit_same):
    """Stage 1 on one row into ``o`` (``cn`` a constant at each call site, so that the loops specialize); returns
    the shadowed pixels. ``lit_same``: the shading leaves occlusion level 0 unchanged (gain 255), so lit pixels
    skip it (the lookups are scalar code anyway: a branch there costs nothing and saves most of the work)."""
    count = 0
    if occ_mode == OCC_FLOAT:
        for x in range(w_px):
            count += np.int32(f[x] >= np.float32(0.5))
        for x in range(w_px):
            q = _quantize(f[x])
            a0, a1, a2 = np.int32(s[cn * x]), np.int32(s[cn * x + 1]), np.int32(s[cn * x + 2])
            if q != 0 or not lit_same:
                a0 = _mul255(a0, np.int32(s0[q]))
                a1 = _mul255(a1, np.int32(s1[q]))
                a2 = _mul255(a2, np.int32(s2[q]))
            o[3 * x] = l0[a0]
            o[3 * x + 1] = l1[a1]
            o[3 * x + 2] = l2[a2]
    elif occ_mode == OCC_ALPHA:   # the alpha kept (the frame's quantized occlusion) and counted
        for x in range(w_px):
            a = s[cn * x + 3]
            m[x] = a
            count += np.int32(a > 127)
            o[3 * x] = l0[s[cn * x]]
            o[3 * x + 1] = l1[s[cn * x + 1]]
            o[3 * x + 2] = l2[s[cn * x + 2]]
    else:
        for x in range(w_px):
            o[3 * x] = l0[s[cn * x]]
            o[3 * x + 1] = l1[s[cn * x + 1]]
            o[3 * x + 2] = l2[s[cn * x + 2]]
    return count


@nb.njit(**_JIT)
def finish(src, cn, occ_mode, occ, shade, lut, out, alpha, sensor, vig, bank, dy, dx3,
           sigma_mode, a32, b32, a64, b64):
    """Write the frame into ``out`` (flat uint8, row y at [3 W y, 3 W (y + 1))) from ``src`` (H, cn W) uint8;
    returns the number of shadowed pixels. ``out`` may be src's own buffer: each row is made in a row buffer and
    written back over bytes of rows already read (3 W (y + 1) <= cn W (y + 1)), so a warp's RGBA output becomes
    the RGB frame in place, without a second frame of memory.

    ``occ_mode``: ``OCC_ALPHA``: src's alpha is the baked occlusion (already shaded), shadowed where > 127 and
    copied to ``alpha`` (H, W) uint8; ``OCC_FLOAT``: ``occ`` (H, W) float32 is the occlusion, shadowed where
    >= 0.5, and src is shaded by ``shade[c, q]`` (uint8 (3, 256) gains at q = the quantized occlusion). ``lut``
    (3, 256) uint8: the tone LUT per channel. ``sensor``: then vignetting (``vig`` uint8 gains over 255, (H, 3 W),
    or its top rows only when the bottom rows mirror them: row y reads row H - 1 - y below) and noise (``bank``
    int16 rows from ``dy``, columns from ``dx3``; ``sigma_mode`` with ``_sigma``'s constants) on the toned levels.
    """
    h_px = src.shape[0]
    w_px = src.shape[1] // cn
    w3 = 3 * w_px
    n_vig = vig.shape[0]
    l0, l1, l2 = lut[0], lut[1], lut[2]
    s0, s1, s2 = shade[0], shade[1], shade[2]
    lit_same = s0[0] == 255 and s1[0] == 255 and s2[0] == 255
    o = np.empty(w3, np.uint8)
    count = 0
    for y in range(h_px):
        m = alpha[y] if occ_mode == OCC_ALPHA else alpha[0]
        f = occ[y] if occ_mode == OCC_FLOAT else occ[0]
        if cn == 4:
            count += _scene_row(src[y], o, m, f, 4, w_px, occ_mode, l0, l1, l2, s0, s1, s2, lit_same)
        else:
            count += _scene_row(src[y], o, m, f, 3, w_px, occ_mode, l0, l1, l2, s0, s1, s2, lit_same)
        d = out[w3 * y:w3 * (y + 1)]
        if not sensor:
            for x in range(w3):
                d[x] = o[x]
            continue
        v = vig[y if y < n_vig else h_px - 1 - y]
        if sigma_mode == NOISE_OFF:
            for x in range(w3):
                d[x] = _mul255(np.int32(o[x]), np.int32(v[x]))
        else:
            b = bank[y + dy, dx3:dx3 + w3]
            for x in range(w3):
                h = np.int32(o[x])
                n = _noise(_sigma(h, sigma_mode, a32, b32, a64, b64), b[x])
                d[x] = min(max(_mul255(h, np.int32(v[x])) + n, np.int32(0)), np.int32(255))
    return count
