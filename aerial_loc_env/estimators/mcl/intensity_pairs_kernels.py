"""The intensity-pair models' per-particle work in one compiled (numba) pass (issue 12): each particle's 2K pair
points projected into the map by its affine, rounded to the nearest pixel, looked up in the database and
compared with the camera's bits (the map's own RGB bytes, or its luma for c = 1), without the (N, 2K) coordinate,
index and word arrays NumPy needed.

Bit for bit the NumPy path it replaced (its branches kept in ``similarity_from_counts``): the map coordinates are
the float32 ``(a0 u + a1 v) + a2'`` of the affine rows (``a2'`` = the translation plus 0.5 in float32, so that
truncation rounds; measured equal to the ``einsum`` they replace on every point of the benchmark's step), clipped
to the map where a point leaves it (then invalid), the agreements counted as integers.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from aerial_loc_env.jit import JIT, prefetch
from aerial_loc_env.sensors import camera as _camera

#: ``sensors.camera.pose_affine`` compiled: eq. (3)'s affine of one particle, the renderer's floats
pose_affine = njit(**JIT)(_camera.pose_affine)


@njit(**JIT)
def pose_affines(terms, poses, cos, sin, out):
    """``pose_affine`` of every pose: ``out`` (N, 2, 3) = ``camera_to_map`` of ``poses`` (N, >= 2) [x_m, y_m, ...]
    with ``cos``/``sin`` (N,) of their yaws and ``terms`` = ``CameraModel.affine_terms``."""
    for m in range(poses.shape[0]):
        a = pose_affine(terms, poses[m, 0], poses[m, 1], cos[m], sin[m])
        out[m, 0, 0], out[m, 0, 1], out[m, 0, 2], out[m, 1, 0], out[m, 1, 1], out[m, 1, 2] = a
    return out


@njit(inline="always", **JIT)
def _pixel(coord, top):
    """A coordinate clipped to [0, top] and truncated, as uint64 through int32 (what a vector unit converts
    without AVX-512), so that the row's product with the width is a 32 x 32 -> 64-bit unsigned multiply (one
    instruction everywhere; a signed 64-bit product is three on AVX2)."""
    return np.uint64(np.uint32(np.int32(min(max(coord, np.float32(0.0)), top))))


@njit(**JIT)
def pair_agreements(poses, cos, sin, terms, uv, pairs, width, height, db, pixel_bytes, channels, nodata, cam_bits,
                    agree, valid):
    """For particle n (its affine ``pose_affine(terms, poses[n, 0], poses[n, 1], cos[n], sin[n])``, eq. (3)'s
    camera pixel -> map pixel, used in float32 with 0.5 added to the translations so that truncation rounds) and
    the j-th used pair i = ``pairs[j]`` (camera points ``uv[i]`` and ``uv[K + i]``, K = ``cam_bits.shape[0]``):
    ``agree[j, n]`` = how many of the
    ``channels`` bits ``db[p1 B + c] > db[p2 B + c]`` (``db`` the database's bytes, B = ``pixel_bytes`` a pixel)
    equal ``cam_bits[i, c]``; ``valid[j, n]`` = both points on the map and not ``nodata`` (flat bool, or empty
    for none). Returns (the agreements of each particle summed (N,) int64, whether any point left the map).

    Pair-major: one pair's points at all particles lie close together on the map (the particles cluster), so
    their lookups hit the cache; particle-major lookups (NumPy's gather) roam over the whole footprint. Each
    pair's lines are prefetched while the previous pair's lookups run: a frame's pairs fall on map lines no step
    touched before (each step draws new pairs), and other work between steps evicts the rest (docs/perf-log.md
    has the figures, and the prefetch distances that did no better). The RGB lookups write each pair's counts
    only; the particles' sums are added after all pairs, in a loop that vectorizes (a running sum per particle in
    the lookups' loop was a load and a store more per lookup)."""
    n, k = poses.shape[0], cam_bits.shape[0]
    sums = np.zeros(n, np.int64)
    w = np.uint64(np.uint32(width))     # (zero-extended: the products are 32 x 32 -> 64-bit)
    wmax, hmax = np.float32(width - 1), np.float32(height - 1)
    fw, fh = np.float32(width), np.float32(height)
    half = np.float32(0.5)
    has_nodata = nodata.shape[0] > 0
    c0, c1, c2 = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
    r0, r1, r2 = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)
    for m in range(n):
        a00, a01, a02, a10, a11, a12 = pose_affine(terms, poses[m, 0], poses[m, 1], cos[m], sin[m])
        c0[m], c1[m], c2[m] = a00, a01, np.float32(a02) + half
        r0[m], r1[m], r2[m] = a10, a11, np.float32(a12) + half
    q1 = np.empty((2, n), np.uint64)          # two pairs' flat pixel indices: this one's and the next one's
    q2 = np.empty((2, n), np.uint64)
    step = np.uint64(pixel_bytes)
    rgb = channels == 3 and pixel_bytes == 3
    one, two = np.uint64(1), np.uint64(2)
    off = np.int32(0)
    used = pairs.shape[0]
    for t in range(used + 1):
        if t < used:                           # pair t's coordinates, and its lookups' lines fetched
            i = pairs[t]
            u1, v1 = np.float32(uv[i, 0]), np.float32(uv[i, 1])
            u2, v2 = np.float32(uv[k + i, 0]), np.float32(uv[k + i, 1])
            vj, p1, p2 = valid[t], q1[t % 2], q2[t % 2]
            for m in range(n):                 # one vectorized loop (clipping is a no-op inside)
                col1 = (c0[m] * u1 + c1[m] * v1) + c2[m]
                row1 = (r0[m] * u1 + r1[m] * v1) + r2[m]
                col2 = (c0[m] * u2 + c1[m] * v2) + c2[m]
                row2 = (r0[m] * u2 + r1[m] * v2) + r2[m]
                inside = ((col1 >= 0) & (col1 < fw) & (row1 >= 0) & (row1 < fh)
                          & (col2 >= 0) & (col2 < fw) & (row2 >= 0) & (row2 < fh))
                off |= np.int32(not inside)
                vj[m] = inside
                p1[m] = _pixel(row1, hmax) * w + _pixel(col1, wmax)
                p2[m] = _pixel(row2, hmax) * w + _pixel(col2, wmax)
            for m in range(n):
                prefetch(db, p1[m] * step)
                prefetch(db, p2[m] * step)
        if t == 0:
            continue
        j = t - 1                              # the previous pair's lookups, its lines on their way
        i, aj, vj, p1, p2 = pairs[j], agree[j], valid[j], q1[j % 2], q2[j % 2]
        if rgb:                                # RGB unrolled, the pair's camera bits hoisted
            g0, g1, g2 = cam_bits[i, 0], cam_bits[i, 1], cam_bits[i, 2]
            for m in range(n):
                b1, b2 = p1[m] * step, p2[m] * step
                a = (np.int64((db[b1] > db[b2]) == g0) + np.int64((db[b1 + one] > db[b2 + one]) == g1)
                     + np.int64((db[b1 + two] > db[b2 + two]) == g2))
                aj[m] = a
        else:
            for m in range(n):
                b1, b2 = p1[m] * step, p2[m] * step
                a = 0
                for c in range(channels):
                    a += np.int64((db[b1 + np.uint64(c)] > db[b2 + np.uint64(c)]) == cam_bits[i, c])
                aj[m] = a
                sums[m] += a
        if has_nodata:
            for m in range(n):
                vj[m] = vj[m] and not nodata[p1[m]] and not nodata[p2[m]]
    if rgb:                                    # the particles' sums in one vectorized pass over the rows
        for j in range(used):
            aj = agree[j]
            for m in range(n):
                sums[m] += aj[m]
    return sums, off != 0


@njit(**JIT)
def camera_pairs(image, u, v, mask, vals, in_mask, uv, cam_bits, kept):
    """The frame's side of the pairs in one pass: ``vals[j]`` = the pixel (``u[j]``, ``v[j]``) of ``image``
    (H, W, C) uint8 as float32, ``uv[j]`` = (u, v) as float64 and, for a ``mask`` (h, w) bool at a reduced
    resolution (empty for none), ``in_mask[j]`` = its value there (``ShadowMask.at``: row ``v h // H`` and
    column ``u w // W``, clipped). Then, for the K = ``cam_bits.shape[0]`` pairs (points j and K + j): their bits
    ``cam_bits[j, c]`` = ``vals[j, c] > vals[K + j, c]`` (eq. (2) on the pixels as they are) and the pairs with no
    or both points in the mask, in order, in ``kept``; returns how many were kept (K - lc)."""
    big_h, big_w = image.shape[0], image.shape[1]
    h, w = mask.shape
    for j in range(u.shape[0]):
        x, y = u[j], v[j]
        for c in range(image.shape[2]):
            vals[j, c] = image[y, x, c]
        uv[j, 0], uv[j, 1] = x, y
        if h > 0:
            in_mask[j] = mask[min((y * h) // big_h, h - 1), min((x * w) // big_w, w - 1)]
    k = cam_bits.shape[0]
    n_kept = 0
    for j in range(k):
        for c in range(cam_bits.shape[1]):
            cam_bits[j, c] = vals[j, c] > vals[k + j, c]
        if in_mask[j] == in_mask[k + j]:
            kept[n_kept] = j
            n_kept += 1
    return n_kept


@njit(**JIT)
def bounded_pairs(raw, width, height, u, v):
    """``u`` = ``rng.integers(0, width, n)`` then ``v`` = ``rng.integers(0, height, n)`` (n = ``u.shape[0]``, even)
    from ``raw``, the n 64-bit words PCG64 gives next (``random_raw``), as NumPy draws them: each value from the next
    32-bit half (the low half of a word first, NumPy's buffered ``next_uint32``) by Lemire's multiply-shift,
    ``(half * bound) >> 32``. Returns False where NumPy would reject a half (``(half * bound) mod 2^32`` below
    ``(2^32 - bound) mod bound``, about one half in 10^7) and draw another: the caller then draws with NumPy."""
    n = u.shape[0]
    for k in range(2):
        bound = np.uint64(width if k == 0 else height)
        threshold = (np.uint64(0xFFFFFFFF) - (bound - np.uint64(1))) % bound
        out = u if k == 0 else v
        for j in range(n):
            h = k * n + j                              # the half's index: word h // 2, low half first
            word = raw[h >> 1]
            half = word & np.uint64(0xFFFFFFFF) if h % 2 == 0 else word >> np.uint64(32)
            m = half * bound
            if (m & np.uint64(0xFFFFFFFF)) < threshold:
                return False
            out[j] = np.int64(m >> np.uint64(32))
    return True
