"""The compiled passes of ``estimators/shadow_detection.py``: the morphology of the detected mask, the shadow index on
a reduced frame and the split statistics, each reproducing the OpenCV/NumPy result it replaced (the tests compare
them)."""

from __future__ import annotations

import numpy as np
from numba import njit

from aerial_loc_env.jit import JIT as _JIT


@njit(**_JIT)
def _open_close(binary, open_runs, close_runs):
    """``binary`` (h, w) uint8 opened by ``open_runs``, then closed by ``close_runs`` (``_runs``; empty: no pass),
    as a new (h, w) uint8 array.

    Each pass works on the image padded by the largest radius R and read as one flat row of stride w + 2R: an
    element offset (dy, dx) is then one shift of that row, and a pass is one vectorized minimum (erosion) or
    maximum (dilation) of shifted rows per offset, with the padding set to the value that never wins (OpenCV's
    default border for morphology: the image alone decides). Outputs in the padding columns are discarded."""
    h, w = binary.shape
    rad = 0
    for runs in (open_runs, close_runs):
        for r in range(runs.shape[0]):
            rad = max(rad, abs(runs[r, 0]), abs(runs[r, 1]), abs(runs[r, 2]))
    stride = w + 2 * rad
    first = rad * stride + rad                      # flat index of pixel (0, 0)
    size = (h + 2 * rad) * stride + 2 * rad         # the last shifted row reads up to 2R past the padded image
    a, b = np.empty(size, np.uint8), np.empty(size, np.uint8)
    for y in range(h):
        row, src = a[first + y * stride:first + y * stride + w], binary[y]
        for x in range(w):
            row[x] = src[x]
    src_buf, dst_buf = a, b
    for p in range(4):
        runs = open_runs if p < 2 else close_runs
        if runs.shape[0] == 0:
            continue
        erode = p == 0 or p == 3                    # opening: erode, dilate; closing: dilate, erode
        _pad(src_buf, h, w, rad, stride, np.uint8(255) if erode else np.uint8(0))
        out = dst_buf[first:first + h * stride]
        n = h * stride
        started = False
        for r in range(runs.shape[0]):
            for dx in range(runs[r, 1], runs[r, 2] + 1):
                off = first + runs[r, 0] * stride + dx
                shifted = src_buf[off:off + n]
                if not started:
                    for i in range(n):
                        out[i] = shifted[i]
                    started = True
                elif erode:
                    for i in range(n):
                        out[i] = min(out[i], shifted[i])
                else:
                    for i in range(n):
                        out[i] = max(out[i], shifted[i])
        src_buf, dst_buf = dst_buf, src_buf
    result = np.empty((h, w), np.uint8)
    for y in range(h):
        row, dst = src_buf[first + y * stride:first + y * stride + w], result[y]
        for x in range(w):
            dst[x] = row[x]
    return result


@njit(**_JIT)
def _pad(buf, h, w, rad, stride, value):
    """Set the padding of a flat padded image (see ``_open_close``) to ``value``: the R rows above and below and
    the 2R columns between one row's end and the next row's start."""
    top = rad * stride + rad
    for i in range(top):
        buf[i] = value
    for y in range(h):
        end = top + y * stride + w
        for i in range(end, end + 2 * rad):
            buf[i] = value
    for i in range(top + (h - 1) * stride + w + 2 * rad, buf.shape[0]):
        buf[i] = value


@njit(**_JIT)
def _index8(small, lum8, c3_table, mode, c3):
    """``clip(index * 255, 0, 255)`` truncated to uint8, the index in float32 as ``shadow_index`` writes it:
    ``0.5 (c3 + 1 - lum / 255)`` (mode 0), ``c3`` (1) or ``1 - lum / 255`` (2); ``c3`` (h, w) receives the
    colour invariant (modes 0 and 1) from ``c3_table``."""
    h, w = lum8.shape
    out = np.empty((h, w), np.uint8)
    for y in range(h):
        _index8_row(small[y], lum8[y], c3, y, out[y], c3_table, mode, w)
    return out


