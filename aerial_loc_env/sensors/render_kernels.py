"""The camera frame's per-pixel finish in one compiled pass (numba): shading, tone, gains, vignetting, noise.

``finish`` turns the warped map (RGBA or RGB uint8) into the final uint8 RGB frame, row by row, each row
through both stages while it sits in L1 (``warp_finish``: the same, with the baked box's bilinear warp of the row
done first, bit for bit OpenCV's; ``level_finish``: a map level's warp and the shadow grid's, for the frames the
bake does not serve):

1. scene: the shadow mask (from the baked alpha, or from a float occlusion, which is also shaded here), then the
   frame's composed tone LUT (gamma and the white-balance/exposure gains, one byte table per channel);
2. sensor: vignetting and signal-dependent noise read from the episode's int16 bank at the frame's offset, added
   with saturation.

Every step is the arithmetic of the OpenCV passes it replaces, reproduced bit for bit
(tests/sensors/test_render_kernel.py
keeps those passes as the reference and compares exactly); what each pass computes, measured exhaustively:

- the uint8 multiply with scale 1/255 (shading, vignetting) and the occlusion's quantization: see
  ``jit``, whose two helpers this pass uses (the vignetting by the same multiply in float32,
  ``_vignetted``: the sensor stage then runs in 16 float32 lanes, not numba's 8 int64);
- ``cv2.transform`` with a diagonal float32 matrix on uint8 is ``rint(v * g)`` in float32, saturated: a byte
  function per channel, so gamma and gains compose into one table per frame (``render.tone_lut``: ``cv2.LUT``'s
  gamma table, then the gains, that arithmetic over the 256 levels in one call, ``tone_table``);
- ``cv2.multiply(S, Z, scale=2**-19)`` on int16 is ``rint(float32(S Z) * 2**-19)`` (the product rounded to
  float32 first, then the exact power-of-two scale);
- the int16 sigma LUT ``rint(256 sqrt(r**2 + g v))`` (float64) is computed here instead of read (a gather per
  element costs more than the whole rest of the sensor stage): in float32 where that reproduces all 256 levels
  (checked per renderer with this module's own arithmetic, ``sigma_mode``), else in float64, which is the
  LUT's own arithmetic.

Loops run over 2-D row slices with explicit narrow casts so that LLVM vectorizes them, with 512-bit vectors
preferred (``jit.wide_vectors``: LLVM's default on AVX-512 Intel cores mixes 256- and 512-bit loops in
these two functions, which then slow down whenever other work ran before them; same bytes); single-threaded on
purpose (benchmarks are per core; users parallelize over environments). The box's samples are taken 8 pixels at a
time by ``jit.bilinear_rgba8`` (two 64-bit loads a pixel, the chain in whatever vector registers the CPU has:
as fast with AVX2 as the loop form is only with AVX-512's byte permutes). Two steps use CPU instructions LLVM does
not pick by itself, each only where the host has them and they pay, the same bytes either way
(``jit``): the box's neighbour loads as AVX-512 gathers (``FAST_GATHER``: Sapphire Rapids and later) and
the tone lookups of RGBA rows as VBMI byte permutes (``FAST_LUT``; elsewhere scalar lookups of whole 32-bit
pixels, the alphas in a vectorized loop of their own). The first call of a process compiles
(seconds) unless numba's cache (``cache=True``, next to this file or in numba's user cache) already holds it.
"""

from __future__ import annotations

import sys

import numba as nb
import numpy as np

from aerial_loc_env.jit import BILINEAR_LANES as _BILINEAR_LANES
from aerial_loc_env.jit import BILINEAR_PIXELS as _BILINEAR_PIXELS
from aerial_loc_env.jit import FAST_GATHER as _FAST_GATHER
from aerial_loc_env.jit import FAST_LUT as _FAST_LUT
from aerial_loc_env.jit import GATHER_LANES as _GATHER_LANES
from aerial_loc_env.jit import JIT as _JIT
from aerial_loc_env.jit import LUT_PIXELS as _LUT_PIXELS
from aerial_loc_env.jit import bilinear_f32x8 as _bilinear_f32x8
from aerial_loc_env.jit import bilinear_rgba8 as _bilinear_rgba8
from aerial_loc_env.jit import borrowed as _borrowed
from aerial_loc_env.jit import fma32 as _fma32
from aerial_loc_env.jit import gather_pairs16 as _gather_pairs16
from aerial_loc_env.jit import keep_alive as _keep_alive
from aerial_loc_env.jit import lut_rgba16 as _lut_rgba16
from aerial_loc_env.jit import mul255 as _mul255
from aerial_loc_env.jit import prefetch as _prefetch
from aerial_loc_env.jit import quantize as _quantize
from aerial_loc_env.jit import saturate_u8 as _saturate_u8
from aerial_loc_env.jit import wide_vectors as _wide_vectors

