"""A window of a downsampled database level, bit for bit the same window of ``cv2.resize(whole, size, INTER_AREA)``.

The estimators downsample their database once with OpenCV's area filter (the patch sampler's level, the template
matcher's working level, the map-ratio detector's luma). On a map read by window (``world.maps.raster.RasterMap``)
the whole image is never in memory, so the level is made window by window; resizing a crop would not do: the crop's
scale (its width over the rounded level width) and the positions of its level pixels are not the whole map's, and
its values differ in the last bits wherever a level pixel straddles source pixels.

``area_window`` computes level pixels [dx0, dx1) x [dy0, dy1) of the whole map's level from the source pixels under
them, with OpenCV's own arithmetic (``modules/imgproc/src/resize.cpp``): the general path's tables
(``computeResizeAreaTab``: per level pixel, the covered source pixels and float32 weights, from the whole map's
scale and the pixel's global index), the horizontal pass then the vertical one in the tables' order in float32
(``ResizeArea_Invoker``), rounding to nearest-even for 8-bit output; and the integer-scale path
(``resizeAreaFast``: a block's sum in OpenCV's order, unrolled by four, times 1 / area; its 2 x 2 vector
variants). tests/estimators/test_windowed_maps.py checks it against ``cv2.resize`` on many sizes, scales, channel
counts and windows.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache

import numpy as np

from aerial_loc_env.errors import ConfigError

#: reads source pixels [v0, v0 + h) x [u0, u0 + w) as (h, w, C) (or (h, w)) of the level's dtype
SourceReader = Callable[[int, int, int, int], np.ndarray]

_DBL_EPSILON = 2.220446049250313e-16


def _scale(src: int, dst: int) -> float:
    """OpenCV's ``scale = 1. / inv_scale`` with ``inv_scale = (double)dst / src``."""
    return 1.0 / (dst / src)


def is_area_fast(src_size: tuple[int, int], dst_size: tuple[int, int]) -> bool:
    """Whether ``cv2.resize`` takes its integer-scale path (``resizeAreaFast``) for these sizes (w, h)."""
    sx, sy = _scale(src_size[0], dst_size[0]), _scale(src_size[1], dst_size[1])
    return abs(sx - _cv_round(sx)) < _DBL_EPSILON and abs(sy - _cv_round(sy)) < _DBL_EPSILON


def _cv_round(x: float) -> int:
    return int(np.rint(x))