@njit(inline="always", **_JIT)
def _index8_row(s_row, l_row, c3, y, o_row, c3_table, mode, w):
    """Row ``y`` of ``_index8`` (``c3``'s row ``y`` written in modes 0 and 1): the table lookups in one loop, the
    arithmetic in another, one per mode: that one vectorizes (with the lookups or the mode's branches in it, the
    whole row stayed scalar)."""
    one, half, k255, zero = np.float32(1.0), np.float32(0.5), np.float32(255.0), np.float32(0.0)
    if mode == 2:
        for x in range(w):
            t = one - np.float32(l_row[x]) / k255
            o_row[x] = np.uint8(min(max(t * k255, zero), k255))
        return
    c_row = c3[y]
    for x in range(w):
        c_row[x] = c3_table[s_row[x, 2], max(s_row[x, 0], s_row[x, 1])]
    if mode == 0:
        for x in range(w):
            t = half * ((c_row[x] + one) - np.float32(l_row[x]) / k255)
            o_row[x] = np.uint8(min(max(t * k255, zero), k255))
    else:
        for x in range(w):
            o_row[x] = np.uint8(min(max(c_row[x] * k255, zero), k255))


@njit(**_JIT)
def _reduce_index8(image, c3_table, mode):
    """``_quarter``, ``cv2.cvtColor(.., COLOR_RGB2GRAY)`` and ``_index8`` in one pass over the frame's rows (an
    (H, W, 3) uint8 frame, H and W multiples of 4): (small, lum8, c3, idx8), each reduced row turned into its
    luminance and index while it is in the cache, without two more calls' fixed costs. The luminance is
    OpenCV's fixed-point sum ``(9798 R + 19235 G + 3735 B + 2^14) >> 15`` (equal to ``cvtColor`` on every 8-bit
    colour, tested); ``c3`` is (0, 0) in mode 2 (no colour invariant)."""
    big_h, big_w = image.shape[0], image.shape[1]
    h, w = big_h // 4, big_w // 4
    small = np.empty((h, w, 3), np.uint8)
    lum8 = np.empty((h, w), np.uint8)
    c3 = np.empty((h, w) if mode != 2 else (0, 0), np.float32)
    out = np.empty((h, w), np.uint8)
    rows, flat_small = image.reshape(big_h, big_w * 3), small.reshape(h, w * 3)
    pair = np.empty(big_w * 3, np.int16)
    lum = np.empty(w, np.int32)
    for y in range(h):
        _quarter_row(rows[4 * y + 1], rows[4 * y + 2], flat_small[y], pair, w)
        s_row, l_row = small[y], lum8[y]
        for x in range(w):
            lum[x] = (np.int32(9798) * np.int32(s_row[x, 0]) + np.int32(19235) * np.int32(s_row[x, 1])
                      + np.int32(3735) * np.int32(s_row[x, 2]) + np.int32(16384)) >> np.int32(15)
        for x in range(w):
            l_row[x] = np.uint8(lum[x])
        _index8_row(s_row, l_row, c3, y, out[y], c3_table, mode, w)
    return small, lum8, c3, out


@njit(**_JIT)
def _quarter(image):
    """``cv2.resize(image, (W // 4, H // 4), interpolation=INTER_LINEAR)`` of an (H, W, 3) uint8 frame, H and W
    multiples of 4: each output pixel's source point falls halfway between source pixels 4x + 1 and 4x + 2 (and
    rows 4y + 1 and 4y + 2), so the bilinear weights are all 1/2 and OpenCV's fixed-point result is the rounded
    mean ``(sum of the 4 + 2) >> 2`` (tests compare it with cv2.resize over random frames). Reads half of the
    frame's rows once: their sum (one vectorized pass a row pair), then every fourth pixel pair of it."""
    big_h, big_w = image.shape[0], image.shape[1]
    h, w = big_h // 4, big_w // 4
    out = np.empty((h, w, 3), np.uint8)
    rows, flat_out = image.reshape(big_h, big_w * 3), out.reshape(h, w * 3)
    pair = np.empty(big_w * 3, np.int16)
    for y in range(h):
        _quarter_row(rows[4 * y + 1], rows[4 * y + 2], flat_out[y], pair, w)
    return out


@njit(inline="always", **_JIT)
def _quarter_row(a, b, o, pair, w):
    """One output row of ``_quarter`` from the frame's rows ``a`` (4y + 1) and ``b`` (4y + 2), flat bytes."""
    two = np.int16(2)
    for i in range(pair.shape[0]):
        pair[i] = np.int16(a[i]) + np.int16(b[i])
    for x in range(w):
        k = 12 * x + 3
        o[3 * x] = np.uint8((pair[k] + pair[k + 3] + two) >> two)
        o[3 * x + 1] = np.uint8((pair[k + 1] + pair[k + 4] + two) >> two)
        o[3 * x + 2] = np.uint8((pair[k + 2] + pair[k + 5] + two) >> two)