#: ``occ_mode`` of ``finish``: where the shadows come from
OCC_NONE, OCC_ALPHA, OCC_FLOAT = 0, 1, 2
#: ``sigma_mode`` of ``finish``: how the noise sigma is obtained from the level (``NOISE_OFF``: no noise)
SIGMA_F32, SIGMA_F64, NOISE_OFF = 0, 1, 2

_NOISE_SCALE = np.float32(2.0 ** -19)  # 2**-(sigma bits 8 + noise bank bits 11)
_LITTLE_ENDIAN = sys.byteorder == "little"
_BYTE, _SHIFT8, _SHIFT16 = np.uint32(255), np.uint32(8), np.uint32(16)
_INV255 = np.float32(1.0 / 255.0)
#: the sensor stage prefetches the noise bank's row this many rows ahead: the bank (2 MB at 600 x 400) is read at a
#: new offset each frame, from L3, in row segments the hardware prefetchers pick up late (further ahead gains
#: nothing more; docs/perf-log.md)
_BANK_AHEAD_ROWS = 16


@nb.njit(inline="always", **_JIT)
def _sigma(h, mode, a32, b32, a64, b64):
    """rint(256 sigma(h)) as float32: float32 ``sqrt(a32 + b32 h)`` (a32 = 65536 r**2, b32 = 65536 g) or the LUT's
    float64 ``256 sqrt(a64 + b64 h)`` (a64 = r**2, b64 = g)."""
    if mode == SIGMA_F32:
        return np.rint(np.sqrt(a32 + b32 * np.float32(h)))
    return np.float32(np.rint(np.sqrt(a64 + b64 * np.float64(h)) * 256.0))


@nb.njit(inline="always", **_JIT)
def _vignetted(h, v):
    """A level ``h`` (float32, integral) times the vignetting gain ``v`` (uint8, over 255), rounded: ``mul255`` in
    float32 (``h v`` is exact and its product with float32(1/255) lies within 3e-6 of ``h v / 255``, which is never
    within 1/510 of a tie: the same integer for every pair, checked exhaustively in the tests). Why float: numba
    widens the integer form to 64-bit lanes, which halved the sensor stage's vector width."""
    return np.rint(h * np.float32(v) * _INV255)


@nb.njit(inline="always", **_JIT)
def _noise(sig, z):
    """The noise in DN (float32, integral), ``rint(float32(S Z) 2**-19)`` for S = ``sig`` (float32, integral) and
    the int16 draw ``z``."""
    return np.rint(sig * np.float32(z) * _NOISE_SCALE)


@nb.njit(inline="always", **_JIT)
def _noisy(lit, sig, z):
    """The output byte: the vignetted level ``lit`` plus ``_noise(sig, z)``, saturated to 0..255 (integral floats
    far below 2**24: the sum is exact, and so is its conversion to int32, saturated by ``jit.saturate_u8``)."""
    return _saturate_u8(np.int32(lit + _noise(sig, z)))


@nb.njit(**_JIT)
def sigma_levels(mode, a32, b32, a64, b64):
    """The 256 sigma values ``finish`` uses (to check them against the renderer's LUT)."""
    out = np.empty(256, np.int32)
    for h in range(256):
        out[h] = np.int32(_sigma(np.int32(h), mode, a32, b32, a64, b64))
    return out


@nb.njit(inline="always", **_JIT)
def _count_at_least(values, threshold):
    """How many of ``values`` are >= ``threshold``, summed as int32: numba widens an integer sum to int64, whose
    lanes are half as many in a vector (a count below 2**31: a row's pixels)."""
    count = np.int32(0)
    for x in range(values.shape[0]):
        count = np.int32(count + np.int32(values[x] >= threshold))
    return count


@nb.njit(inline="always", **_JIT)
def _scene_row(s, o, m, f, cn, w_px, occ_mode, l0, l1, l2, s0, s1, s2, lit_same, tabs):
    """Stage 1 on one row into ``o`` (``cn`` a constant at each call site, so that the loops specialize); returns
    the shadowed pixels. ``lit_same``: the shading leaves occlusion level 0 unchanged (gain 255), so lit pixels
    skip it (the lookups are scalar code anyway: a branch there costs nothing and saves most of the work)."""
    count = 0
    if occ_mode == OCC_FLOAT:
        count = _count_at_least(f[:w_px], np.float32(0.5))
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
        start = 0
        if cn == 4 and _FAST_LUT:   # 16 pixels at a time by byte permutes (``tabs``: l0, l1, l2 end to end)
            start = w_px - w_px % _LUT_PIXELS
            for x in range(0, start, _LUT_PIXELS):
                count += _lut_rgba16(s, x, tabs, o, m)
        for x in range(start, w_px):    # (vectorized: the alphas apart from the lookups)
            m[x] = s[cn * x + 3]
        count += _count_at_least(m[start:w_px], np.uint8(128))
        if cn == 4 and _LITTLE_ENDIAN:  # a pixel one 32-bit load, its channels its bytes from the lowest
            px = s.view(np.uint32)
            for x in range(start, w_px):
                p = px[x]
                o[3 * x] = l0[p & _BYTE]
                o[3 * x + 1] = l1[(p >> _SHIFT8) & _BYTE]
                o[3 * x + 2] = l2[(p >> _SHIFT16) & _BYTE]
        else:
            for x in range(start, w_px):
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
def tone_table(unit, gamma, gains, out):
    """``out[c, v]``: the tone curve's level ``rint(255 unit[v] ** gamma)`` (``unit`` the 256 levels over 255,
    float64; ``render.gamma_lut``'s arithmetic, libm's ``pow``; a NaN ``gamma``: the level ``v`` itself) times
    channel c's gain ``gains[c]`` (float64, cast to float32), rounded half to even and saturated (``gain_byte``):
    ``cv2.LUT`` of the tone curve, then ``cv2.transform`` of uint8 levels by a diagonal float32 matrix (the zero terms
    add nothing), as ``render.tone_lut`` uses it. One call for the frame's whole table."""
    for v in range(unit.shape[0]):
        level = np.uint8(v) if np.isnan(gamma) else np.uint8(np.rint(255.0 * unit[v] ** gamma))
        for c in range(out.shape[0]):
            out[c, v] = gain_byte(level, np.float32(gains[c]))


