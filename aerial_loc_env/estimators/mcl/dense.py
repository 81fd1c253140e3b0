"""Dense template similarities as MCL measurement models: SSD, NCC and mutual information (Choi & Park,
Tables 6 and 9: the "standard" comparison models of the shadow-aware model).

Each model compares the camera image, reduced to ``patch_width_px x patch_height_px`` gray levels, with the
database patch reconstructed at every particle's pose (``estimators.patches``: one ``cv2.remap`` for all
particles). The similarity ``xi`` is 1 for identical images and lower otherwise:

- SSD: ``xi = 1 - RMS(I - I_hat) / 255``;
- NCC: ``xi = ncc(I, I_hat)`` in [-1, 1] (invariant to gain and offset);
- MI:  ``xi = MI(I, I_hat) / H(I)`` in [0, 1] (joint histogram of ``bins`` quantized gray levels; MI of an
  image with itself is its entropy ``H(I)``).

The likelihood is the paper's eq. (5) applied to every similarity alike, ``xi ~ N(1, sigma)``:
``log p(z | x) = -(1 - xi)^2 / (2 sigma^2)``, so that the models differ only in their similarity. Particles
whose footprint leaves the map or touches no-data get the model's worst similarity.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, NamedTuple

import numpy as np

from ...config import rng
from ...errors import ConfigError
from ..patches import PatchGeometry, PatchSampler, reduce_image, to_gray
from ..protocol import parse_observation
from .measurement import MeasurementModel, register_model


# ---------------------------------------------------------------------- vectorized similarities
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


def quantize(values: np.ndarray, bins: int, lo: float = 0.0, hi: float = 256.0) -> np.ndarray:
    """Bin indices (int32, same shape) of ``values`` in ``bins`` equal bins over [lo, hi)."""
    q = ((np.asarray(values, dtype=np.float32) - lo) * (bins / (hi - lo))).astype(np.int32)
    return np.clip(q, 0, bins - 1, out=q)


def _entropy_rows(p: np.ndarray) -> np.ndarray:
    """Shannon entropy (nats) of each row of probabilities ``p`` (N, M)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        logs = np.where(p > 0, np.log(np.where(p > 0, p, 1.0)), 0.0)
    return -(p * logs).sum(axis=1)


def entropy(values: np.ndarray, bins: int = 16, lo: float = 0.0, hi: float = 256.0) -> float:
    """Entropy (nats) of the gray-level histogram of ``values`` with ``bins`` bins over [lo, hi)."""
    q = quantize(np.ravel(values), bins, lo, hi)
    hist = np.bincount(q, minlength=bins).astype(np.float64)[None] / q.size
    return float(_entropy_rows(hist)[0])


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
    table = _nlogn_table(k)
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


@functools.lru_cache(maxsize=8)
def _nlogn_table(k: int) -> np.ndarray:
    """``c log c`` (float64) for the counts c = 0..k (0 log 0 = 0)."""
    c = np.arange(k + 1, dtype=np.float64)
    out = np.zeros(k + 1)
    out[1:] = c[1:] * np.log(c[1:])
    return out


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


# ---------------------------------------------------------------------- models
@dataclass(frozen=True)
class DenseConfig:
    """Reduced resolution of the comparison and the spread of eq. (5); ``bins`` is used by MI only."""

    patch_width_px: int = field(default=60, metadata=rng(2, 1000, doc="samples across the frame"))
    patch_height_px: int = field(default=40, metadata=rng(2, 1000, doc="samples along the frame"))
    sigma: float = field(default=0.1, metadata=rng(0.0, 10.0, lo_open=True, doc="std of xi in eq. (5)"))
    bins: int = field(default=16, metadata=rng(2, 256, doc="MI gray-level bins"))


class DensePrepared(NamedTuple):
    ref: np.ndarray          # (K,) float32 reduced camera gray levels
    extra: Any               # model-specific per-frame data