@lru_cache(maxsize=64)
def _area_tab(ssize: int, dsize: int, d0: int, d1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``computeResizeAreaTab`` for destination pixels [d0, d1): (taps, d1 - d0) source indices, float32 weights
    and a use mask, tap t of a pixel being its t-th table entry (the order the sums run in); unused taps have
    weight 0 at the pixel's first source index. The same double arithmetic as OpenCV's loop, for all pixels at
    once."""
    scale = _scale(ssize, dsize)
    dx = np.arange(d0, d1, dtype=np.float64)
    fsx1 = dx * scale
    fsx2 = fsx1 + scale
    cell = np.minimum(scale, ssize - fsx1)
    sx2 = np.minimum(np.floor(fsx2), ssize - 1)
    sx1 = np.minimum(np.ceil(fsx1), sx2)
    first = (sx1 - fsx1) > 1e-3
    last = (fsx2 - sx2) > 1e-3
    n_full = (sx2 - sx1).astype(np.int64)
    n_first = first.astype(np.int64)
    taps = int((n_first + n_full + last).max())
    alpha_first = ((sx1 - fsx1) / cell).astype(np.float32)
    alpha_full = (1.0 / cell).astype(np.float32)
    alpha_last = (np.minimum(np.minimum(fsx2 - sx2, 1.0), cell) / cell).astype(np.float32)
    base = (sx1 - n_first).astype(np.int64)        # the pixel's first source index
    idx = np.empty((taps, dx.size), np.int64)
    alpha = np.zeros((taps, dx.size), np.float32)
    use = np.zeros((taps, dx.size), bool)
    for t in range(taps):
        j = t - n_first                            # position among the full taps
        is_first = first & (t == 0)
        is_full = (j >= 0) & (j < n_full)
        is_last = last & (j == n_full)
        idx[t] = np.where(is_first, sx1 - 1, np.where(is_full, sx1 + j, np.where(is_last, sx2, base)))
        alpha[t] = np.where(is_first, alpha_first, np.where(is_full, alpha_full, np.where(is_last, alpha_last, 0)))
        use[t] = is_first | is_full | is_last
    for a in (idx, alpha, use):
        a.flags.writeable = False
    return idx, alpha, use


def level_pixels_within(src_size: tuple[int, int], dst_size: tuple[int, int],
                        box: tuple[int, int, int, int]) -> tuple[int, int, int, int] | None:
    """The level pixels (dx0, dy0, dx1, dy1) whose source pixels all lie in the source ``box`` (u0, v0, u1, v1)
    (None when no level pixel does)."""
    out = []
    for axis in (0, 1):
        s0, s1 = box[axis], box[axis + 2]
        if is_area_fast(src_size, dst_size):
            k = _cv_round(_scale(src_size[axis], dst_size[axis]))
            d0, d1 = -(-s0 // k), min(dst_size[axis], s1 // k)
        else:
            f = src_size[axis] / dst_size[axis]
            c0, c1 = max(0, int(s0 / f) - 1), min(dst_size[axis], int(math.ceil(s1 / f)) + 1)
            if c0 >= c1:
                return None
            idx, _, use = _area_tab(src_size[axis], dst_size[axis], c0, c1)
            lo = np.where(use, idx, np.iinfo(np.int64).max).min(axis=0)
            hi = np.where(use, idx, -1).max(axis=0)
            inside = np.flatnonzero((lo >= s0) & (hi < s1))
            if inside.size == 0:
                return None
            d0, d1 = c0 + int(inside[0]), c0 + int(inside[-1]) + 1
        if d0 >= d1:
            return None
        out.append((d0, d1))
    return out[0][0], out[1][0], out[0][1], out[1][1]


def source_box(src_size: tuple[int, int], dst_size: tuple[int, int],
               box: tuple[int, int, int, int]) -> tuple[int, int, int, int]:
    """The source pixels (u0, v0, u1, v1) that level pixels ``box`` = (dx0, dy0, dx1, dy1) are made from."""
    dx0, dy0, dx1, dy1 = box
    if is_area_fast(src_size, dst_size):
        kx, ky = _cv_round(_scale(src_size[0], dst_size[0])), _cv_round(_scale(src_size[1], dst_size[1]))
        return dx0 * kx, dy0 * ky, min(src_size[0], dx1 * kx), min(src_size[1], dy1 * ky)
    xi, _, xu = _area_tab(src_size[0], dst_size[0], dx0, dx1)
    yi, _, yu = _area_tab(src_size[1], dst_size[1], dy0, dy1)
    return int(xi[xu].min()), int(yi[yu].min()), int(xi[xu].max()) + 1, int(yi[yu].max()) + 1


def area_window(read: SourceReader, src_size: tuple[int, int], dst_size: tuple[int, int],
                box: tuple[int, int, int, int], dtype: np.dtype | type) -> np.ndarray:
    """Level pixels ``box`` = (dx0, dy0, dx1, dy1) of ``cv2.resize(source, dst_size, interpolation=INTER_AREA)``
    (sizes (w, h), a downsampling in both axes), from the source pixels ``read`` gives (``source_box``), as
    (dy1 - dy0, dx1 - dx0[, C]) of ``dtype`` (float32 with 1 to 4 channels, or uint8 with 1)."""
    dtype = np.dtype(dtype)
    if dtype not in (np.dtype(np.float32), np.dtype(np.uint8)):
        raise ConfigError(f"area_window: {dtype} levels are not supported (float32 or uint8)")
    if not (dst_size[0] <= src_size[0] and dst_size[1] <= src_size[1]):
        raise ConfigError(f"area_window: {src_size} -> {dst_size} is not a downsampling")
    dx0, dy0, dx1, dy1 = box
    if not (0 <= dx0 < dx1 <= dst_size[0] and 0 <= dy0 < dy1 <= dst_size[1]):
        raise ConfigError(f"area_window: box {box} is not inside the {dst_size} level")
    su0, sv0, su1, sv1 = source_box(src_size, dst_size, box)
    src = np.asarray(read(su0, sv0, su1 - su0, sv1 - sv0))
    squeeze = src.ndim == 2
    if squeeze:
        src = src[..., None]
    if src.dtype != dtype:
        raise ConfigError(f"area_window: the source is {src.dtype}, the level {dtype}")
    if tuple(src_size) == tuple(dst_size):
        out = src.copy()
    elif is_area_fast(src_size, dst_size):
        out = _fast(src, _cv_round(_scale(src_size[0], dst_size[0])), _cv_round(_scale(src_size[1], dst_size[1])),
                    dx0, src_size[0])
    else:
        out = _general(src, src_size, dst_size, box, su0, sv0)
    return out[..., 0] if squeeze else out


def _general(src: np.ndarray, src_size, dst_size, box, su0: int, sv0: int) -> np.ndarray:
    """``ResizeArea_Invoker``: per source row, buf[dx] += S[si] * alpha in table order; per level row,
    sum = beta buf (first entry), then sum += beta buf; float32 throughout, rounded to nearest-even for uint8."""
    dx0, dy0, dx1, dy1 = box
    xi, xa, xu = _area_tab(src_size[0], dst_size[0], dx0, dx1)
    yi, ya, yu = _area_tab(src_size[1], dst_size[1], dy0, dy1)
    # an unused tap adds (a source value) x 0 = 0: the sum is unchanged (the layers are finite)
    s = src.astype(np.float32, copy=False)
    buf = s[:, xi[0] - su0] * xa[0][None, :, None]
    for t in range(1, xi.shape[0]):
        buf += s[:, xi[t] - su0] * xa[t][None, :, None]
    out = buf[yi[0] - sv0] * ya[0][:, None, None]
    for t in range(1, yi.shape[0]):
        out += buf[yi[t] - sv0] * ya[t][:, None, None]
    if src.dtype == np.uint8:
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    return out


def _fast(src: np.ndarray, kx: int, ky: int, dx0: int, src_w: int) -> np.ndarray:
    """``resizeAreaFast``: the k x k block of each level pixel (every block is whole: the source size is k times the
    level's). float32: 2 x 2 with 1 or 4 channels goes through the vector op ((a0 + a1) + (b0 + b1)) * 0.25 for
    the first 4 floor(w / 4) values of a row, else the block's values in row-major order summed as OpenCV's loop
    unrolled by four does, times the float32 1 / area; uint8: the integer sum times 1 / area, rounded, or
    (sum + 2) >> 2 for 2 x 2."""
    h, w, cn = src.shape[0] // ky, src.shape[1] // kx, src.shape[2]
    blocks = src.reshape(h, ky, w, kx, cn)
    vals = [blocks[:, sy, :, sx, :] for sy in range(ky) for sx in range(kx)]   # the ofs order: rows, then columns
    if src.dtype == np.uint8:
        total = np.zeros((h, w, cn), np.int64)
        for v in vals:
            total += v
        if kx == 2 and ky == 2 and cn in (1, 3, 4):
            return ((total + 2) >> 2).astype(np.uint8)
        scaled = total.astype(np.float32) * np.float32(1.0 / (kx * ky))
        return np.clip(np.rint(scaled), 0, 255).astype(np.uint8)
    area = len(vals)
    acc = np.zeros((h, w, cn), np.float32)
    k = 0
    while k <= area - 4:
        acc = acc + (((vals[k] + vals[k + 1]) + vals[k + 2]) + vals[k + 3])
        k += 4
    while k < area:
        acc = acc + vals[k]
        k += 1
    out = acc * np.float32(1.0 / area)
    if kx == 2 and ky == 2 and cn in (1, 4):
        vec = ((vals[0] + vals[1]) + (vals[2] + vals[3])) * np.float32(0.25)
        if cn == 4:
            return vec
        # the vector op covers elements [0, 4 floor(w1 / 4)) of each row, w1 = the level's width (every row's
        # blocks are whole); those are global indices, the window starts at dx0
        w1 = src_w // 2
        gx = np.arange(dx0, dx0 + w)
        out = np.where((gx < 4 * (w1 // 4))[None, :, None], vec, out)
    return out