@nb.njit(inline="always", **_JIT)
def _tone_tables(lut):
    """The (3, 256) tone LUT as the scene stage reads it: one row per channel, and all three end to end (``tabs``,
    for ``jit.lut_rgba16``)."""
    return lut[0], lut[1], lut[2], np.ascontiguousarray(lut).reshape(lut.size)


@nb.njit(inline="always", **_JIT)
def _sensor_row(o, d, y, h_px, sensor, vig, bank, dy, dx3, sigma_mode, a32, b32, a64, b64):
    """Stage 2 on row y's toned levels ``o`` into ``d`` (a copy without ``sensor``); see ``finish``."""
    w3 = o.shape[0]
    if not sensor:
        for x in range(w3):
            d[x] = o[x]
        return
    v = vig[y if y < vig.shape[0] else h_px - 1 - y]
    ahead = y + dy + _BANK_AHEAD_ROWS
    if sigma_mode != NOISE_OFF and ahead < bank.shape[0]:   # the bank row read 16 rows down, a line at a time
        later = bank[ahead]
        for x in range(dx3, dx3 + w3, 32):
            _prefetch(later, x)
    if sigma_mode == NOISE_OFF:
        for x in range(w3):
            d[x] = _saturate_u8(np.int32(_vignetted(np.float32(o[x]), v[x])))
    elif sigma_mode == SIGMA_F32:   # one loop per mode: no branch inside
        b = bank[y + dy, dx3:dx3 + w3]
        for x in range(w3):
            h = np.float32(o[x])
            d[x] = _noisy(_vignetted(h, v[x]), _sigma(h, SIGMA_F32, a32, b32, a64, b64), b[x])
    else:
        b = bank[y + dy, dx3:dx3 + w3]
        for x in range(w3):
            h = np.float32(o[x])
            d[x] = _noisy(_vignetted(h, v[x]), _sigma(h, SIGMA_F64, a32, b32, a64, b64), b[x])


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
    _wide_vectors()
    h_px = src.shape[0]
    w_px = src.shape[1] // cn
    w3 = 3 * w_px
    owned = np.empty(w3, np.uint8)
    # the arrays the row helpers bind again per row, as views numba counts no references to (``jit.borrowed``)
    src, occ, shade, lut, out, alpha, vig, bank, o = _borrowed((src, occ, shade, lut, out, alpha, vig, bank, owned))
    l0, l1, l2, tabs = _tone_tables(lut)
    s0, s1, s2 = shade[0], shade[1], shade[2]
    lit_same = s0[0] == 255 and s1[0] == 255 and s2[0] == 255
    count = 0
    for y in range(h_px):
        m = alpha[y] if occ_mode == OCC_ALPHA else alpha[0]
        f = occ[y] if occ_mode == OCC_FLOAT else occ[0]
        if cn == 4:
            count += _scene_row(src[y], o, m, f, 4, w_px, occ_mode, l0, l1, l2, s0, s1, s2, lit_same, tabs)
        else:
            count += _scene_row(src[y], o, m, f, 3, w_px, occ_mode, l0, l1, l2, s0, s1, s2, lit_same, tabs)
        _sensor_row(o, out[w3 * y:w3 * (y + 1)], y, h_px, sensor, vig, bank, dy, dx3, sigma_mode, a32, b32, a64, b64)
    _keep_alive(owned)
    return count


#: pixels per vector step of OpenCV's warpAffine (8UC4, INTER_LINEAR) on x86-64 with AVX2: a row's last
#: ``W mod WARP_STEP_PX`` pixels take its scalar formula for the source coordinates (see ``warp_finish``)
WARP_STEP_PX = 16


