"""Compiled kernels of the perspective camera (``perspective.py``): the march, the per-pixel maps, facade shading.

Why: the per-pixel view maps were a dozen OpenCV warps of the march grid plus NumPy passes over 1-D gathers of the
relief pixels, each pass writing a temporary array. Here: one pass over the march grid, and per band of cells one
row-major pass for the flat pixels then the relief pixels' fixed-point steps over the band's list (independent
lookups overlap, where one pixel's chain of dependent lookups is latency-bound).

How the loops are laid out (LLVM vectorizes a loop only when it can bound every address it touches: one load from a
computed index, one store through a computed index, or one signed index that numba wraps when negative keeps the
whole loop scalar): index passes, vectorized and branch-free (rounding and window tests on the floats:
``_round_px``, ``_window_index``, ``_dsm_index``; int32 flat indices), then a scalar pass of the loads alone
(``_read_row``, ``_gather``), then the next vectorized pass. The march reads every probe of every cell (a row of
cells at a time) and takes the highest level hit (the first from the top: levels decrease); it neither stops at a
cell's first hit nor skips cells whose probe segment crosses no block above the lowest height: those branches cost
more than the loads they would save. In the maps: the third lookup is done for every listed pixel (cheaper than a
branch); the maps are scattered cell by cell, four pixels at a time (loads first, then stores, at unsigned indices:
SLP-vectorized); the facades are listed branch-free only in cells with a wall, and their facing (a float64 square
root) computed over that list alone; untilted rays are the pixel offsets themselves, computed where listed. Both
kernels prefer 512-bit vectors (``jit.wide_vectors``). The timings of these layouts, and the variants that did not
pay, are in docs/perf-log.md.

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
fixed point, so there the old path differed in rare probes). ``tests/sensors/test_perspective_kernels.py`` checks all
of it against the OpenCV/NumPy reference. The kernels compile on first use (seconds, once per view kind: nadir or
tilted) and are cached beside the module.
"""

from __future__ import annotations

import numba
import numpy as np

from aerial_loc_env.jit import FAST_GATHER as _FAST_GATHER
from aerial_loc_env.jit import GATHER_LANES as _GATHER_LANES
from aerial_loc_env.jit import JIT as _JIT
from aerial_loc_env.jit import borrowed as _borrowed
from aerial_loc_env.jit import fma32 as _fma
from aerial_loc_env.jit import fma64 as _fma64
from aerial_loc_env.jit import gather_f32x16 as _gather_f32x16
from aerial_loc_env.jit import index32 as _index32
from aerial_loc_env.jit import keep_alive as _keep_alive
from aerial_loc_env.jit import wide_vectors as _wide
from aerial_loc_env.sensors.render_kernels import (
    OCC_ALPHA,
    _box_layout,
    _row_buffers,
    _scene_row,
    _sensor_row,
    _shade_row,
    _tone_tables,
    _warp_row,
    gain_byte,
)

#: the march's cells: blocks of MARCH_FACTOR x MARCH_FACTOR camera pixels, probed on the heights' block maximum
MARCH_FACTOR = 4
_LANES = 16    # OpenCV's nearest warps: vector body in blocks of 2 x 8 float32 lanes (AVX2), scalar tail after it
_F32 = np.float32
_U1, _U2, _U3 = np.uint64(1), np.uint64(2), np.uint64(3)   # unsigned offsets (no wraparound)
_FAR = -(1 << 30)   # an int32 pixel far outside any window (below every rounded coordinate within +-1e9)


@numba.njit(inline="always", **_JIT)
def _round_px(s: np.float32) -> np.int32:
    """Round half to even (cvRound / v_round) to int32; far outside any image (or NaN) -> ``_FAR``, below every
    window. Branch-free (a select): the loops calling it vectorize."""
    return np.int32(np.rint(s if _F32(-1.0e9) < s < _F32(1.0e9) else _F32(_FAR)))


@numba.njit(inline="always", **_JIT)
def _row_terms(terms: np.ndarray, probes: np.ndarray, y: int) -> None:
    """``terms`` (n, 12) of row ``y`` for the warps ``probes`` (n, 9) (see ``_probe_row``)."""
    yf = _F32(y)
    for i in range(probes.shape[0]):
        for a in range(3):
            m0, m1, m2 = probes[i, 3 * a], probes[i, 3 * a + 1], probes[i, 3 * a + 2]
            terms[i, a] = m0
            terms[i, 3 + a] = yf * m1 + m2
            terms[i, 6 + a] = yf * m1
            terms[i, 9 + a] = m2


@numba.njit(inline="always", **_JIT)
def _window_index(ix: np.int32, iy: np.int32, rows: int, cols: int, stride: int) -> np.int32:
    """Flat index (int32, rows ``stride`` apart) of (ix, iy) in a (rows, cols) window, -1 outside it
    (branch-free)."""
    inside = (ix >= 0) & (ix < cols) & (iy >= 0) & (iy < rows)
    return _index32(iy, np.int32(stride), ix) if inside else np.int32(-1)


@numba.njit(inline="always", **_JIT)
def _probe_row(q: np.ndarray, c0: np.float32, c1: np.float32, c2: np.float32, v0: np.float32, v1: np.float32,
               v2: np.float32, t0: np.float32, t1: np.float32, t2: np.float32, m2: np.float32, m5: np.float32,
               m8: np.float32, body: int, rows: int, cols: int, stride: int, perspective: bool) -> None:
    """The source pixels OpenCV's nearest warp reads for the destination pixels (x, y) of a row, as flat indices
    ``q`` (int32, rows ``stride`` apart) in a (rows, cols) window, -1 outside it, from one row of ``_row_terms``: the
    warp's x coefficients ``c`` (M0, M3, M6), its row terms in the vector body ``v`` (``y M1 + M2`` etc., rounded)
    and in the scalar tail ``t`` (``y M1`` etc.; then M2, M5, M8): the vector body's ``fma(M0, x, .)`` for x <
    ``body``, the compiled tail's ``fma(x, M0, y M1) + M2`` after it (two vectorized loops)."""
    for x in range(body):
        xf = _F32(np.int32(x))
        sx, sy = _fma(c0, xf, v0), _fma(c1, xf, v1)
        if perspective:
            w = _fma(c2, xf, v2)
            sx, sy = sx / w, sy / w
        q[x] = _window_index(_round_px(sx), _round_px(sy), rows, cols, stride)
    for x in range(body, q.size):
        xf = _F32(np.int32(x))
        sx, sy = _fma(xf, c0, t0) + m2, _fma(xf, c1, t1) + m5
        if perspective:
            w = _fma(xf, c2, t2) + m8
            sx, sy = sx / w, sy / w
        q[x] = _window_index(_round_px(sx), _round_px(sy), rows, cols, stride)


