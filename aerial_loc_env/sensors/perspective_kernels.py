"""Compiled kernels of the perspective camera (``perspective.py``): the march, the per-pixel maps, facade shading.

Why: the per-pixel view maps were a dozen OpenCV warps of the march grid plus NumPy passes over 1-D gathers of the
relief pixels, each pass writing a temporary array. Here: one pass over the march grid (a cell stops at its first
hit), and per band of cells one row-major pass for the flat pixels then the relief pixels' fixed-point steps over
the band's list (independent lookups overlap; one pixel's chain of dependent lookups was latency-bound).
The march skips a cell whose probe segment crosses no block (``_BLOCK`` pooled px) above the lowest march height:
it cannot hit (the same result, not an approximation). What is left is memory-bound: the relief pixels' gathers
from the height model and the march's probes. Measured and not kept: a relief cell whose lookups all fall in
blocks of one height (block minimum = maximum) skipping them (no gain within the noise on the perf scene and on
RealisticPaper), a uint16 palette of the height model (2-byte gathers: 4 % of the maps kernel), the march
without early exit (slower).

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
These are OpenCV 5's kernels as dispatched on x86-64 with AVX2 (measured against it; OpenCV 4 rounded its warps in
fixed point, so there the old path differed in rare probes). ``tests/test_perspective_kernels.py`` checks all of it
against the OpenCV/NumPy reference. The kernels compile on first use (about 4 s per view kind: nadir or tilted) and
are cached beside the module.
"""

from __future__ import annotations

import numba
import numpy as np

from ..world.kernels import JIT as _JIT
from ..world.kernels import fma32 as _fma
from .frame_kernel import gain_byte

_BLOCK = 4     # the march's skip test: maxima of 4 x 4 pooled pixels
_LANES = 16    # OpenCV's nearest warps: vector body in blocks of 2 x 8 float32 lanes (AVX2), scalar tail after it
_F32 = np.float32


@numba.njit(inline="always", **_JIT)
def _round_px(s: np.float32) -> int:
    """Round half to even (cvRound / v_round); far outside any image (or NaN) -> a large negative index."""
    if not (-1.0e9 < s < 1.0e9):
        return -(1 << 40)
    return int(np.rint(s))


# The per-probe and per-pixel helpers take scalars only: an array argument costs a reference count per call (an
# atomic add and subtract), which made an inlined lookup four times slower.

@numba.njit(inline="always", **_JIT)
def _warp_point(c0: np.float32, c1: np.float32, c2: np.float32, v0: np.float32, v1: np.float32, v2: np.float32,
                t0: np.float32, t1: np.float32, t2: np.float32, m2: np.float32, m5: np.float32, m8: np.float32,
                x: int, body: bool, perspective: bool) -> tuple[int, int]:
    """The source pixel OpenCV's nearest warp reads for destination pixel (x, y), from one row of ``_row_terms``:
    the warp's x coefficients ``c`` (M0, M3, M6), its row terms in the vector body ``v`` (``y M1 + M2`` etc.,
    rounded) and in the scalar tail ``t`` (``y M1`` etc.; then M2, M5, M8): ``body`` picks the vector body's
    ``fma(M0, x, .)`` or the compiled tail's ``fma(x, M0, y M1) + M2``."""
    xf = _F32(x)
    if body:
        sx, sy = _fma(c0, xf, v0), _fma(c1, xf, v1)
        if perspective:
            w = _fma(c2, xf, v2)
            sx, sy = sx / w, sy / w
    else:
        sx, sy = _fma(xf, c0, t0) + m2, _fma(xf, c1, t1) + m5
        if perspective:
            w = _fma(xf, c2, t2) + m8
            sx, sy = sx / w, sy / w
    return _round_px(sx), _round_px(sy)


@numba.njit(inline="always", **_JIT)
def _row_terms(terms: np.ndarray, probes: np.ndarray, y: int) -> None:
    """``terms`` (n, 12) of row ``y`` for the warps ``probes`` (n, 9) (see ``_warp_point``)."""
    yf = _F32(y)
    for i in range(probes.shape[0]):
        for a in range(3):
            m0, m1, m2 = probes[i, 3 * a], probes[i, 3 * a + 1], probes[i, 3 * a + 2]
            terms[i, a] = m0
            terms[i, 3 + a] = yf * m1 + m2
            terms[i, 6 + a] = yf * m1
            terms[i, 9 + a] = m2