@nb.njit(**_JIT)
def warp_finish(box, m, lut, out, alpha, sensor, vig, bank, dy, dx3, sigma_mode, a32, b32, a64, b64):
    """``finish`` (``OCC_ALPHA``) of the bilinear warp of the baked box, each row warped into a row buffer and
    finished while it sits in L1: no warped RGBA frame goes through memory, and the box's pixels that the row 8
    rows down will read are prefetched (a frame starts with the box out of cache after the step's other work).

    ``box`` (bh, bw) uint32: the box's RGBA pixels (``rgba.view(np.uint32)``: the bytes are only moved, so the
    channel order is memory order on any endianness); ``m`` (2, 3) float64: the inverse affine (frame pixel ->
    box pixel); ``alpha`` (H, W) uint8 receives the warped alpha; the rest as ``finish``; returns the number of
    shadowed pixels. The warp is ``cv2.warpAffine(rgba, m, (W, H), INTER_LINEAR | WARP_INVERSE_MAP,
    BORDER_CONSTANT 0)`` of OpenCV 5 bit for bit, its arithmetic found by measurement
    (tests/sensors/test_render_kernel.py compares over random affines, borders included): the float32 source point of
    pixel (x, y) is ``fma(m00, x, m01 y + m02)`` with float32 coefficients (the row's base rounded, then one fused
    step), except in a row's last ``W mod WARP_STEP_PX`` pixels, where it is ``fma(m00, x, m01 y) + m02``; the value is
    the fma chain of ``estimators.patches_kernels`` on the four neighbours (the border's 0 outside), rounded half to
    even.

    Loops (a row at a time): the source points, the weights per pixel and the neighbours' indices; the prefetches;
    the samples (``_sample_row``: ``jit.bilinear_rgba8`` 8 pixels a call, or where AVX-512 gathers pay the four
    neighbours' gathers then the blend over the row's pixels, ``_blend_row``); then ``finish``'s tone lookups and
    sensor stage. A row whose
    neighbours are not all inside the box takes the general path (floor, border) in its coordinate and gather loops
    only. One pass is faster than ``cv2.warpAffine`` then ``finish`` (docs/perf-log.md).
    """
    _wide_vectors()
    h_px, w_px = alpha.shape
    w3 = 3 * w_px
    owned = (np.empty(w_px, np.float32), np.empty(w_px, np.float32), _row_buffers(w_px))
    # the arrays the row helpers bind again per row, as views numba counts no references to (``jit.borrowed``)
    box, m, lut, out, alpha, vig, bank = _borrowed((box, m, lut, out, alpha, vig, bank))
    fu, fv = _borrowed(owned[0]), _borrowed(owned[1])
    fa, fb, idx, q00, q01, q10, q11, c00, c01, c10, c11, rgba, o, no_occ = _borrowed(owned[2])
    flat, bw, _, _, _ = _box_layout(box)
    l0, l1, l2, tabs = _tone_tables(lut)
    ahead = np.int64(np.rint(8.0 * m[1, 1])) * bw + np.int64(np.rint(8.0 * m[0, 1]))   # 8 frame rows down
    count = 0
    for y in range(h_px):
        _affine_row(m, y, fu, fv)
        _warp_row(box, flat, ahead, fu, fv, fa, fb, idx, rgba, q00, q01, q10, q11, c00, c01, c10, c11)
        count += _scene_row(rgba, o, alpha[y], no_occ, 4, w_px, OCC_ALPHA, l0, l1, l2, l0, l1, l2, False, tabs)
        _sensor_row(o, out[w3 * y:w3 * (y + 1)], y, h_px, sensor, vig, bank, dy, dx3, sigma_mode, a32, b32, a64, b64)
    _keep_alive(owned)
    return count


@nb.njit(inline="always", **_JIT)
def _warp_row(box, flat, ahead, fu, fv, fa, fb, idx, rgba, q00, q01, q10, q11, c00, c01, c10, c11):
    """The bilinear samples of a box (uint32 RGBA pixels, ``flat`` its pixels in one row) at a row's source points
    (``fu``, ``fv``) into ``rgba``, zero outside the box, bit for bit ``cv2.warpAffine``'s: the row inside takes
    ``_sample_row`` after prefetching the box lines that the row ``ahead`` (a flat offset) will read (a frame starts
    with the box out of cache after the step's other work), a row across the edge ``_border_row``."""
    bh, bw = box.shape
    stride, umax, vmax = np.uint32(bw), np.float32(bw - 1), np.float32(bh - 1)
    if _weights_row(fu, fv, fa, fb, idx, stride, umax, vmax) == 0:
        for x in range(0, fu.shape[0], 4):
            k = np.int64(idx[x]) + ahead
            _prefetch(flat, k)
            _prefetch(flat, k + bw)
        _sample_row(flat, idx, stride, fa, fb, rgba, q00, q01, q10, q11, c00, c01, c10, c11)
    else:
        _border_row(box, fu, fv, fa, fb, q00, q01, q10, q11)
        _blend_row(c00, c01, c10, c11, fa, fb, rgba, 0)


