"""Today's (before issue 12's kernels) code, kept only as the references the tests compare the compiled kernels
against: similarities of stacked patches (N, K) in NumPy, the patches from one ``cv2.remap`` over float32
coordinate maps ``e00 col + (e01 row + e02)``, and the intensity-pair models' gather and XNOR count."""

from __future__ import annotations

import math

import cv2
import numpy as np

from aerial_loc_env.estimators.mcl.dense import _entropy_rows, nlogn_table, quantize
from aerial_loc_env.estimators.mcl.intensity_pairs import similarity_from_counts


def remap_patches(sampler, states: np.ndarray, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The sampler as it was: coordinate maps for every grid node, one ``cv2.remap`` per channel (OpenCV's
    1-channel float path: exact bilinear weights), validity from the grid corners and the NaNs of the whole
    patch. Patches (N, h, w[, C]) float32 and validity (N,) bool."""
    e = sampler.grid_to_level(states, altitude_m).astype(np.float32)
    n = e.shape[0]
    gh, gw = sampler.geometry.height_px, sampler.geometry.width_px
    cols, rows = np.arange(gw, dtype=np.float32), np.arange(gh, dtype=np.float32)
    mx = (e[:, 0, 0, None] * cols)[:, None, :] + (e[:, 0, 1, None] * rows + e[:, 0, 2, None])[:, :, None]
    my = (e[:, 1, 0, None] * cols)[:, None, :] + (e[:, 1, 1, None] * rows + e[:, 1, 2, None])[:, :, None]
    level = sampler.level if sampler.level.ndim == 3 else sampler.level[..., None]
    # borderValue=nan is the Scalar (nan, 0, 0, 0): outside the level only the first channel is NaN
    res = np.stack([cv2.remap(np.ascontiguousarray(level[..., ch]), mx.reshape(-1, gw), my.reshape(-1, gw),
                              cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                              borderValue=float("nan") if ch == 0 else 0.0)
                    for ch in range(level.shape[2])], axis=-1)
    out = res.reshape((n, gh, gw) + sampler.level.shape[2:])
    lw, lh = sampler.level_size
    cu = np.stack([mx[:, 0, 0], mx[:, 0, -1], mx[:, -1, 0], mx[:, -1, -1]], axis=1)
    cv = np.stack([my[:, 0, 0], my[:, 0, -1], my[:, -1, 0], my[:, -1, -1]], axis=1)
    valid = (cu.min(1) >= 0) & (cu.max(1) <= lw - 1) & (cv.min(1) >= 0) & (cv.max(1) <= lh - 1)
    if sampler.has_nan:
        valid &= ~np.isnan(out.reshape(n, -1)).any(axis=1)
    return out, valid


def msd(patches: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Mean squared difference (N,) between each row of ``patches`` (N, K) and ``ref`` (K,)."""
    p = np.asarray(patches, dtype=np.float32)
    r = np.asarray(ref, dtype=np.float32)
    k = r.size
    # sum (p - r)^2 = sum p^2 - 2 p.r + sum r^2 without an (N, K) temporary; einsum, not BLAS (one core)
    s = (np.einsum("nk,nk->n", p, p).astype(np.float64)
         - 2.0 * np.einsum("nk,k->n", p, r).astype(np.float64) + float(r @ r))
    return np.maximum(s, 0.0) / k


def ncc(patches: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Normalized cross-correlation (N,) in [-1, 1] of each row of ``patches`` (N, K) with ``ref`` (K,).

    A constant row or a constant ``ref`` has no defined correlation; it scores 0 (no evidence either way).
    """
    return ncc_unit(patches, unit_ref(ref))


def unit_ref(ref: np.ndarray) -> np.ndarray | None:
    """``ref`` centred and scaled to unit norm (float32), or None for a constant ``ref``: the part of ``ncc``
    that depends on the frame only (computed once per frame, not once per chunk of particles)."""
    r = np.asarray(ref, dtype=np.float64)
    rc = r - r.mean()
    rn = float(np.sqrt(rc @ rc))
    return None if rn < 1e-9 else (rc / rn).astype(np.float32)


def ncc_unit(patches: np.ndarray, unit: np.ndarray | None) -> np.ndarray:
    """``ncc`` of the rows of ``patches`` (N, K) with a reference already made ``unit_ref``."""
    p = np.asarray(patches, dtype=np.float32)
    if unit is None:
        return np.zeros(p.shape[0])
    k = unit.size
    dot = np.einsum("nk,k->n", p, unit).astype(np.float64)           # p . r~ (no BLAS threads)
    s1 = p.sum(axis=1).astype(np.float64)
    s2 = np.einsum("nk,nk->n", p, p).astype(np.float64)
    var = np.maximum(s2 - s1 * s1 / k, 0.0)                           # sum (p - mean p)^2
    out = np.zeros(p.shape[0])
    ok = var > 1e-6 * k
    out[ok] = dot[ok] / np.sqrt(var[ok])
    return np.clip(out, -1.0, 1.0)


def mutual_information(patches: np.ndarray, ref: np.ndarray, bins: int = 16, lo: float = 0.0,
                       hi: float = 256.0, *, ref_bins: np.ndarray | None = None) -> np.ndarray:
    """Mutual information (N,) in nats between each row of ``patches`` (N, K) and ``ref`` (K,).

    One ``np.bincount`` over all rows: the joint bin of sample k of row n is ``n B^2 + B q(p_nk) + q(r_k)``,
    built in uint8 while ``B^2 <= 256`` (16 bins: one byte per sample until the row offset is added). The
    entropies come from the integer counts c through a table of ``c log c``:
    ``H = log K - sum_c c log c / K`` (no (N, B^2) float64 probabilities and logs). ``ref_bins``:
    ``quantize(ref, bins, lo, hi)`` when the caller already has it (once per frame, not per chunk of rows).
    """
    p = np.asarray(patches)
    n, k = p.shape
    qr = quantize(ref, bins, lo, hi) if ref_bins is None else ref_bins
    offsets = np.arange(n, dtype=np.intp)[:, None] * (bins * bins)
    if bins * bins <= 256:
        q = _quantize_u8(p, bins, lo, hi)
        q *= np.uint8(bins)
        q += qr.astype(np.uint8)
        idx = q + offsets                               # the intp copy np.bincount would make anyway
    else:
        idx = quantize(p, bins, lo, hi).astype(np.intp)
        idx *= bins
        idx += qr
        idx += offsets
    counts = np.bincount(idx.ravel(), minlength=n * bins * bins).reshape(n, bins, bins)
    table = nlogn_table(k)
    log_k = math.log(k)
    sum_joint = table[counts].sum(axis=(1, 2))
    sum_p = table[counts.sum(axis=2)].sum(axis=1)
    sum_r = float(table[np.bincount(qr, minlength=bins)].sum())
    # MI = H_p + H_r - H_joint with H = log K - sum c log c / K
    return (log_k - (sum_p + sum_r - sum_joint) / k).astype(np.float64)


def _quantize_u8(values: np.ndarray, bins: int, lo: float, hi: float) -> np.ndarray:
    """``quantize`` as uint8 (bins <= 256): the same float32 product, clipped before the cast (equal for finite
    values: truncation and clipping to [0, bins - 1] commute)."""
    v = np.asarray(values, dtype=np.float32)
    t = np.multiply(v - np.float32(lo) if lo != 0.0 else v, np.float32(bins / (hi - lo)))
    np.clip(t, 0, bins - 1, out=t)
    return t.astype(np.uint8)


def mutual_information_reference(patches: np.ndarray, ref: np.ndarray, bins: int = 16, lo: float = 0.0,
                                 hi: float = 256.0) -> np.ndarray:
    """The direct form (normalized joint histogram, entropies of probabilities): the tests' reference."""
    p = np.asarray(patches)
    n, k = p.shape
    qr = quantize(ref, bins, lo, hi)
    idx = quantize(p, bins, lo, hi).astype(np.int64) * bins + qr + (np.arange(n) * (bins * bins))[:, None]
    joint = np.bincount(idx.ravel(), minlength=n * bins * bins).reshape(n, bins, bins) / float(k)
    h_p = _entropy_rows(joint.sum(axis=2))
    h_r = _entropy_rows(joint[:1].sum(axis=1))[0]
    h_joint = _entropy_rows(joint.reshape(n, bins * bins))
    return h_p + h_r - h_joint


def xnor_similarity_reference(cam_bits: np.ndarray, db_bits: np.ndarray, valid: np.ndarray | None,
                              channels: int, pair_weights: np.ndarray | None) -> np.ndarray:
    """Eq. (4)/(6) as it was counted: ``db_bits`` (N, K, C) against ``cam_bits`` (K, C) over the first
    ``channels`` (the others padding that agrees: the alpha byte of a packed RGBA word), SWAR counts; an invalid
    pair (``valid`` (N, K) False) half an agreement; ``pair_weights`` (K,) the soft allocation."""
    n, k, c_all = db_bits.shape
    c = c_all if channels is None else channels
    if valid is None and pair_weights is None:
        return (k * c - _count_disagreements(db_bits, cam_bits, c)) / (k * c)
    counts = _count_channels(db_bits == cam_bits[None]) - (c_all - c)         # (N, K) agreements of c
    # the half agreements and the weights as they were applied (unchanged: the library's tail)
    return similarity_from_counts(counts, counts.sum(axis=1), valid, c, pair_weights)


def _count_disagreements(db_bits: np.ndarray, cam_bits: np.ndarray, c: int) -> np.ndarray:
    """Disagreeing bits (N,) int64 of the first ``c`` channels of ``db_bits`` (N, K, C) against ``cam_bits``
    (K, C): an exact integer count, so the similarity is the same float whichever way it is counted.

    For C = 4 (packed RGBA words) and K < 256 the K words of a particle are added as uint32: each byte then
    holds the count of one channel (at most K, no carry between bytes), read back byte by byte. Half the
    time of a uint8 reduction over the (N, 4K) bytes. Padding channels (beyond ``c``) agree by construction."""
    n, k, c_all = db_bits.shape
    dis = np.not_equal(db_bits, cam_bits[None])
    if c_all == 4 and k < 256 and dis.flags.c_contiguous:
        per_byte = dis.view(np.uint32).reshape(n, k).sum(axis=1, dtype=np.uint32)
        total = (per_byte & np.uint32(0xFF)).astype(np.int64)
        for shift in (8, 16, 24):     # all four bytes (padding bytes agree): no byte-order assumption
            total += (per_byte >> np.uint32(shift)) & np.uint32(0xFF)
        return total
    return np.count_nonzero(dis[..., :c].reshape(n, k * c), axis=1).astype(np.int64)


def _count_channels(agree: np.ndarray) -> np.ndarray:
    """Sum of a bool (N, K, C) array over its last axis as float32 (N, K). For C = 4 the four bytes of each
    pair are read as one uint32 and added by a multiply (SWAR): 10x faster than a reduce over a length-4 axis."""
    if agree.shape[2] == 4 and agree.flags.c_contiguous:
        word = agree.view(np.uint32)[..., 0]
        return ((word * np.uint32(0x01010101)) >> np.uint32(24)).astype(np.float32)
    return agree.sum(axis=2, dtype=np.float32)


def pair_similarity_reference(model, prepared, states: np.ndarray, altitude_m: float) -> np.ndarray:
    """``IntensityPairsModel.similarity`` as it was: the pair points through one float32 ``einsum``, clipped
    and truncated to (N, 2K) int32 indices, one gather of the packed words, the bytes compared, the XNOR count
    (SWAR on the RGBA words)."""
    cam_bits = prepared.cam_bits if prepared.keep is None else prepared.cam_bits[prepared.keep]
    weights = prepared.pair_weights
    if weights is not None and prepared.keep is not None:
        weights = weights[prepared.keep]
    K, c = cam_bits.shape
    if K == 0:
        return np.full(states.shape[0], 0.5)
    uv = prepared.uv if prepared.keep is None else prepared.uv[np.concatenate([prepared.keep] * 2)]
    a = model.camera.camera_to_map(model.orthomap, states[:, 0], states[:, 1], states[:, 2], altitude_m)
    n = a.shape[0]
    a2 = a.transpose(1, 0, 2).reshape(2 * n, 3).astype(np.float32)
    a2[:, 2] += np.float32(0.5)
    uvh = np.ones((3, uv.shape[0]), np.float32)
    uvh[:2] = uv.T
    pts = np.einsum("nk,kp->np", a2, uvh)
    col, row = pts[:n], pts[n:]
    W, H = model._W, model._H
    inside = None
    if col.min() < 0 or row.min() < 0 or col.max() >= W or row.max() >= H:
        inside = (col >= 0) & (col < W) & (row >= 0) & (row < H)
        np.clip(col, 0, W - 1, out=col)
        np.clip(row, 0, H - 1, out=row)
    flat = row.astype(np.int32)
    flat *= np.int32(W)
    flat += col.astype(np.int32)
    if c == 3:                          # the database as it was: RGB packed in a uint32 (RGBA) per pixel
        words = cv2.cvtColor(np.ascontiguousarray(model.orthomap.rgb), cv2.COLOR_RGB2RGBA).reshape(-1).view(np.uint32)
    else:
        words = model._db
    db = words[flat]
    if c == 3:
        db8 = db.view(np.uint8).reshape(db.shape[0], 2 * K, 4)
        db_bits = db8[:, :K] > db8[:, K:]
        cam_bits = np.concatenate([cam_bits, np.zeros((K, 1), bool)], axis=1)
    else:
        db_bits = (db[:, :K] > db[:, K:])[..., None]
    valid = inside
    if model._nodata is not None:
        ok = ~model._nodata[flat]
        valid = ok if valid is None else valid & ok
    valid_pairs = None if valid is None else valid[:, :K] & valid[:, K:]
    return xnor_similarity_reference(cam_bits, db_bits, valid_pairs, c, weights)
