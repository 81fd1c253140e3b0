"""Today's (before issue 12's kernels) dense similarity code and patch sampler, kept only as the references the
tests compare the compiled kernels against: similarities of stacked patches (N, K) in NumPy, and the patches
from one ``cv2.remap`` over float32 coordinate maps ``e00 col + (e01 row + e02)``."""

from __future__ import annotations

import math

import cv2
import numpy as np

from aerial_loc_env.estimators.mcl.dense import _entropy_rows, nlogn_table, quantize


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