@nb.njit(inline="always", **_JIT)
def _affine_row(m, y, fu, fv):
    """Row y's float32 source points under the inverse affine ``m`` (2, 3) float64 as OpenCV 5's ``warpAffine``
    (INTER_LINEAR, 8UC4 and 32FC1 alike) computes them: ``fma(m00, x, m01 y + m02)`` with float32 coefficients, and
    ``fma(m00, x, m01 y) + m02`` in the row's last ``W mod WARP_STEP_PX`` pixels (its scalar tail)."""
    w_px = fu.shape[0]
    m0, m1, m2 = np.float32(m[0, 0]), np.float32(m[0, 1]), np.float32(m[0, 2])
    m3, m4, m5 = np.float32(m[1, 0]), np.float32(m[1, 1]), np.float32(m[1, 2])
    yf = np.float32(y)
    bu, bv = m1 * yf + m2, m4 * yf + m5
    for x in range(w_px):       # (x through int32: a vector conversion without AVX-512, the same float)
        fu[x] = _fma32(m0, np.float32(np.int32(x)), bu)
        fv[x] = _fma32(m3, np.float32(np.int32(x)), bv)
    pu, pv = m1 * yf, m4 * yf
    for x in range(w_px - w_px % WARP_STEP_PX, w_px):
        fu[x] = _fma32(m0, np.float32(np.int32(x)), pu) + m2
        fv[x] = _fma32(m3, np.float32(np.int32(x)), pv) + m5


@nb.njit(**_JIT)
def level_finish(box, m, grid, mg, shade, h_px, w_px, lut, out, sensor, vig, bank, dy, dx3, sigma_mode, a32, b32,
                 a64, b64):
    """``finish`` (``OCC_FLOAT``) of a map level's bilinear warp with the cast shadows' grid warped beside it, each
    row warped, shaded and finished while it sits in L1: the frames a bake does not serve (a pyramid level above 0),
    without a warped RGBA frame and a float occlusion frame going through memory and without their two OpenCV calls.

    ``box`` (bh, bw) uint32: the level's RGBA pixels, warped by ``m`` as ``warp_finish`` warps its box (bit for bit
    ``cv2.warpAffine`` INTER_LINEAR | WARP_INVERSE_MAP, zero border); ``grid`` (gh, gw) float32: the occlusion at
    the points of ``mg`` (frame pixel -> grid pixel, (2, 3) float64), bit for bit that warp of a float32 image with
    a replicated border (the same source points, ``_affine_row``; the value the fma chain of
    ``jit.bilinear_f32x8``, unrounded, the neighbours clamped to the grid); ``shade`` (3, 256) uint8: the shading
    gains at the quantized occlusion; ``out`` receives the (``h_px``, ``w_px``, 3) frame, flat; the rest as
    ``finish``; returns the number of shadowed pixels (occlusion >= 0.5)."""
    _wide_vectors()
    w3 = 3 * w_px
    table8 = np.full(1024, 255, np.uint8)     # the shading gains of each level as one 32-bit pixel (memory order)
    for q in range(256):
        for c in range(3):
            table8[4 * q + c] = shade[c, q]
    f32 = np.float32
    # fu, fv, gu, gv, ga, gb, occ; gidx; qrow (the quantized occlusion, and the tone pass's alpha row after it), the
    # gains; the row buffers
    owned = ((np.empty(w_px, f32), np.empty(w_px, f32), np.empty(w_px, f32), np.empty(w_px, f32),
              np.empty(w_px, f32), np.empty(w_px, f32), np.empty(w_px, f32)), np.empty(w_px, np.uint32),
             (np.empty(w_px, np.uint8), np.empty(4 * w_px, np.uint8)), table8, _row_buffers(w_px))
    # the arrays the row helpers bind again per row, as views numba counts no references to (``jit.borrowed``)
    box, m, grid, mg, lut, out, vig, bank = _borrowed((box, m, grid, mg, lut, out, vig, bank))
    fu, fv, gu, gv, ga, gb, occ = _borrowed(owned[0])
    gidx = _borrowed(owned[1])
    qrow, gains = _borrowed(owned[2])
    table = _borrowed(owned[3]).view(np.uint32)
    fa, fb, idx, q00, q01, q10, q11, c00, c01, c10, c11, rgba, o, no_occ = _borrowed(owned[4])
    flat, bw, _, _, _ = _box_layout(box)
    gh, gw = grid.shape
    gflat = grid.reshape(gh * gw)
    gumax, gvmax, gstride = np.float32(gw - 1), np.float32(gh - 1), np.uint32(gw)
    l0, l1, l2, tabs = _tone_tables(lut)
    ahead = np.int64(np.rint(8.0 * m[1, 1])) * bw + np.int64(np.rint(8.0 * m[0, 1]))   # 8 frame rows down
    g_ahead = np.int64(np.rint(8.0 * mg[1, 1])) * gw + np.int64(np.rint(8.0 * mg[0, 1]))
    count = 0
    for y in range(h_px):
        _affine_row(m, y, fu, fv)
        _affine_row(mg, y, gu, gv)
        _warp_row(box, flat, ahead, fu, fv, fa, fb, idx, rgba, q00, q01, q10, q11, c00, c01, c10, c11)
        if _weights_row(gu, gv, ga, gb, gidx, gstride, gumax, gvmax) == 0:
            for x in range(0, w_px, 16):     # the grid's rows that row y + 8 will read
                k = np.int64(gidx[x]) + g_ahead
                _prefetch(gflat, k)
                _prefetch(gflat, k + gw)
            _sample_f32_row(gflat, gidx, gstride, ga, gb, occ)
        else:
            _replicate_row(grid, gu, gv, occ)
        count += _shade_rgba_row(rgba, occ, qrow, gains, table)
        _scene_row(rgba, o, qrow, no_occ, 4, w_px, OCC_ALPHA, l0, l1, l2, l0, l1, l2, False, tabs)
        _sensor_row(o, out[w3 * y:w3 * (y + 1)], y, h_px, sensor, vig, bank, dy, dx3, sigma_mode, a32, b32, a64, b64)
    _keep_alive(owned)
    return count