@njit(**_JIT)
def _split_stats(binary, lum8, c3, lum_pairwise):
    """Pixels inside (``binary`` != 0), the luminance sums inside and outside, and the c3 sums of each class (0
    where ``c3`` is empty), each class's values added as NumPy's float32 ``compress(...).sum()`` adds them
    (pairwise, row-major); the luminance sums exact integers unless ``lum_pairwise`` (an image too large for
    exact float32 sums of 8-bit values: NumPy's float32 mean then, as before). The exact sums are integer sums
    in the counting pass (one vectorized loop), not a chain of dependent float additions after it."""
    h, w = binary.shape
    n_in, lum_in_int, lum_all_int = 0, 0, 0
    for y in range(h):
        b, lum = binary[y], lum8[y]
        for x in range(w):
            inside = np.int64(b[x] != 0)
            n_in += inside
            lum_in_int += inside * np.int64(lum[x])
            lum_all_int += np.int64(lum[x])
    lum_in, lum_out = np.float64(lum_in_int), np.float64(lum_all_int - lum_in_int)
    if not lum_pairwise and c3.shape[0] == 0:
        return n_in, lum_in, lum_out, np.float32(0.0), np.float32(0.0)
    # each class's values in row-major order (branch-free: every value is written to both, the class's index
    # advances; one spare slot each for the writes past the end)
    n_out = h * w - n_in
    l_in, l_out = np.empty(n_in + 1, np.float32), np.empty(n_out + 1, np.float32)
    c_in, c_out = np.empty(n_in + 1, np.float32), np.empty(n_out + 1, np.float32)
    k_in, k_out = 0, 0
    has_c3 = c3.shape[0] > 0
    for y in range(h):
        b, lum = binary[y], lum8[y]
        for x in range(w):
            inside = np.int64(b[x] != 0)
            if lum_pairwise:
                v = np.float32(lum[x])
                l_in[k_in], l_out[k_out] = v, v
            if has_c3:
                v = c3[y, x]
                c_in[k_in], c_out[k_out] = v, v
            k_in += inside
            k_out += 1 - inside
    if lum_pairwise:
        lum_in, lum_out = np.float64(_pairwise_sum(l_in, 0, k_in)), np.float64(_pairwise_sum(l_out, 0, k_out))
    if c3.shape[0] == 0:
        return n_in, lum_in, lum_out, np.float32(0.0), np.float32(0.0)
    return n_in, lum_in, lum_out, _pairwise_sum(c_in, 0, k_in), _pairwise_sum(c_out, 0, k_out)


@njit(**_JIT)
def _split_figures(idx8, lum8, c3, lum_pairwise):
    """Otsu's split of the index ``idx8`` (h, w) uint8 (``_otsu``: 1 above the threshold) and the two figures the
    detector decides on: (split, both classes non-empty, the shadow class's mean luminance over the rest's, its
    mean ``c3`` minus the rest's: 0 where ``c3`` is empty). The means are NumPy's float32 means from
    ``_split_stats``' sums (``float32(sum) / float32(count)``), the ratio and the difference in float64, as
    ``ShadowDetector.detect`` computed them."""
    h, w = idx8.shape
    threshold = _otsu(idx8)
    binary = np.empty((h, w), np.uint8)
    for y in range(h):
        src, dst = idx8[y], binary[y]
        for x in range(w):
            dst[x] = np.uint8(src[x] > threshold)
    n_in, lum_in, lum_out, c3_in, c3_out = _split_stats(binary, lum8, c3, lum_pairwise)
    n_out = binary.size - n_in
    if n_in == 0 or n_out == 0:
        return binary, False, 0.0, 0.0
    mean_in = np.float64(np.float32(lum_in) / np.float32(n_in))
    mean_out = np.float64(np.float32(lum_out) / np.float32(n_out))
    ratio = mean_in / max(mean_out, 1e-6)
    shift = 0.0
    if c3.shape[0] > 0:
        shift = np.float64(np.float32(c3_in) / np.float32(n_in)) - np.float64(np.float32(c3_out) / np.float32(n_out))
    return binary, True, ratio, shift