@numba.njit(inline="always", **_JIT)
def _read_row(flat: np.ndarray, base: int, q: np.ndarray, out: np.ndarray) -> None:
    """``out[x] = flat[base + q[x]]`` where ``q[x] >= 0``, ``flat[base]`` elsewhere (the caller ignores it): the
    loads alone, unconditional (scalar; the loops around them vectorize)."""
    for x in range(q.size):
        out[x] = flat[np.uint64(base + max(q[x], np.int32(0)))]


def _march_kernel(perspective: bool):
    """``march`` for affine (nadir) or projective (tilted) cell->pooled warps: a compile-time constant (a runtime
    flag made the probe several times slower; numba keys its cache on the closure's value)."""

    @numba.njit(**_JIT)
    def march(z0: np.ndarray, relief: np.ndarray, probes: np.ndarray, thresholds: np.ndarray, levels: np.ndarray,
              pooled: np.ndarray, ground: np.ndarray, window: np.ndarray) -> int:
        """The coarse march of ``ReliefView.maps`` over the (hc, wc) grid, a row of cells at a time: every probe's
        pixel (vectorized), the heights there (the loads alone), then the hits (vectorized); returns the number of
        relief cells.

        ``probes`` (steps + 1, 9) float32: the warp of cell (x, y) to the pooled window at height 0 (row 0: where
        the ``ground`` reach is read) and at each march height, top down; a cell's hit height is the first
        ``levels[i]`` whose pooled height exceeds ``thresholds[i]`` (0 without one), ``z0`` the hits' 3 x 3
        maximum; ``relief`` marks cells with ``z0 > 0`` or a non-zero ``ground`` at height 0. ``pooled`` and
        ``ground`` (C-contiguous, of one shape) are read in ``window`` (row0, col0, rows, cols), zero outside."""
        _wide()
        hc, wc = z0.shape
        nr, nc = np.int32(window[2]), np.int32(window[3])
        stride = np.int32(pooled.shape[1])
        base = window[0] * np.int64(stride) + window[1]
        pool, reach = pooled.reshape(-1), ground.reshape(-1)
        body = (wc // _LANES) * _LANES
        steps = thresholds.size
        hit_flat = np.zeros((hc + 2) * (wc + 2), np.float32)   # zero-padded for the 3 x 3 maximum
        hit = hit_flat.reshape(hc + 2, wc + 2)
        tm = np.empty((steps + 1, 12), np.float32)     # each warp's terms on the row (_row_terms)
        q = np.empty((steps + 1, wc), np.int32)        # each probe's pixel on the row
        val = np.empty((steps + 1, wc), np.float32)    # and the height read there
        zeros = np.zeros(wc, np.float32)
        acc = np.empty((2, wc), np.float32)            # the running maxima, from one row into the other
        for y in range(hc):
            _row_terms(tm, probes, y)
            for i in range(steps + 1):
                _probe_row(q[i], tm[i, 0], tm[i, 1], tm[i, 2], tm[i, 3], tm[i, 4], tm[i, 5], tm[i, 6], tm[i, 7],
                           tm[i, 8], tm[i, 9], tm[i, 10], tm[i, 11], body, nr, nc, stride, perspective)
            _read_row(reach, base, q[0], val[0])
            for i in range(1, steps + 1):
                _read_row(pool, base, q[i], val[i])
            o = (y + 1) * (wc + 2) + 1
            r_row, hit_row, q0, v0 = relief[y], hit_flat[o:o + wc], q[0], val[0]
            for x in range(wc):
                r_row[x] = np.uint8((q0[x] >= 0) & (v0[x] > _F32(0.0)))
            src = zeros
            for i in range(1, steps + 1):  # the first hit from the top: the highest level hit (levels decrease)
                level, threshold, qi, vi = levels[i - 1], thresholds[i - 1], q[i], val[i]
                dst = hit_row if i == steps else acc[i % 2]
                for x in range(wc):
                    dst[x] = max(src[x], level * _F32((qi[x] >= 0) & (vi[x] > threshold)))
                src = dst
            if steps == 0:
                for x in range(wc):
                    hit_row[x] = _F32(0.0)
        count = 0
        across = np.empty((3, wc), np.float32)     # the rows' maxima over x - 1..x + 1, cycled
        for y in range(-2, hc):
            if y + 2 < hc + 2:
                row, out = hit[y + 2], across[(y + 2) % 3]
                for x in range(wc):
                    out[x] = max(max(row[x], row[x + 1]), row[x + 2])
            if y < 0:
                continue
            a0, a1, a2 = across[y % 3], across[(y + 1) % 3], across[(y + 2) % 3]
            z_row, r_row = z0[y], relief[y]
            for x in range(wc):
                z = max(max(a0[x], a1[x]), a2[x])
                z_row[x] = z
                rel = r_row[x] | np.uint8(z > 0.0)
                r_row[x] = rel
                count += rel
        return count
    return march


@numba.njit(inline="always", **_JIT)
def _top(pooled: np.ndarray, probe: np.ndarray, window: np.ndarray, hc: int, wc: int, perspective: bool) -> float:
    """``top_height``'s maximum (``perspective`` a constant at each call site)."""
    nr, nc = np.int32(window[2]), np.int32(window[3])
    stride = np.int32(pooled.shape[1])
    base = window[0] * np.int64(stride) + window[1]
    pool = pooled.reshape(-1)
    body = (wc // _LANES) * _LANES
    tm = np.empty((1, 12), np.float32)
    q = np.empty(wc, np.int32)
    val = np.empty(wc, np.float32)
    top = -np.inf
    for y in range(hc):
        _row_terms(tm, probe, y)
        _probe_row(q, tm[0, 0], tm[0, 1], tm[0, 2], tm[0, 3], tm[0, 4], tm[0, 5], tm[0, 6], tm[0, 7], tm[0, 8],
                   tm[0, 9], tm[0, 10], tm[0, 11], body, nr, nc, stride, perspective)
        _read_row(pool, base, q, val)
        for x in range(wc):
            top = max(top, np.float64(val[x] if q[x] >= 0 else _F32(0.0)))
    return top


def _top_kernel(perspective: bool):
    """``top_height`` for an affine (nadir) or projective (tilted) warp (a compile-time constant, as for
    ``march``)."""

    @numba.njit(**_JIT)
    def top_height(pooled: np.ndarray, probe: np.ndarray, window: np.ndarray, hc: int, wc: int) -> float:
        """The largest of the (hc, wc) heights OpenCV's nearest ``warpAffine`` / ``warpPerspective`` of the window
        (row0, col0, rows, cols) of ``pooled`` by ``probe`` (1, 9) float32 reads, zero outside it
        (``cv2.minMaxLoc``'s maximum of that warp: the same pixels as ``march``'s probes)."""
        return _top(pooled, probe, window, hc, wc, perspective)
    return top_height


@numba.njit(inline="always", **_JIT)
def _mm3(p: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
    """``out = p @ q`` for 3 x 3 float64 matrices as NumPy's ``@`` gives it on x86-64 (OpenBLAS's FMA kernels):
    each entry ``fma(p_i2, q_2j, fma(p_i1, q_1j, p_i0 q_0j))`` (tests/sensors/test_perspective_kernels.py compares
    them over random matrices)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = _fma64(p[i, 2], q[2, j], _fma64(p[i, 1], q[1, j], p[i, 0] * q[0, j]))


@numba.njit(**_JIT)
def tilt_matrix(k: np.ndarray, k_inv: np.ndarray, cr: float, sr: float, cp: float, sp: float,
                out: np.ndarray) -> None:
    """``out`` (3, 3) float64 = ``k @ R_roll @ R_pitch @ k_inv`` (``perspective.tilt_homography``), the products
    left to right as NumPy's ``@`` gives them (``_mm3``); ``R_roll = [[cr, 0, sr], [0, 1, 0], [-sr, 0, cr]]``,
    ``R_pitch = [[1, 0, 0], [0, cp, -sp], [0, sp, cp]]`` (``cr``, ``sr``: the roll's cosine and sine, ``cp``, ``sp``
    the pitch's)."""
    r, t, u = np.zeros((3, 3)), np.empty((3, 3)), np.empty((3, 3))
    r[0, 0], r[0, 2], r[1, 1], r[2, 0], r[2, 2] = cr, sr, 1.0, -sr, cr
    _mm3(k, r, t)
    r[:] = 0.0
    r[0, 0], r[1, 1], r[1, 2], r[2, 1], r[2, 2] = 1.0, cp, -sp, sp, cp
    _mm3(t, r, u)
    _mm3(u, k_inv, out)


_FLT_EPSILON = float(np.finfo(np.float32).eps)   # cv2.perspectiveTransform's |w| threshold


@numba.njit(**_JIT)
def map_corners(a: np.ndarray, tilt: np.ndarray, corners: np.ndarray, tilted: bool, out: np.ndarray) -> None:
    """``out`` (n, 2) float64: the camera points ``corners`` (n, 2), through the tilt homography ``tilt`` (3, 3)
    when ``tilted`` (``cv2.perspectiveTransform``'s arithmetic on x86-64: ``X = fma(x, m0, y m1) + m2``, ``w`` the
    same of the third row, ``(X, Y) * (1 / w)``, 0 where ``|w|`` is within float32's epsilon), then through the
    affine ``a`` (2, 3) (NumPy's ``a @ [x, y, 1]``: ``fma(a2, 1, fma(a1, y, a0 x))``, as ``_mm3``)."""
    for i in range(corners.shape[0]):
        x, y = corners[i, 0], corners[i, 1]
        if tilted:
            w = _fma64(x, tilt[2, 0], y * tilt[2, 1]) + tilt[2, 2]
            if abs(w) > _FLT_EPSILON:
                w = 1.0 / w
                x, y = (_fma64(x, tilt[0, 0], y * tilt[0, 1]) + tilt[0, 2]) * w, \
                    (_fma64(x, tilt[1, 0], y * tilt[1, 1]) + tilt[1, 2]) * w
            else:
                x = y = 0.0
        for r in range(2):
            out[i, r] = _fma64(a[r, 2], 1.0, _fma64(a[r, 1], y, a[r, 0] * x))


@numba.njit(inline="always", **_JIT)
def _probe(m2p: np.ndarray, to_map: np.ndarray, nadir_x: float, nadir_y: float, k: float, s: np.ndarray,
           t: np.ndarray, u: np.ndarray, out: np.ndarray) -> None:
    """``out`` (9,) float32: ``m2p @ S(k) @ to_map`` rounded, S(k) = ``[[k, 0, nadir_x (1 - k)], [0, k, nadir_y
    (1 - k)], [0, 0, 1]]``: the cells' points m(z) = nadir + k (g - nadir), k = 1 - z / H, in pooled px (``s``,
    ``t``, ``u``: 3 x 3 scratch)."""
    s[:] = 0.0
    s[0, 0] = s[1, 1] = k
    s[0, 2], s[1, 2], s[2, 2] = nadir_x * (1.0 - k), nadir_y * (1.0 - k), 1.0
    _mm3(m2p, s, t)
    _mm3(t, to_map, u)
    for i in range(9):
        out[i] = np.float32(u[i // 3, i % 3])


@numba.njit(inline="always", **_JIT)
def _view_args(a: np.ndarray, tilt: np.ndarray, shift: np.ndarray, unshift: np.ndarray, cu: float, cv: float,
               origin_x: int, origin_y: int, tilted: bool, centre: np.ndarray, conj: np.ndarray, flat: np.ndarray,
               lin: np.ndarray) -> tuple[float, float, float, float]:
    """``view_args``' outputs; returns the nadir point (map px) and the same less the origin (float64)."""
    nadir_x = _fma64(a[0, 0], cu, a[0, 1] * cv) + a[0, 2]   # NumPy's 2 x 2 matrix-vector product on x86-64
    nadir_y = _fma64(a[1, 0], cu, a[1, 1] * cv) + a[1, 2]
    ox, oy = nadir_x - np.float64(origin_x), nadir_y - np.float64(origin_y)
    centre[0], centre[1] = np.float32(cu), np.float32(cv)
    if tilted:
        t, u = np.empty((3, 3)), np.empty((3, 3))
        _mm3(unshift, tilt, t)
        _mm3(t, shift, u)
        for i in range(3):
            for j in range(3):
                conj[i, j] = np.float32(u[i, j])
    else:
        conj[:] = 0.0
    flat[0, 0], flat[0, 1], flat[0, 2] = np.float32(a[0, 0]), np.float32(a[0, 1]), np.float32(ox)
    flat[1, 0], flat[1, 1], flat[1, 2] = np.float32(a[1, 0]), np.float32(a[1, 1]), np.float32(oy)
    lin[0, 0], lin[0, 1], lin[1, 0], lin[1, 1] = flat[0, 0], flat[0, 1], flat[1, 0], flat[1, 1]
    return nadir_x, nadir_y, ox, oy


@numba.njit(**_JIT)
def view_args(a: np.ndarray, tilt: np.ndarray, shift: np.ndarray, unshift: np.ndarray, cu: float, cv: float,
              origin_x: int, origin_y: int, tilted: bool, centre: np.ndarray, conj: np.ndarray, flat: np.ndarray,
              lin: np.ndarray) -> None:
    """The maps kernel's per-frame arguments (float32) from the camera -> map affine ``a`` (2, 3) float64: the
    principal point (``centre``: cu, cv), the tilt homography ``tilt`` conjugated by the centring (``conj``:
    ``unshift @ tilt @ shift``; zero untilted), the ground point's affine about the maps' origin (``flat``: the
    linear part and the nadir point less (``origin_x``, ``origin_y``)) and its linear part (``lin``)."""
    _view_args(a, tilt, shift, unshift, cu, cv, origin_x, origin_y, tilted, centre, conj, flat, lin)


def _plan_kernel(perspective: bool):
    """``plan_view`` for an untilted (affine probes) or tilted (projective) view (a compile-time constant, as for
    ``march``)."""
    march_rows = march[perspective]

    @numba.njit(**_JIT)
    def plan_view(a: np.ndarray, tilt: np.ndarray, shift: np.ndarray, unshift: np.ndarray, cu: float, cv: float,
                  big_h: float, frac: float, tol: float, origin_x: int, origin_y: int, march_window: np.ndarray,
                  pooled: np.ndarray, ground: np.ndarray, warps: np.ndarray, levels: np.ndarray, z0: np.ndarray,
                  relief: np.ndarray, centre: np.ndarray, conj: np.ndarray, flat: np.ndarray, lin: np.ndarray,
                  consts: np.ndarray) -> int:
        """A frame's plan (``ReliefView.plan``) in one call: the nadir point, the probes' warps, the top height
        (``top_height``), the march (``march``) into ``z0``/``relief``, and the maps kernel's arguments (``centre``,
        ``conj``, ``flat``, ``lin`` (``view_args``), ``consts``, float32); returns the relief cells (0: flat ground,
        ``consts`` left zero), -1 where nothing stands under the footprint (z_top <= 0; ``z0``/``relief`` zeroed).

        ``a`` (2, 3) float64: camera -> map (level 0); ``tilt`` (3, 3) float64: the tilt homography (the identity
        untilted); ``shift``/``unshift``: the translation by the principal point (cu, cv) and its inverse; ``big_h``
        the altitude H, ``frac`` the height cap's fraction of H, ``tol`` the surface tolerance; (``origin_x``,
        ``origin_y``): the map pixel at the maps' zero; ``march_window`` int64 (row0, col0, rows, cols) of ``pooled``;
        ``warps`` (steps + 1, 9) float32 and ``levels`` (2, steps) float32 (the levels less 1e-4, the levels):
        scratch. The float64 arithmetic is the NumPy expressions' it replaced, operation by operation (``_mm3``)."""
        nadir_x, nadir_y, ox, oy = _view_args(a, tilt, shift, unshift, cu, cv, origin_x, origin_y, perspective,
                                              centre, conj, flat, lin)
        consts[:] = 0.0
        # the march grid -> camera px (block centres), through the tilt, to the map; map px -> pooled px of the window
        f = np.float64(MARCH_FACTOR)
        m3 = np.zeros((3, 3))
        m3[:2, :] = a
        m3[2, 2] = 1.0
        grid = np.zeros((3, 3))
        grid[0, 0] = grid[1, 1] = f
        grid[0, 2] = grid[1, 2] = (f - 1.0) / 2.0
        grid[2, 2] = 1.0
        t, u, to_map = np.empty((3, 3)), np.empty((3, 3)), np.empty((3, 3))
        _mm3(m3, tilt, t)
        _mm3(t, grid, to_map)
        m2p = np.zeros((3, 3))
        m2p[0, 0] = m2p[1, 1] = 1.0 / f
        m2p[0, 2] = (0.5 / f - 0.5) - np.float64(march_window[1])
        m2p[1, 2] = (0.5 / f - 0.5) - np.float64(march_window[0])
        m2p[2, 2] = 1.0
        s = np.empty((3, 3))
        hc, wc = z0.shape
        _probe(m2p, to_map, nadir_x, nadir_y, 1.0, s, t, u, warps[0])
        z_raw = _top(pooled, warps[0:1], march_window, hc, wc, perspective)
        z_top = min(z_raw, frac * big_h)
        if z_top <= 0.0:
            z0[:] = 0.0
            relief[:] = 0
            return -1
        steps = levels.shape[1]
        for i in range(steps):
            level = z_top * np.float64(steps - i) / np.float64(steps)
            levels[0, i] = np.float32(level - 1e-4)
            levels[1, i] = np.float32(level)
            _probe(m2p, to_map, nadir_x, nadir_y, 1.0 - level / big_h, s, t, u, warps[i + 1])
        count = march_rows(z0, relief, warps, levels[0], levels[1], pooled, ground, march_window)
        if count == 0:
            return 0
        cap = frac * big_h if z_raw > frac * big_h else np.inf
        consts[0], consts[1], consts[2], consts[3] = np.float32(nadir_x), np.float32(nadir_y), np.float32(ox), \
            np.float32(oy)
        consts[4], consts[5], consts[6] = np.float32(big_h), np.float32(tol), np.float32(cap)
        return count
    return plan_view


@numba.njit(inline="always", **_JIT)
def _dsm_index(du: np.float32, dv: np.float32, k: np.float32, nx: np.float32, ny: np.float32, rows: int, cols: int,
               c0: int, r0: int, c1: int, r1: int, replicate: bool) -> tuple[np.int32, np.int32, bool]:
    """The pixel of h(m(z)) in the (rows, cols) height model nearest to nadir + k (du, dv): its flat index (int32:
    the sides are below remap's limit), 0 and whether it is inside (height 0 outside; the index is then 0); or
    (``replicate``: maps beyond remap's size limit are read in a window) its column and row in the window (c0, r0,
    c1, r1), its border replicated. Branch-free, so that the loops computing indices vectorize: the rounding
    (``_round_px``) and the window test on the rounded floats (exact integers: the same decisions)."""
    fx = du * k + nx
    fy = dv * k + ny
    if replicate:
        sx, sy = fx - _F32(c0), fy - _F32(r0)
        ix = min(max(_round_px(sx), np.int32(0)), np.int32(c1 - c0 - 1))  # far outside or NaN: the first pixel
        iy = min(max(_round_px(sy), np.int32(0)), np.int32(r1 - r0 - 1))
        return ix + np.int32(c0), iy + np.int32(r0), True
    rx, ry = np.rint(fx), np.rint(fy)
    inside = (rx >= _F32(0.0)) & (rx < _F32(cols)) & (ry >= _F32(0.0)) & (ry < _F32(rows))   # False for NaN
    ix = np.int32(rx) if inside else np.int32(0)
    iy = np.int32(ry) if inside else np.int32(0)
    return _index32(iy, np.int32(cols), ix), np.int32(0), inside


@numba.njit(inline="always", **_JIT)
def _gather(heights: np.ndarray, cols: int, ix: np.ndarray, iy: np.ndarray, out: np.ndarray, m: int,
            flat: bool) -> None:
    """``out[:m]``: the heights (flat, rows ``cols`` apart) at the flat indices ``ix`` or (not ``flat``) the pixels
    (``ix``, ``iy``) (int32, inside): the loads alone (the loops computing the indices vectorize), by AVX-512
    gathers 16 at a time where they pay (``jit.gather_f32x16``), else scalar."""
    start = 0
    if _FAST_GATHER and flat:   # 16 lookups a hardware gather where it pays (``jit.FAST_GATHER``)
        start = m - m % _GATHER_LANES
        for j in range(0, start, _GATHER_LANES):
            _gather_f32x16(heights, ix, j, out)
    for j in range(start, m):
        if flat:
            out[j] = heights[np.uint64(np.uint32(ix[j]))]
        else:
            out[j] = heights[np.uint64(iy[j]) * np.uint64(cols) + np.uint64(ix[j])]


@numba.njit(inline="always", **_JIT)
def _band_scratch(size: int, wc: int) -> tuple:
    """The buffers a band of ``size`` pixels (``wc`` cells) needs in ``_band_kernel``'s bands."""
    f32 = np.float32
    return (np.empty(size, f32), np.empty(size, f32), np.empty(wc, np.int64), np.empty(wc, np.int64),
            np.empty(size, f32), np.empty(size, f32), np.empty(size, f32), np.empty(size, f32), np.empty(size, f32),
            np.empty(size, f32), np.empty(size, np.int32), np.empty(size, np.int32), np.empty(size, np.int32),
            np.empty(size, np.bool_), np.empty(size, f32), np.empty(size, f32), np.empty(size, f32))


def _band_kernel(tilted: bool, replicate: bool):
    """The maps of one band of cells (``factor`` rows of pixels) for nadir or tilted rays, reading the height model
    with zeros or (a window of a map beyond remap's size limit) its border outside: compile-time constants, as for
    ``march``. Inlined into ``view_maps`` (whole planes) and ``view_finish`` (a band's rows at a time)."""

    @numba.njit(inline="always", **_JIT)
    def band(cy: int, y_off: int, out_x: np.ndarray, out_y: np.ndarray, w: int, h: int, facade: np.ndarray,
             facing: np.ndarray, n: int, z0: np.ndarray, relief: np.ndarray, factor: int, centre: np.ndarray,
             tilt: np.ndarray, flat: np.ndarray, lin: np.ndarray, consts: np.ndarray, dsm: np.ndarray,
             window: np.ndarray, scratch: tuple) -> int:
        """Band ``cy``'s rows y into ``out_x``/``out_y`` rows ``y - y_off``; its facades appended to
        ``facade``/``facing`` from ``n`` on (frame flat indices, in flat-index order); returns the new count."""
        (band_du, band_dv, cells, wall_at, bdu, bdv, bk, bz, bz2, bk1, wall, pix_x, pix_y, ins, got, wall_u,
         wall_v) = scratch
        wc = z0.shape[1]
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
        map_x, map_y = out_x.reshape(out_x.size), out_y.reshape(out_y.size)
        shift = y_off * w       # frame flat index -> the planes' flat index
        y0, y1 = cy * factor, min(cy * factor + factor, h)
        for y in range(y0, y1):
            v = _F32(y) - cv
            o = (y - y0) * w
            du_row, dv_row = band_du[o:o + w], band_dv[o:o + w]
            gx_row, gy_row = out_x[y - y_off], out_y[y - y_off]
            for x in range(w):
                u = _F32(np.int32(x)) - cu
                if tilted:
                    den = _fma(u, t20, _fma(v, t21, t22))
                    ru = _fma(u, t00, _fma(v, t01, t02)) / den
                    rv = _fma(u, t10, _fma(v, t11, t12)) / den
                else:
                    ru, rv = u, v
                gx_row[x] = _fma(ru, a0, _fma(rv, a1, a2))
                gy_row[x] = _fma(ru, b0, _fma(rv, b1, b2))
                if tilted:      # (untilted: the rays are the offsets, computed where listed)
                    du_row[x] = l00 * ru + l01 * rv
                    dv_row[x] = l10 * ru + l11 * rv
        m = 0
        n_cells = 0
        for cx in range(wc):
            if relief[cy, cx] == 0:
                continue
            cells[n_cells] = cx
            n_cells += 1
            k0 = one - z0[cy, cx] / big_h
            xa, xb = cx * factor, min(cx * factor + factor, w)
            for y in range(y0, y1):
                o = (y - y0) * w
                v = _F32(y) - cv
                if xb - xa == 4:        # a whole cell of the march's 4 x 4 blocks: loads, then stores (SLP;
                    a, b = np.uint64(o + xa), np.uint64(m)     # unsigned: no negative-index wraparound)
                    p1, p2, p3, q1, q2, q3 = a + _U1, a + _U2, a + _U3, b + _U1, b + _U2, b + _U3
                    if tilted:
                        u0, u1, u2, u3 = band_du[a], band_du[p1], band_du[p2], band_du[p3]
                        v0, v1, v2, v3 = band_dv[a], band_dv[p1], band_dv[p2], band_dv[p3]
                    else:
                        x0 = _F32(xa)
                        r0_, r1_ = x0 - cu, (x0 + _F32(1.0)) - cu
                        r2_, r3_ = (x0 + _F32(2.0)) - cu, (x0 + _F32(3.0)) - cu
                        u0, u1 = l00 * r0_ + l01 * v, l00 * r1_ + l01 * v
                        u2, u3 = l00 * r2_ + l01 * v, l00 * r3_ + l01 * v
                        v0, v1 = l10 * r0_ + l11 * v, l10 * r1_ + l11 * v
                        v2, v3 = l10 * r2_ + l11 * v, l10 * r3_ + l11 * v
                    bdu[b], bdu[q1], bdu[q2], bdu[q3] = u0, u1, u2, u3
                    bdv[b], bdv[q1], bdv[q2], bdv[q3] = v0, v1, v2, v3
                    bk[b], bk[q1], bk[q2], bk[q3] = k0, k0, k0, k0
                    m += 4
                else:
                    for x in range(xa, xb):
                        if tilted:
                            bdu[m] = band_du[o + x]
                            bdv[m] = band_dv[o + x]
                        else:
                            u = _F32(np.int32(x)) - cu
                            bdu[m] = l00 * u + l01 * v
                            bdv[m] = l10 * u + l11 * v
                        bk[m] = k0
                        m += 1
        for j in range(m):      # z1: the height of the surface the ray is in just below its march hit
            pix_x[j], pix_y[j], ins[j] = _dsm_index(bdu[j], bdv[j], bk[j], nx, ny, rows, cols, c0, r0, c1, r1,
                                                    replicate)
        _gather(heights, cols, pix_x, pix_y, got, m, not replicate)
        for j in range(m):      # z2 = h(m(z1)) (the same point where z1 = z0, e.g. open ground)
            g, inside = got[j], ins[j]
            z1 = min(g if inside else zero, cap)
            bz[j] = z1
            k1 = one - z1 / big_h
            bk1[j] = k1
            pix_x[j], pix_y[j], ins[j] = _dsm_index(bdu[j], bdv[j], k1, nx, ny, rows, cols, c0, r0, c1, r1,
                                                    replicate)
        _gather(heights, cols, pix_x, pix_y, got, m, not replicate)
        for j in range(m):      # not settled on a surface after one step: one more (z3)
            k1, k0, z1, g, inside = bk1[j], bk[j], bz[j], got[j], ins[j]
            same = k1 == k0
            z2 = z1 if same else min(g if inside else zero, cap)
            bz2[j] = z2
            bk[j] = k1      # (= k0 where same: a k is 1 - z / H, never -0.0)
            k2 = one - z2 / big_h
            bk1[j] = k2
            pix_x[j], pix_y[j], ins[j] = _dsm_index(bdu[j], bdv[j], k2, nx, ny, rows, cols, c0, r0, c1, r1,
                                                    replicate)
        _gather(heights, cols, pix_x, pix_y, got, m, not replicate)
        for j in range(m):      # settled (or a wall: below) at the last step's point
            z1, z2, g, inside, k1, k0 = bz[j], bz2[j], got[j], ins[j], bk1[j], bk[j]
            z3 = min(g if inside else zero, cap)
            again = abs(z2 - z1) > tol
            scale = k1 if again else k0
            bz[j] = bdu[j] * scale + ox
            bz2[j] = bdv[j] * scale + oy
            wall[j] = np.int32(again & (abs(z3 - z2) > tol))  # still jumping: the ray entered through a wall
        n0 = n
        j = 0
        for c in range(n_cells):    # scattered to the maps
            xa, xb = cells[c] * factor, min(cells[c] * factor + factor, w)
            for y in range(y0, y1):
                row_x, row_y = out_x[y - y_off], out_y[y - y_off]
                if xb - xa == 4:        # loads, then stores (SLP)
                    a, b = np.uint64(j), np.uint64(xa)
                    p1, p2, p3, q1, q2, q3 = a + _U1, a + _U2, a + _U3, b + _U1, b + _U2, b + _U3
                    u0, u1, u2, u3 = bz[a], bz[p1], bz[p2], bz[p3]
                    v0, v1, v2, v3 = bz2[a], bz2[p1], bz2[p2], bz2[p3]
                    row_x[b], row_x[q1], row_x[q2], row_x[q3] = u0, u1, u2, u3
                    row_y[b], row_y[q1], row_y[q2], row_y[q3] = v0, v1, v2, v3
                    j += 4
                else:
                    for x in range(xa, xb):
                        row_x[x] = bz[j]
                        row_y[x] = bz2[j]
                        j += 1
        j = 0
        for c in range(n_cells):    # each cell's first listed pixel if the cell has a wall, else -1
            size_c = (y1 - y0) * (min(cells[c] * factor + factor, w) - cells[c] * factor)
            any_wall = np.int32(0)
            for i in range(size_c):
                any_wall |= wall[np.uint64(j + i)]
            wall_at[c] = j if any_wall != 0 else -1
            j += size_c
        for y in range(y0, y1):     # the walls listed (written at n, kept where a wall) row by row: the
            for c in range(n_cells):    # frame's facades in flat-index order
                if wall_at[c] < 0:
                    continue
                xa, xb = cells[c] * factor, min(cells[c] * factor + factor, w)
                j = wall_at[c] + (y - y0) * (xb - xa)
                for x in range(xa, xb):
                    ju, iu = np.uint64(j), np.uint64(n - n0)
                    facade[np.uint64(n)] = y * w + x
                    wall_u[iu] = bdu[ju]
                    wall_v[iu] = bdv[ju]
                    n += wall[ju]
                    j += 1
        for i in range(n - n0):     # walls: coloured from where the ray meets the ground, facing it
            du, dv = wall_u[i], wall_v[i]
            dist = max(_F32(np.sqrt(np.float64(du) * du + np.float64(dv) * dv)), _F32(1e-3))
            scale = one + one / dist
            wall_u[i] = du * scale + ox
            wall_v[i] = dv * scale + oy
            bdu[i] = -(du / dist)
            bdv[i] = dv / dist
        band_facade, band_facing = facade[n0:n], facing[n0:n]
        for i in range(n - n0):
            p = np.uint64(band_facade[i] - shift)
            map_x[p] = wall_u[i]
            map_y[p] = wall_v[i]
            band_facing[i, 0] = bdu[i]
            band_facing[i, 1] = bdv[i]
        return n

    return band


def _maps_kernel(tilted: bool, replicate: bool):
    """``view_maps`` for nadir or tilted rays, reading the height model with zeros or (a window of a map beyond
    remap's size limit) its border outside (``_band_kernel``)."""
    band = _band_kernel(tilted, replicate)

    @numba.njit(**_JIT)
    def view_maps(out_x: np.ndarray, out_y: np.ndarray, facade: np.ndarray, facing: np.ndarray, z0: np.ndarray,
                  relief: np.ndarray, factor: int, centre: np.ndarray, tilt: np.ndarray, flat: np.ndarray,
                  lin: np.ndarray, consts: np.ndarray, dsm: np.ndarray, window: np.ndarray) -> int:
        """The per-pixel maps of ``ReliefView.maps`` into ``out_x``/``out_y`` (h, w) float32; returns the number
        of facade pixels, whose flat indices and facing directions are written to ``facade``/``facing`` in
        flat-index order (the finishing pass takes them row by row without sorting).

        Rays: pixel offsets from the principal point ``centre`` (cu, cv), through the centred tilt homography
        ``tilt`` (3, 3) float32 when tilted. Flat cells (``relief`` 0): ``flat`` (2, 3) float32 rows (alpha, beta,
        gamma) of the ground point ``fma(u, alpha, fma(v, beta, gamma))``. Relief cells: ``lin`` (2, 2) float32
        the affine's linear part (ground point - nadir), ``consts`` float32 (nadir x, nadir y, origin-shifted nadir
        x, y, H, surface tolerance, height cap), fixed-point steps from the cell's ``z0`` on ``dsm`` (C-contiguous;
        read per ``window``: c0, r0, c1, r1)."""
        _wide()
        h, w = out_x.shape
        # One band of cells (factor rows of pixels) at a time: every pixel's ray and ground point row by row (flat
        # cells keep it), then the relief cells' pixels listed cell by cell, then each fixed-point step over the
        # whole list (independent lookups overlap; a pixel's chain of dependent lookups is latency-bound).
        scratch = _band_scratch(factor * w, z0.shape[1])
        n = 0
        for cy in range(z0.shape[0]):
            n = band(cy, 0, out_x, out_y, w, h, facade, facing, n, z0, relief, factor, centre, tilt, flat, lin,
                     consts, dsm, window, scratch)
        return n

    return view_maps


@numba.njit(inline="always", **_JIT)
def _facade_gain(fx: np.float32, fy: np.float32, sun: np.ndarray) -> np.float32:
    """``ReliefView.facade_gains``'s sunlit gain of a facade facing (``fx``, ``fy``) (east, north), in its float32
    operations and their order: ``sun`` float32 (sin az, cos az, the direct light's coefficient, half the ambient,
    1 / gamma, facade_gain)."""
    towards = (_F32(0.0) + fx * sun[0]) + fy * sun[1]      # (portable.matmul: products added in index order)
    lit = min(sun[3] + sun[2] * max(towards, _F32(0.0)), _F32(1.5))
    return sun[5] * lit ** sun[4]


@numba.njit(**_JIT)
def facade_gains(facing: np.ndarray, sun: np.ndarray, out: np.ndarray) -> None:
    """``out`` (n,) float32: the sunlit gain (``_facade_gain``) of each facing (n, 2) float32."""
    for i in range(out.size):
        out[i] = _facade_gain(facing[i, 0], facing[i, 1], sun)


def _finish_kernel(tilted: bool, replicate: bool):
    """``view_finish`` for nadir or tilted rays (``_band_kernel``'s constants)."""
    band = _band_kernel(tilted, replicate)

    @numba.njit(**_JIT)
    def view_finish(box: np.ndarray, facade: np.ndarray, facing: np.ndarray, gains: np.ndarray, sun: np.ndarray,
                    fixed_gain: float, z0: np.ndarray, relief: np.ndarray, factor: int, centre: np.ndarray,
                    tilt: np.ndarray, flat: np.ndarray, lin: np.ndarray, consts: np.ndarray, dsm: np.ndarray,
                    window: np.ndarray, lut: np.ndarray, out: np.ndarray, alpha: np.ndarray, sensor: bool,
                    vig: np.ndarray, bank: np.ndarray, dy: int, dx3: int, sigma_mode: int, a32: np.float32,
                    b32: np.float32, a64: float, b64: float) -> int:
        """The frame of ``view_maps``' maps: ``render_kernels.warp_finish`` with the box sampled through them (bit for
        bit OpenCV 5's ``cv2.remap(rgba, map_x, map_y, INTER_LINEAR, BORDER_CONSTANT 0)``), the facade pixels scaled
        by their gains after the alpha is taken and before the tone (``render_kernels._shade_row``), a band of cells
        at a time: the band's maps (its rows of each plane, in cache: the planes never go through memory), facades
        and gains, then the band's rows sampled and finished. Returns the shadowed pixels.

        ``box`` (bh, bw) uint32 as ``warp_finish``'s, the maps made in its pixels (``consts``' origin-shifted
        nadir); ``facade``/``facing``/``gains``: buffers for up to H W facades (``gains`` float32 with a sun, else
        float64: the gain's precision), the facades' gains ``_facade_gain`` with ``sun`` (its first value NaN:
        none) else ``fixed_gain``; the maps' arguments as ``view_maps``', the rest as ``warp_finish``'s after its
        matrix. The box lines 8 rows down are prefetched from the flat ground's step per row (the later rows' maps
        are not made yet)."""
        _wide()
        h_px, w_px = alpha.shape
        hc, wc = z0.shape
        # the arrays the band and row helpers bind again per band and row, as views numba counts no references to
        owned = (_band_scratch(factor * w_px, wc), np.empty((factor, w_px), np.float32),
                 np.empty((factor, w_px), np.float32), _row_buffers(w_px))
        scratch, band_x, band_y = _borrowed(owned[0]), _borrowed(owned[1]), _borrowed(owned[2])
        fa, fb, idx, q00, q01, q10, q11, c00, c01, c10, c11, rgba, o, no_occ = _borrowed(owned[3])
        box, facade, facing, gains, alpha, out, vig, bank, lut, sun = _borrowed(
            (box, facade, facing, gains, alpha, out, vig, bank, lut, sun))
        z0, relief, centre, tilt, flat, lin, consts, dsm, window = _borrowed(
            (z0, relief, centre, tilt, flat, lin, consts, dsm, window))
        flat_box, bw, umax, vmax, stride = _box_layout(box)
        l0, l1, l2, tabs = _tone_tables(lut)
        w3 = 3 * w_px
        lit = not np.isnan(sun[0])
        # the box lines 8 rows down (the flat ground's step per camera row): the band's later rows are not made yet
        ahead = np.int64(np.rint(_F32(8.0) * flat[1, 1])) * bw + np.int64(np.rint(_F32(8.0) * flat[0, 1]))
        n, t, count = 0, 0, 0
        for cy in range(hc):
            y0 = cy * factor
            n0 = n
            n = band(cy, y0, band_x, band_y, w_px, h_px, facade, facing, n, z0, relief, factor, centre, tilt, flat,
                     lin, consts, dsm, window, scratch)
            for i in range(n0, n):
                gains[i] = _facade_gain(facing[i, 0], facing[i, 1], sun) if lit else fixed_gain
            for y in range(y0, min(y0 + factor, h_px)):
                _warp_row(box, flat_box, ahead, band_x[y - y0], band_y[y - y0], fa, fb, idx, rgba, q00, q01, q10,
                          q11, c00, c01, c10, c11)
                t = _shade_row(rgba, facade, gains, t, n, np.int64(y) * w_px, w_px)
                count += _scene_row(rgba, o, alpha[y], no_occ, 4, w_px, OCC_ALPHA, l0, l1, l2, l0, l1, l2, False,
                                    tabs)
                _sensor_row(o, out[w3 * y:w3 * (y + 1)], y, h_px, sensor, vig, bank, dy, dx3, sigma_mode, a32, b32,
                            a64, b64)
        _keep_alive(owned)
        return count

    return view_finish


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
top_height = {tilted: _top_kernel(tilted) for tilted in (False, True)}
plan_view = {tilted: _plan_kernel(tilted) for tilted in (False, True)}
view_maps = {(tilted, replicate): _maps_kernel(tilted, replicate)      # by tilt and border (compiled when used)
             for tilted in (False, True) for replicate in (False, True)}
view_finish = {(tilted, replicate): _finish_kernel(tilted, replicate)
               for tilted in (False, True) for replicate in (False, True)}

__all__ = ["facade_gains", "map_corners", "march", "plan_view", "shade_pixels", "tilt_matrix", "top_height",
           "view_args", "view_finish", "view_maps"]