@numba.njit(inline="always", **_JIT)
def _window_index(ix: int, iy: int, rows: int, cols: int, stride: int) -> int:
    """Flat index (rows ``stride`` apart) of (ix, iy) in a (rows, cols) window, -1 outside it."""
    if 0 <= ix < cols and 0 <= iy < rows:
        return iy * stride + ix
    return -1


def _march_kernel(perspective: bool):
    """``march`` for affine (nadir) or projective (tilted) cell->pooled warps: a compile-time constant (a runtime
    flag tripled the probe's cost; numba keys its cache on the closure's value)."""

    @numba.njit(**_JIT)
    def march(z0: np.ndarray, relief: np.ndarray, probes: np.ndarray, thresholds: np.ndarray, levels: np.ndarray,
              pooled: np.ndarray, ground: np.ndarray, window: np.ndarray) -> int:
        """The coarse march of ``ReliefView.maps``, one cell of the (hc, wc) grid at a time; returns the number of
        relief cells.

        ``probes`` (steps + 1, 9) float32: the warp of cell (x, y) to the pooled window at height 0 (row 0: where
        the ``ground`` reach is read) and at each march height, top down; a cell's hit height is the first
        ``levels[i]`` whose pooled height exceeds ``thresholds[i]`` (0 without one), ``z0`` the hits' 3 x 3
        maximum; ``relief`` marks cells with ``z0 > 0`` or a non-zero ``ground`` at height 0. ``pooled`` and
        ``ground`` (C-contiguous, of one shape) are read in ``window`` (row0, col0, rows, cols), zero outside."""
        hc, wc = z0.shape
        nr, nc = window[2], window[3]
        stride = pooled.shape[1]
        base = window[0] * stride + window[1]
        pool, reach = pooled.reshape(-1), ground.reshape(-1)
        body = (wc // _LANES) * _LANES
        steps = thresholds.size
        # Skip test: a cell's probes lie on the segment between its first and last (m(z) is linear in z), so
        # their pixels lie in that segment's box widened by a pixel (rounding); where the block maximum over the box
        # is at most the lowest threshold no probe can hit (exact: the same decision as probing every height)
        bnr, bnc = -(-nr // _BLOCK), -(-nc // _BLOCK)
        blocks = np.zeros((bnr, bnc), np.float32)
        for r in range(nr):
            for c in range(nc):
                blocks[r // _BLOCK, c // _BLOCK] = max(blocks[r // _BLOCK, c // _BLOCK], pool[base + r * stride + c])
        low = thresholds[steps - 1]
        hit = np.zeros((hc, wc), np.float32)
        tm = np.empty((steps + 1, 12), np.float32)     # each warp's terms on the row (_row_terms)
        for y in range(hc):
            _row_terms(tm, probes, y)
            for x in range(wc):
                ix, iy = _warp_point(tm[0, 0], tm[0, 1], tm[0, 2], tm[0, 3], tm[0, 4], tm[0, 5], tm[0, 6], tm[0, 7],
                                     tm[0, 8], tm[0, 9], tm[0, 10], tm[0, 11], x, x < body, perspective)
                q = _window_index(ix, iy, nr, nc, stride)
                relief[y, x] = 1 if q >= 0 and reach[base + q] > 0.0 else 0
                ax, ay = _warp_point(tm[1, 0], tm[1, 1], tm[1, 2], tm[1, 3], tm[1, 4], tm[1, 5], tm[1, 6], tm[1, 7],
                                     tm[1, 8], tm[1, 9], tm[1, 10], tm[1, 11], x, x < body, perspective)
                n = steps
                bx, by = _warp_point(tm[n, 0], tm[n, 1], tm[n, 2], tm[n, 3], tm[n, 4], tm[n, 5], tm[n, 6], tm[n, 7],
                                     tm[n, 8], tm[n, 9], tm[n, 10], tm[n, 11], x, x < body, perspective)
                c0, c1 = max(min(ax, bx) - 1, 0), min(max(ax, bx) + 1, nc - 1)
                r0, r1 = max(min(ay, by) - 1, 0), min(max(ay, by) + 1, nr - 1)
                if c0 > c1 or r0 > r1:
                    continue            # the whole segment outside the window: reads zeros
                top = _F32(0.0)
                for br in range(r0 // _BLOCK, r1 // _BLOCK + 1):
                    for bc in range(c0 // _BLOCK, c1 // _BLOCK + 1):
                        top = max(top, blocks[br, bc])
                if top <= low:
                    continue
                for i in range(1, steps + 1):   # the first and last probes are (ax, ay) and (bx, by)
                    if i == 1:
                        ix, iy = ax, ay
                    elif i == steps:
                        ix, iy = bx, by
                    else:
                        ix, iy = _warp_point(tm[i, 0], tm[i, 1], tm[i, 2], tm[i, 3], tm[i, 4], tm[i, 5], tm[i, 6],
                                             tm[i, 7], tm[i, 8], tm[i, 9], tm[i, 10], tm[i, 11], x, x < body,
                                             perspective)
                    q = _window_index(ix, iy, nr, nc, stride)
                    if q >= 0 and pool[base + q] > thresholds[i - 1]:
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
    return _window_index(_round_px(fx), _round_px(fy), rows, cols, cols)


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
        # One band of cells (factor rows of pixels) at a time: every pixel's ray and ground point row by row (flat
        # cells keep it), then the relief cells' pixels listed cell by cell, then each fixed-point step over the
        # whole list (independent lookups overlap; a pixel's chain of dependent lookups was latency-bound).
        size = factor * w
        ray_u, ray_v = np.empty(size, np.float32), np.empty(size, np.float32)
        pix = np.empty(size, np.int64)
        bdu, bdv = np.empty(size, np.float32), np.empty(size, np.float32)
        bk, bz, bz2 = np.empty(size, np.float32), np.empty(size, np.float32), np.empty(size, np.float32)
        n = 0
        for cy in range(hc):
            y0, y1 = cy * factor, min(cy * factor + factor, h)
            for y in range(y0, y1):
                v = _F32(y) - cv
                ru_row, rv_row = ray_u[(y - y0) * w:(y - y0 + 1) * w], ray_v[(y - y0) * w:(y - y0 + 1) * w]
                gx_row, gy_row = out_x[y], out_y[y]
                for x in range(w):
                    u = _F32(x) - cu
                    if tilted:
                        den = _fma(u, t20, _fma(v, t21, t22))
                        ru = _fma(u, t00, _fma(v, t01, t02)) / den
                        rv = _fma(u, t10, _fma(v, t11, t12)) / den
                    else:
                        ru, rv = u, v
                    ru_row[x], rv_row[x] = ru, rv
                    gx_row[x] = _fma(ru, a0, _fma(rv, a1, a2))
                    gy_row[x] = _fma(ru, b0, _fma(rv, b1, b2))
            m = 0
            for cx in range(wc):
                if relief[cy, cx] == 0:
                    continue
                k0 = one - z0[cy, cx] / big_h
                for y in range(y0, y1):
                    for x in range(cx * factor, min(cx * factor + factor, w)):
                        ru, rv = ray_u[(y - y0) * w + x], ray_v[(y - y0) * w + x]
                        pix[m] = y * w + x
                        bdu[m] = l00 * ru + l01 * rv
                        bdv[m] = l10 * ru + l11 * rv
                        bk[m] = k0
                        m += 1
            for j in range(m):      # z1: the height of the surface the ray is in just below its march hit
                q = _dsm_index(bdu[j], bdv[j], bk[j], nx, ny, rows, cols, c0, r0, c1, r1, replicate)
                bz[j] = min(heights[q] if q >= 0 else zero, cap)
            for j in range(m):      # z2 = h(m(z1)) (the same point where z1 = z0, e.g. open ground: no lookup)
                k1 = one - bz[j] / big_h
                if k1 != bk[j]:
                    q = _dsm_index(bdu[j], bdv[j], k1, nx, ny, rows, cols, c0, r0, c1, r1, replicate)
                    bz2[j] = min(heights[q] if q >= 0 else zero, cap)
                    bk[j] = k1
                else:
                    bz2[j] = bz[j]
            for j in range(m):
                du, dv, scale, z1, z2 = bdu[j], bdv[j], bk[j], bz[j], bz2[j]
                if abs(z2 - z1) > tol:          # not settled on a surface after one step: one more
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
            image[p, i] = gain_byte(image[p, i], g)


march = {tilted: _march_kernel(tilted) for tilted in (False, True)}     # by tilt: affine / projective probes
view_maps = {(tilted, replicate): _maps_kernel(tilted, replicate)      # by tilt and border (compiled when used)
             for tilted in (False, True) for replicate in (False, True)}

__all__ = ["march", "shade_pixels", "view_maps"]