@njit(**_JIT)
def _classify(idx8, lum8, c3, lum_pairwise, max_luminance_ratio, min_blue_shift, open_runs, close_runs):
    """The detector's work after the index ``idx8`` (h, w) uint8 in one call: Otsu's split and its figures
    (``_split_figures``), the decision and the morphology. Returns the mask (h, w) uint8 (``_open_close`` of the
    split), or zeros when a class is empty, the shadow class is not darker than ``max_luminance_ratio`` times the
    rest, or (``c3`` not empty) not bluer by ``min_blue_shift``."""
    binary, split, ratio, shift = _split_figures(idx8, lum8, c3, lum_pairwise)
    if not split or ratio > max_luminance_ratio or (c3.shape[0] > 0 and not shift >= min_blue_shift):
        return np.zeros(binary.shape, np.uint8)
    return _open_close(binary, open_runs, close_runs)


@njit(**_JIT)
def _otsu(img):
    """Otsu's threshold of an 8-bit image as OpenCV computes it (``cv2.threshold(.., THRESH_OTSU)``'s
    ``getThreshVal_Otsu``: the histogram's mean and the classes' running means in float64, the first level of
    the largest between-class variance, levels where a class holds less than FLT_EPSILON skipped; tests compare
    it with OpenCV over many images): pixels above it are the upper class."""
    h, w = img.shape
    hist = np.zeros(256, np.int64)
    for y in range(h):
        row = img[y]
        for x in range(w):
            hist[row[x]] += 1
    scale = 1.0 / (h * w)
    mu = 0.0
    for i in range(256):
        mu += i * np.float64(hist[i])
    mu *= scale
    eps = np.float64(np.finfo(np.float32).eps)
    mu1, q1, max_sigma, max_val = 0.0, 0.0, 0.0, 0
    for i in range(256):
        p_i = hist[i] * scale
        mu1 *= q1
        q1 += p_i
        q2 = 1.0 - q1
        if min(q1, q2) < eps or max(q1, q2) > 1.0 - eps:
            continue
        mu1 = (mu1 + i * p_i) / q1
        mu2 = (mu - q1 * mu1) / q2
        sigma = q1 * q2 * (mu1 - mu2) * (mu1 - mu2)
        if sigma > max_sigma:
            max_sigma, max_val = sigma, i
    return max_val


@njit(**_JIT)
def _pairwise_sum(a, lo, n):
    """NumPy's pairwise summation of ``a[lo:lo + n]`` (float32 or float64, summed in that type) as
    ``np.add.reduce`` does it (its
    ``pairwise_sum``: blocks of at most 128 added by ``_block_sum``, longer runs halved at a multiple of 8 and
    the halves' sums added), walked with an explicit stack: numba's on-disk cache does not keep recursive
    functions (a cached recursive version crashed)."""
    if n <= 128:
        return _block_sum(a, lo, n)
    f_lo, f_n = np.empty(64, np.int64), np.empty(64, np.int64)
    f_left, f_stage = np.empty(64, a.dtype), np.empty(64, np.int64)
    f_lo[0], f_n[0], f_stage[0] = lo, n, 0
    top = 1
    val = f_left[0]                               # (its type; always set by a block before it is read)
    while True:
        f = top - 1
        half = f_n[f] // 2
        half -= half % 8
        if f_stage[f] == 0:                       # first the left half
            f_stage[f] = 1
            c_lo, c_n = f_lo[f], half
        elif f_stage[f] == 1:                     # the left half's sum is in val: then the right half
            f_left[f] = val
            f_stage[f] = 2
            c_lo, c_n = f_lo[f] + half, f_n[f] - half
        else:                                     # the right half's sum is in val: this run's sum
            val = f_left[f] + val
            top -= 1
            if top == 0:
                return val
            continue
        if c_n <= 128:
            val = _block_sum(a, c_lo, c_n)
        else:
            f_lo[top], f_n[top], f_stage[top] = c_lo, c_n, 0
            top += 1


@njit(**_JIT)
def _block_sum(a, lo, n):
    """NumPy's sum of a run of at most 128 (in ``a``'s float type): in order from zero below 8, else eight running
    sums combined as ``((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))`` and the rest added in order."""
    if n < 8:
        res = np.zeros(1, a.dtype)[0]
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    while i < n - (n % 8):
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res
