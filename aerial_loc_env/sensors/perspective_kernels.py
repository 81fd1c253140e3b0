"""Compiled kernels of the perspective camera (``perspective.py``): the march, the per-pixel maps, facade shading.

Why: the per-pixel view maps were a dozen OpenCV warps of the march grid plus NumPy passes over 1-D gathers of the
relief pixels (about 2x the cost of a bare frame warp); one pass per grid, each pixel's ray marched and refined in
registers, costs a fraction of it.

Exactness: the maps equal those of the OpenCV/NumPy implementation they replace (perspective v5) bit for bit. Every
float32 operation is the one that implementation did, in the same order:
- the march probes read the 4 x 4 block maximum at the nearest pooled pixel of ``M (x, y, 1)`` as OpenCV 5's
  nearest-neighbour ``warpAffine`` / ``warpPerspective`` compute it: float32 coefficients, the row term
  ``y M1 + M2`` rounded, then ``fma(M0, x, .)`` in the 16-lane vector body (``_LANES``) and the compiled scalar tail
  ``fma(x, M0, y M1) + M2`` beyond it; round half to even (``v_round``); zero outside the source;
- ``addWeighted`` on float32 is ``fma(a, alpha, fma(b, beta, gamma))`` with float32 coefficients, ``divide`` a true
  float32 division, ``remap`` (nearest) rounds half to even and reads zero outside the source;
- the refinement's NumPy float32 arithmetic is done operation by operation (products and sums rounded apart: numba
  without fastmath fuses nothing but the explicit ``_fma``), ``np.hypot`` as glibc's ``hypotf`` (double sqrt).
``tests/test_perspective_kernels.py`` checks all of it against the OpenCV/NumPy reference.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

_LANES = 16    # OpenCV's nearest warps: vector body in blocks of 2 x 8 float32 lanes (AVX2), scalar tail after it
_JIT = {"cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}
_F32 = np.float32


@intrinsic
def _fma(typingctx, a, b, c):
    """float32 a * b + c with one rounding (LLVM's fma: the FMA instruction, or libm's fmaf without one)."""
    if not all(t == types.float32 for t in (a, b, c)):   # no silent casts: every operand must be float32
        return None
    sig = types.float32(types.float32, types.float32, types.float32)

    def codegen(context, builder, signature, args):
        f32 = ir.FloatType()
        fn = builder.module.declare_intrinsic("llvm.fma", [f32], ir.FunctionType(f32, [f32, f32, f32]))
        return builder.call(fn, args)

    return sig, codegen


@numba.njit(inline="always", **_JIT)
def _round_px(s: np.float32) -> int:
    """Round half to even (cvRound / v_round); far outside any image (or NaN) -> a large negative index."""
    if not (-1.0e9 < s < 1.0e9):
        return -(1 << 40)
    return int(np.rint(s))


# The helpers below take scalars only: an array argument costs a reference count per call (an atomic add and
# subtract), which made an inlined lookup four times slower.

@numba.njit(inline="always", **_JIT)
def _warp_point(m0: np.float32, m1: np.float32, m2: np.float32, m3: np.float32, m4: np.float32, m5: np.float32,
                m6: np.float32, m7: np.float32, m8: np.float32, x: int, y: int, body: bool,
                perspective: bool) -> tuple[int, int]:
    """The source pixel OpenCV's nearest warp reads for destination pixel (x, y) through ``m0..m8`` (row-major
    3 x 3; affine: the last row unused): ``body`` in the row's vector body, else its scalar tail."""
    xf, yf = _F32(x), _F32(y)
    if body:
        sx = _fma(m0, xf, yf * m1 + m2)
        sy = _fma(m3, xf, yf * m4 + m5)
        if perspective:
            w = _fma(m6, xf, yf * m7 + m8)
            sx, sy = sx / w, sy / w
    else:
        sx = _fma(xf, m0, yf * m1) + m2
        sy = _fma(xf, m3, yf * m4) + m5
        if perspective:
            w = _fma(xf, m6, yf * m7) + m8
            sx, sy = sx / w, sy / w
    return _round_px(sx), _round_px(sy)


@numba.njit(inline="always", **_JIT)
def _window_index(ix: int, iy: int, rows: int, cols: int) -> int:
    """Flat index of (ix, iy) in a (rows, cols) window, -1 outside it."""
    if 0 <= ix < cols and 0 <= iy < rows:
        return iy * cols + ix
    return -1