#: pixels per block of ``_shade_rgba_row``'s multiplies (a block whose gains are all 255 is skipped)
_SHADE_BLOCK_PX = 16
_NO_GAIN = np.uint32(0xFFFFFFFF)     # a pixel's gains word that leaves it as it is


@nb.njit(inline="always", **_JIT)
def _shade_rgba_row(rgba, occ, qrow, gains, table):
    """A row's RGBA samples shaded in place by the float occlusion ``occ`` (``finish``'s ``OCC_FLOAT`` arithmetic:
    ``mul255`` by channel c's gain at the quantized occlusion q), so that its tone lookups are those of a baked
    row; returns the shadowed pixels (occlusion >= 0.5). ``table`` (256,) uint32: the three gains of each level as
    a pixel's bytes (alpha 255); ``qrow`` (W,) uint8 and ``gains`` (4 W,) uint8 are row buffers. The count and the
    levels (vectorized loops), one 32-bit gains lookup a pixel (scalar), then every byte's ``mul255`` (vectorized,
    in 16-bit lanes: at most 255 * 255 + 128 + 254, no overflow) in blocks of ``_SHADE_BLOCK_PX`` pixels, skipping
    the blocks whose gains are all 255 (``mul255(v, 255) = v``: sunlit ground where the shading leaves level 0
    alone)."""
    w_px = occ.shape[0]
    count = _count_at_least(occ, np.float32(0.5))
    for x in range(w_px):
        qrow[x] = np.uint8(_quantize(occ[x]))
    g32 = gains.view(np.uint32)
    for x in range(w_px):
        g32[x] = table[qrow[x]]
    n = _SHADE_BLOCK_PX
    body = w_px - w_px % n
    for blk in range(0, body, n):
        if g32[blk] == _NO_GAIN and g32[blk + n - 1] == _NO_GAIN:
            same = _NO_GAIN
            for i in range(n):
                same &= g32[blk + i]
            if same == _NO_GAIN:
                continue
        _mul255_bytes(rgba[4 * blk:4 * blk + 4 * n], gains[4 * blk:4 * blk + 4 * n])
    _mul255_bytes(rgba[4 * body:], gains[4 * body:])
    return count


@nb.njit(inline="always", **_JIT)
def _mul255_bytes(values, gains):
    """``values[j] = mul255(values[j], gains[j])`` (uint8 arrays of one length) in 16-bit arithmetic."""
    for j in range(values.shape[0]):
        p = np.uint16(values[j]) * np.uint16(gains[j]) + np.uint16(128)
        values[j] = np.uint8((p + (p >> np.uint16(8))) >> np.uint16(8))


@nb.njit(inline="always", **_JIT)
def _sample_f32_row(plane, idx, stride, fa, fb, out):
    """The bilinear values (unrounded float32) of a row's points inside a float32 plane: ``jit.bilinear_f32x8`` 8
    points a call, the same fma chain on the rest."""
    n = idx.shape[0]
    body = n - n % _BILINEAR_LANES
    for x in range(0, body, _BILINEAR_LANES):
        _bilinear_f32x8(plane, idx, stride, fa, fb, out, x)
    one = np.uint32(1)
    for x in range(body, n):
        k = idx[x]
        a, b = fa[x], fb[x]
        p00, p01, p10, p11 = plane[k], plane[k + one], plane[k + stride], plane[k + stride + one]
        v0 = _fma32(a, p01 - p00, p00)
        v1 = _fma32(a, p11 - p10, p10)
        out[x] = _fma32(b, v1 - v0, v0)