class DenseModel(MeasurementModel):
    """Common frame of the dense models: reduce the camera image, sample the patches, score ``xi``."""

    Config: ClassVar[type] = DenseConfig
    #: the similarity given to particles whose footprint leaves the map or touches no-data
    worst_xi: ClassVar[float] = 0.0

    def __init__(self, config: DenseConfig | None = None) -> None:
        super().__init__(config or DenseConfig())
        self.sampler: PatchSampler | None = None

    def reset(self, briefing, rng: np.random.Generator) -> None:
        cfg = self.config
        m = briefing.orthomap
        geometry = PatchGeometry(cfg.patch_width_px, cfg.patch_height_px)
        self.sampler = PatchSampler(m, briefing.camera, geometry, to_gray(m.rgb), briefing.altitude_m,
                                    nodata=m.nodata)

    def prepare(self, observation: Mapping[str, np.ndarray], rng: np.random.Generator,
                info: Mapping[str, Any] | None = None) -> DensePrepared:
        if self.sampler is None:
            raise ConfigError(f"{type(self).__name__}: call reset(briefing, rng) before prepare()")
        obs = parse_observation(observation)
        cam = self.sampler.camera
        if obs.image.shape[:2] != (cam.height_px, cam.width_px):
            raise ConfigError(f"{type(self).__name__}: observation image {obs.image.shape[:2]} differs from the "
                              f"briefing's camera ({cam.height_px}, {cam.width_px})")
        g = self.sampler.geometry
        ref = reduce_image(to_gray(obs.image), g.width_px, g.height_px).ravel()
        return DensePrepared(ref, self._prepare_ref(ref))

    def _prepare_ref(self, ref: np.ndarray) -> Any:
        return None

    def similarity(self, prepared: DensePrepared, patches: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def log_likelihood(self, prepared: DensePrepared, states: np.ndarray, altitude_m: float) -> np.ndarray:
        if self.sampler is None:
            raise ConfigError(f"{type(self).__name__}: call reset(briefing, rng) before log_likelihood()")
        n = len(states)
        xi = np.empty(n)
        n_valid = 0
        # scored a chunk of particles at a time, while its samples are in the cache (the same xi per particle)
        for part, patches, valid in self.sampler.sample_chunks(states, altitude_m):
            flat = patches.reshape(len(patches), -1)
            if not valid.all():
                flat[~valid] = 0.0                      # NaN-free input; these rows get worst_xi below
            xi[part] = np.where(valid, self.similarity(prepared, flat), self.worst_xi)
            n_valid += int(valid.sum())
        self.last_stats = {"valid": n_valid, "xi_max": float(xi.max()) if xi.size else float("nan")}
        return -np.square(1.0 - xi) / (2.0 * self.config.sigma ** 2)


class SSDModel(DenseModel):
    """Sum of squared differences: ``xi = 1 - RMS / 255``. Fast; fooled by shadows (Choi & Park, V.B)."""

    def similarity(self, prepared: DensePrepared, patches: np.ndarray) -> np.ndarray:
        return 1.0 - np.sqrt(msd(patches, prepared.ref)) / 255.0


class NCCModel(DenseModel):
    """Normalized cross-correlation: gain/offset invariant, ``xi`` in [-1, 1]."""

    worst_xi: ClassVar[float] = -1.0

    def _prepare_ref(self, ref: np.ndarray) -> np.ndarray | None:
        return unit_ref(ref)

    def similarity(self, prepared: DensePrepared, patches: np.ndarray) -> np.ndarray:
        return ncc_unit(patches, prepared.extra)


class MIModel(DenseModel):
    """Mutual information normalized by the camera entropy: ``xi = MI / H(I)`` in [0, 1]."""

    def __init__(self, config: DenseConfig | None = None) -> None:
        super().__init__(config)
        self._ref_bins: tuple[np.ndarray, np.ndarray] | None = None   # (the frame's ref, its bins)

    def _prepare_ref(self, ref: np.ndarray) -> float:
        return entropy(ref, self.config.bins)

    def similarity(self, prepared: DensePrepared, patches: np.ndarray) -> np.ndarray:
        h_ref = prepared.extra
        if h_ref <= 1e-12:
            return np.zeros(len(patches))          # a uniform camera frame carries no information
        if self._ref_bins is None or self._ref_bins[0] is not prepared.ref:   # once per frame, not per chunk
            self._ref_bins = (prepared.ref, quantize(prepared.ref, self.config.bins))
        return mutual_information(patches, prepared.ref, self.config.bins, ref_bins=self._ref_bins[1]) / h_ref


register_model("ssd", SSDModel)
register_model("ncc", NCCModel, sigma=0.2)
register_model("mi", MIModel)