def _march_kernel(perspective: bool):
    """``march`` for affine (nadir) or projective (tilted) cell->pooled warps: a compile-time constant (a runtime
    flag tripled the probe's cost; numba keys its cache on the closure's value)."""

    @numba.njit(**_JIT)
    def march(z0: np.ndarray, relief: np.ndarray, probes: np.ndarray, thresholds: np.ndarray, levels: np.ndarray,
              pooled: np.ndarray, ground: np.ndarray) -> int:
        """The coarse march of ``ReliefView.maps``, one cell of the (hc, wc) grid at a time; returns the number of
        relief cells.

        ``probes`` (steps + 1, 9) float32: the warp of cell (x, y) to the pooled window at height 0 (row 0: where
        the ``ground`` reach is read) and at each march height, top down; a cell's hit height is the first
        ``levels[i]`` whose pooled height exceeds ``thresholds[i]`` (0 without one), ``z0`` the hits' 3 x 3
        maximum; ``relief`` marks cells with ``z0 > 0`` or a non-zero ``ground`` at height 0. ``pooled`` and
        ``ground``: C-contiguous windows of the same shape, zero outside."""
        hc, wc = z0.shape
        nr, nc = pooled.shape
        pool, reach = pooled.reshape(-1), ground.reshape(-1)
        body = (wc // _LANES) * _LANES
        steps = thresholds.size
        hit = np.zeros((hc, wc), np.float32)
        for y in range(hc):
            for x in range(wc):
                ix, iy = _warp_point(probes[0, 0], probes[0, 1], probes[0, 2], probes[0, 3], probes[0, 4],
                                     probes[0, 5], probes[0, 6], probes[0, 7], probes[0, 8], x, y, x < body,
                                     perspective)
                q = _window_index(ix, iy, nr, nc)
                relief[y, x] = 1 if q >= 0 and reach[q] > 0.0 else 0
                for i in range(1, steps + 1):
                    ix, iy = _warp_point(probes[i, 0], probes[i, 1], probes[i, 2], probes[i, 3], probes[i, 4],
                                         probes[i, 5], probes[i, 6], probes[i, 7], probes[i, 8], x, y, x < body,
                                         perspective)
                    q = _window_index(ix, iy, nr, nc)
                    if q >= 0 and pool[q] > thresholds[i - 1]:
                        hit[y, x] = levels[i - 1]
                        break
        count = 0
        for y in range(hc):
            for x in range(wc):
                z = hit[y, x]
                for yy in range(max(y - 1, 0), min(y + 2, hc)):
                    for xx in range(max(x - 1, 0), min(x + 2, wc)):
                        z = max(z, hit[yy, xx])
                z0[y, x] = z
                if z > 0.0:
                    relief[y, x] = 1
                count += relief[y, x]
        return count

    return march


@numba.njit(inline="always", **_JIT)
def _dsm_index(du: np.float32, dv: np.float32, k: np.float32, nx: np.float32, ny: np.float32, rows: int, cols: int,
               c0: int, r0: int, c1: int, r1: int, replicate: bool) -> int:
    """The flat index of h(m(z)) in the (rows, cols) height model, nearest to nadir + k (du, dv); -1 outside it
    (height 0), or (``replicate``) the border of the window (c0, r0, c1, r1) replicated (maps beyond remap's
    size limit are read in a window)."""
    fx = du * k + nx
    fy = dv * k + ny
    if replicate:
        ix = min(max(_round_px(fx - _F32(c0)), 0), c1 - c0 - 1) + c0
        iy = min(max(_round_px(fy - _F32(r0)), 0), r1 - r0 - 1) + r0
        return iy * cols + ix
    return _window_index(_round_px(fx), _round_px(fy), rows, cols)


def _maps_kernel(tilted: bool, replicate: bool):
    """``view_maps`` for nadir or tilted rays, reading the height model with zeros or (a window of a map beyond
    remap's size limit) its border outside: compile-time constants, as for ``march``."""

    @numba.njit(**_JIT)
    def view_maps(out_x: np.ndarray, out_y: np.ndarray, facade: np.ndarray, facing: np.ndarray, z0: np.ndarray,
                  relief: np.ndarray, factor: int, centre: np.ndarray, tilt: np.ndarray, flat: np.ndarray,
                  lin: np.ndarray, consts: np.ndarray, dsm: np.ndarray, window: np.ndarray) -> int:
        """The per-pixel maps of ``ReliefView.maps`` into ``out_x``/``out_y`` (h, w) float32; returns the number
        of facade pixels, whose flat indices and facing directions are written to ``facade``/``facing`` (cell by
        cell).

        Rays: pixel offsets from the principal point ``centre`` (cu, cv), through the centred tilt homography
        ``tilt`` (3, 3) float32 when tilted. Flat cells (``relief`` 0): ``flat`` (2, 3) float32 rows (alpha, beta,
        gamma) of the ground point ``fma(u, alpha, fma(v, beta, gamma))``. Relief cells: ``lin`` (2, 2) float32
        the affine's linear part (ground point - nadir), ``consts`` float32 (nadir x, nadir y, origin-shifted nadir
        x, y, H, surface tolerance, height cap), fixed-point steps from the cell's ``z0`` on ``dsm`` (C-contiguous;
        read per ``window``: c0, r0, c1, r1)."""
        h, w = out_x.shape
        hc, wc = z0.shape
        rows, cols = dsm.shape
        heights = dsm.reshape(-1)
        c0, r0, c1, r1 = window[0], window[1], window[2], window[3]
        cu, cv = centre[0], centre[1]
        nx, ny, ox, oy, big_h, tol, cap = consts[0], consts[1], consts[2], consts[3], consts[4], consts[5], consts[6]
        a0, a1, a2, b0, b1, b2 = flat[0, 0], flat[0, 1], flat[0, 2], flat[1, 0], flat[1, 1], flat[1, 2]
        l00, l01, l10, l11 = lin[0, 0], lin[0, 1], lin[1, 0], lin[1, 1]
        t00, t01, t02, t10, t11, t12 = tilt[0, 0], tilt[0, 1], tilt[0, 2], tilt[1, 0], tilt[1, 1], tilt[1, 2]
        t20, t21, t22 = tilt[2, 0], tilt[2, 1], tilt[2, 2]
        one, zero = _F32(1.0), _F32(0.0)
        map_x, map_y = out_x.reshape(h * w), out_y.reshape(h * w)
        # one band of cells (factor rows of pixels) at a time: its relief pixels are listed first, then each
        # fixed-point step runs over the whole list (independent lookups overlap)
        size = factor * w
        pix = np.empty(size, np.int64)
        bdu, bdv = np.empty(2 * size, np.float32), np.empty(size, np.float32)
        bk, bz = np.empty(size, np.float32), np.empty(size, np.float32)
        n = 0
        for cy in range(hc):
            y0, y1 = cy * factor, min(cy * factor + factor, h)
            m = 0
            for cx in range(wc):
                rel = relief[cy, cx] != 0
                k0 = one - z0[cy, cx] / big_h
                for y in range(y0, y1):
                    v = _F32(y) - cv
                    for x in range(cx * factor, min(cx * factor + factor, w)):
                        u = _F32(x) - cu
                        if tilted:
                            den = _fma(u, t20, _fma(v, t21, t22))
                            ru = _fma(u, t00, _fma(v, t01, t02)) / den
                            rv = _fma(u, t10, _fma(v, t11, t12)) / den
                        else:
                            ru, rv = u, v
                        if not rel:
                            out_x[y, x] = _fma(ru, a0, _fma(rv, a1, a2))
                            out_y[y, x] = _fma(ru, b0, _fma(rv, b1, b2))
                            continue
                        pix[m] = y * w + x
                        bdu[m] = l00 * ru + l01 * rv
                        bdv[m] = l10 * ru + l11 * rv
                        bk[m] = k0
                        m += 1
            for j in range(m):      # z1: the height of the surface the ray is in just below its march hit
                q = _dsm_index(bdu[j], bdv[j], bk[j], nx, ny, rows, cols, c0, r0, c1, r1, replicate)
                bz[j] = min(heights[q] if q >= 0 else zero, cap)
            for j in range(m):      # z2 = h(m(z1)) in bk
                bk[j] = one - bz[j] / big_h
                q = _dsm_index(bdu[j], bdv[j], bk[j], nx, ny, rows, cols, c0, r0, c1, r1, replicate)
                z2 = min(heights[q] if q >= 0 else zero, cap)
                bz[j] = z2 - bz[j]
                bdu[m + j] = z2
            for j in range(m):
                du, dv, scale = bdu[j], bdv[j], bk[j]
                if abs(bz[j]) > tol:            # not settled on a surface after one step: one more
                    z2 = bdu[m + j]
                    scale = one - z2 / big_h
                    q = _dsm_index(du, dv, scale, nx, ny, rows, cols, c0, r0, c1, r1, replicate)
                    z3 = min(heights[q] if q >= 0 else zero, cap)
                    if abs(z3 - z2) > tol:      # still jumping: the ray entered through a wall
                        dist = max(_F32(np.sqrt(np.float64(du) * du + np.float64(dv) * dv)), _F32(1e-3))
                        scale = one + one / dist
                        facade[n] = pix[j]
                        facing[n, 0] = -(du / dist)
                        facing[n, 1] = dv / dist
                        n += 1
                map_x[pix[j]] = du * scale + ox
                map_y[pix[j]] = dv * scale + oy
        return n

    return view_maps


@numba.njit(**_JIT)
def shade_pixels(image: np.ndarray, pixels: np.ndarray, gain: np.ndarray) -> None:
    """``image`` (n_px, c) uint8 rows ``pixels`` times ``gain`` (one per pixel, float32), rounded half to even and
    clipped to 0..255, in place (NumPy's ``rint(uint8 * float32)``)."""
    c = image.shape[1]
    for j in range(pixels.size):
        p, g = pixels[j], gain[j]
        for i in range(c):
            image[p, i] = np.uint8(min(max(np.rint(_F32(image[p, i]) * g), _F32(0.0)), _F32(255.0)))


march = {tilted: _march_kernel(tilted) for tilted in (False, True)}     # by tilt: affine / projective probes
view_maps = {(tilted, replicate): _maps_kernel(tilted, replicate)      # by tilt and border (compiled when used)
             for tilted in (False, True) for replicate in (False, True)}

__all__ = ["march", "shade_pixels", "view_maps"]