@nb.njit(**_JIT)
def _replicate_row(grid, fu, fv, out):
    """The general path of ``level_finish``'s occlusion row: the floor, the weights, the four neighbours clamped to
    the grid (a replicated border), the fma chain. Points are clamped to [-2, size + 1] first (the conversion stays
    defined): beyond that both neighbours on an axis are the same edge pixel, whose difference is 0 whatever the
    weight, so the values are those of the unclamped points."""
    gh, gw = grid.shape
    for x in range(fu.shape[0]):
        cu, cv, x0, y0 = _clamped_floor(fu[x], fv[x], gw, gh)
        a = cu - np.float32(x0)
        b = cv - np.float32(y0)
        xa, xb = min(max(x0, 0), gw - 1), min(max(x0 + 1, 0), gw - 1)
        ya, yb = min(max(y0, 0), gh - 1), min(max(y0 + 1, 0), gh - 1)
        p00, p01, p10, p11 = grid[ya, xa], grid[ya, xb], grid[yb, xa], grid[yb, xb]
        v0 = _fma32(a, p01 - p00, p00)
        v1 = _fma32(a, p11 - p10, p10)
        out[x] = _fma32(b, v1 - v0, v0)


@nb.njit(inline="always", **_JIT)
def _shade_row(rgba, shade_px, shade_gain, t, n, row_px, w_px):
    """The sampled row ``rgba`` (RGBA bytes; the frame's row starting at flat index ``row_px``, ``w_px`` wide) at
    its pixels among ``shade_px[t:n]`` (frame flat indices in flat-index order: the row's come first) scaled by
    ``shade_gain`` (``gain_byte``: a view's facades); returns the index past the row's pixels."""
    end = row_px + w_px
    while t < n and shade_px[t] < end:
        p, g = 4 * (shade_px[t] - row_px), shade_gain[t]
        rgba[p] = gain_byte(rgba[p], g)
        rgba[p + 1] = gain_byte(rgba[p + 1], g)
        rgba[p + 2] = gain_byte(rgba[p + 2], g)
        t += 1
    return t


@nb.njit(inline="always", **_JIT)
def gain_byte(v, g):
    """``rint(v g)`` clipped to 0..255 for a byte ``v`` and a gain ``g`` (NumPy's ``uint8 * float32`` in float32,
    or in float64 for a float64 gain)."""
    return np.uint8(min(max(np.rint(np.float32(v) * g), np.float32(0.0)), np.float32(255.0)))


@nb.njit(inline="always", **_JIT)
def _box_layout(box):
    """A box of uint32 pixels as the sampling passes read it: flat, its width, the largest source point whose four
    neighbours are all inside (exclusive, float32, per axis) and the row stride."""
    bh, bw = box.shape
    return box.reshape(bh * bw), bw, np.float32(bw - 1), np.float32(bh - 1), np.uint32(bw)


@nb.njit(inline="always", **_JIT)
def _row_buffers(w_px):
    """The row buffers of the box-sampling passes (``warp_finish``, ``perspective_kernels.view_finish``): the
    bilinear weights per pixel, the top-left neighbours' indices, the four neighbours as uint32 pixels and as their
    bytes, the sampled RGBA row, the toned RGB row, and ``_scene_row``'s float occlusion (unused with the baked
    alpha)."""
    q = np.empty((4, w_px), np.uint32)
    q00, q01, q10, q11 = q[0], q[1], q[2], q[3]
    return (np.empty(w_px, np.float32), np.empty(w_px, np.float32), np.empty(w_px, np.uint32),
            q00, q01, q10, q11, q00.view(np.uint8), q01.view(np.uint8), q10.view(np.uint8), q11.view(np.uint8),
            np.empty(4 * w_px, np.uint8), np.empty(3 * w_px, np.uint8), np.empty(1, np.float32))


@nb.njit(inline="always", **_JIT)
def _weights_row(fu, fv, fa, fb, idx, stride, umax, vmax):
    """A row's source points (``fu``, ``fv``) -> the bilinear weights (``fa``, ``fb``) and the top-left neighbours' flat
    indices (``idx``), the floor taken by truncation; returns non-zero where a point is not inside
    ``[0, umax) x [0, vmax)`` (then the row takes ``_border_row``: the truncation is no floor there)."""
    outside = np.int32(0)
    for x in range(fu.shape[0]):
        u, v = fu[x], fv[x]
        iu, iv = np.int32(u), np.int32(v)        # the floor where the row is inside (checked on the floats)
        fa[x] = u - np.float32(iu)
        fb[x] = v - np.float32(iv)
        idx[x] = np.uint32(iv) * stride + np.uint32(iu)
        inside = (u >= 0) & (v >= 0) & (u < umax) & (v < vmax)     # (false for NaN)
        outside = np.int32(outside | np.int32(not inside))  # (carried as int32: see ``_count_at_least``)
    return outside


@nb.njit(inline="always", **_JIT)
def _sample_row(flat, idx, stride, fa, fb, rgba, q00, q01, q10, q11, c00, c01, c10, c11):
    """The bilinear samples of a row inside the box into ``rgba``: 8 pixels a call of ``jit.bilinear_rgba8`` (two
    64-bit loads a pixel, the chain in vector registers of any width), the row's last ``W mod 8`` pixels by
    ``_gather_row`` and ``_blend_row``; where AVX-512 gathers pay (``FAST_GATHER``), the whole row by those two
    (``jit.gather_pairs16``). The same bytes either way."""
    if _FAST_GATHER:
        _gather_row(flat, idx, stride, q00, q01, q10, q11, 0)
        _blend_row(c00, c01, c10, c11, fa, fb, rgba, 0)
        return
    n = idx.shape[0]
    body = n - n % _BILINEAR_PIXELS
    for x in range(0, body, _BILINEAR_PIXELS):
        _bilinear_rgba8(flat, idx, stride, fa, fb, rgba, x)
    if body < n:
        _gather_row(flat, idx, stride, q00, q01, q10, q11, body)
        _blend_row(c00, c01, c10, c11, fa, fb, rgba, body)


@nb.njit(inline="always", **_JIT)
def _gather_row(flat, idx, stride, q00, q01, q10, q11, start):
    """The four neighbours (uint32 RGBA pixels) of each point of a row inside the box from point ``start`` on
    (``jit.gather_pairs16`` where the hardware gather pays)."""
    n, one = idx.shape[0], np.uint32(1)
    body = start
    if _FAST_GATHER:    # each neighbour pair (x, x + 1) as one 64-bit load, 16 points at a time
        body = n - (n - start) % _GATHER_LANES
        for x in range(start, body, _GATHER_LANES):
            _gather_pairs16(flat, idx, x, 0, q00, q01)
            _gather_pairs16(flat, idx, x, stride, q10, q11)
    for x in range(body, n):   # (elsewhere: one pass, four loads a point)
        k = idx[x]
        q00[x] = flat[k]
        q01[x] = flat[k + one]
        q10[x] = flat[k + stride]
        q11[x] = flat[k + stride + one]


@nb.njit(inline="always", **_JIT)
def _blend_row(c00, c01, c10, c11, fa, fb, rgba, start):
    """The bilinear value of each channel (the neighbours' bytes ``c..``, each pixel's weights ``fa``/``fb``) from
    pixel ``start`` on: the fma chain of ``estimators.patches_kernels``, rounded half to even. A pixel's four
    channels in the inner loop: LLVM broadcasts the weights in registers instead of storing them spread to the four
    channels and loading them back."""
    for x in range(start, fa.shape[0]):
        a, b = fa[x], fb[x]
        for c in range(4):
            j = 4 * x + c
            p00, p01 = np.float32(c00[j]), np.float32(c01[j])
            p10, p11 = np.float32(c10[j]), np.float32(c11[j])
            v0 = _fma32(a, p01 - p00, p00)
            v1 = _fma32(a, p11 - p10, p10)
            rgba[j] = _saturate_u8(np.int32(np.rint(_fma32(b, v1 - v0, v0))))


@nb.njit(inline="always", **_JIT)
def _clamped_floor(u, v, w, h):
    """A point (float32) clamped to [-2, w + 1] x [-2, h + 1] (any point beyond, or NaN (-> -2), reads what a point
    there reads, and the conversion stays defined), and the floor of the clamped point (int32): (cu, cv, x0, y0)."""
    cu = u if u > np.float32(-2.0) else np.float32(-2.0)
    cv = v if v > np.float32(-2.0) else np.float32(-2.0)
    cu = cu if cu < np.float32(w + 1) else np.float32(w + 1)
    cv = cv if cv < np.float32(h + 1) else np.float32(h + 1)
    x0, y0 = np.int32(cu), np.int32(cv)
    x0 -= np.int32(np.float32(x0) > cu)
    y0 -= np.int32(np.float32(y0) > cv)
    return cu, cv, x0, y0


@nb.njit(**_JIT)
def _border_row(box, fu, fv, fa, fb, q00, q01, q10, q11):
    """The general path of a ``warp_finish`` row: the floor (clamped to [-2, size + 1]: any point beyond, or NaN,
    is as far outside, and the conversion stays defined), the weights, and the four neighbours, 0 outside the
    box."""
    bh, bw = box.shape
    zero = np.uint32(0)
    for x in range(fu.shape[0]):
        u, v = fu[x], fv[x]
        _, _, x0, y0 = _clamped_floor(u, v, bw, bh)
        fa[x] = u - np.float32(x0)
        fb[x] = v - np.float32(y0)
        in_x0, in_x1, in_y0, in_y1 = 0 <= x0 < bw, 0 <= x0 + 1 < bw, 0 <= y0 < bh, 0 <= y0 + 1 < bh
        q00[x] = box[y0, x0] if in_x0 and in_y0 else zero
        q01[x] = box[y0, x0 + 1] if in_x1 and in_y0 else zero
        q10[x] = box[y0 + 1, x0] if in_x0 and in_y1 else zero
        q11[x] = box[y0 + 1, x0 + 1] if in_x1 and in_y1 else zero
