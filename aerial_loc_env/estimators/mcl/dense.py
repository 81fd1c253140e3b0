"""Dense template similarities as MCL measurement models: SSD, NCC and mutual information (Choi & Park,
Tables 6 and 9: the "standard" comparison models of the shadow-aware model).

Each model compares the camera image, reduced to ``patch_width_px x patch_height_px`` gray levels, with the
database patch reconstructed at every particle's pose (``estimators.patches``: sampled and scored in one
compiled pass over the particles, cv2.remap's bilinear samples). The similarity ``xi`` is 1 for identical images
and lower otherwise:

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

from aerial_loc_env import portable
from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.measurement import MeasurementModel, register_model
from aerial_loc_env.estimators.patches import HISTOGRAM, MOMENTS, PatchGeometry, PatchSampler, reduce_image, to_gray
from aerial_loc_env.estimators.protocol import parse_observation


# ---------------------------------------------------------------------- per-frame pieces
def quantize(values: np.ndarray, bins: int, lo: float = 0.0, hi: float = 256.0) -> np.ndarray:
    """Bin indices (int32, same shape) of ``values`` in ``bins`` equal bins over [lo, hi): the float32 product
    ``(v - lo) (bins / (hi - lo))`` truncated and clipped (the kernel quantizes the particles' samples alike)."""
    q = ((np.asarray(values, dtype=np.float32) - lo) * (bins / (hi - lo))).astype(np.int32)
    return np.clip(q, 0, bins - 1, out=q)


def _entropy_rows(p: np.ndarray) -> np.ndarray:
    """Shannon entropy (nats) of each row of probabilities ``p`` (N, M)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        logs = np.where(p > 0, portable.log(np.where(p > 0, p, 1.0)), 0.0)
    return -(p * logs).sum(axis=1)


def entropy(values: np.ndarray, bins: int = 16, lo: float = 0.0, hi: float = 256.0) -> float:
    """Entropy (nats) of the gray-level histogram of ``values`` with ``bins`` bins over [lo, hi)."""
    q = quantize(np.ravel(values), bins, lo, hi)
    hist = np.bincount(q, minlength=bins).astype(np.float64)[None] / q.size
    return float(_entropy_rows(hist)[0])


@functools.lru_cache(maxsize=8)
def nlogn_table(k: int) -> np.ndarray:
    """``c log c`` (float64) for the counts c = 0..k (0 log 0 = 0): entropies from integer counts,
    ``H = log K - sum_c c log c / K``."""
    c = np.arange(k + 1, dtype=np.float64)
    out = np.zeros(k + 1)
    out[1:] = c[1:] * portable.log(c[1:])
    return out


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

    def _score(self, prepared: DensePrepared, states: np.ndarray, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Similarities (N,) of the particles whose view is valid, and that validity (N,) bool."""
        raise NotImplementedError

    def log_likelihood(self, prepared: DensePrepared, states: np.ndarray, altitude_m: float) -> np.ndarray:
        if self.sampler is None:
            raise ConfigError(f"{type(self).__name__}: call reset(briefing, rng) before log_likelihood()")
        xi, valid = self._score(prepared, states, altitude_m)
        xi = np.where(valid, xi, self.worst_xi)
        self.last_stats = {"valid": int(valid.sum()), "xi_max": float(xi.max()) if xi.size else float("nan")}
        return -np.square(1.0 - xi) / (2.0 * self.config.sigma ** 2)

    def _moments(self, prepared: DensePrepared, states: np.ndarray, altitude_m: float
                 ) -> tuple[np.ndarray, np.ndarray]:
        """The kernel's (sum d, sum d^2, sum (p - r)^2, sum d r) per particle, ``d = p - mean(ref)``, and the
        validity (footprint inside, no NaN sample)."""
        g = self.sampler.geometry
        shift = float(prepared.ref.mean(dtype=np.float64))
        stats, valid = self.sampler.score(states, altitude_m, MOMENTS, shift=shift,
                                          ref=prepared.ref.reshape(g.height_px, g.width_px))
        valid &= ~np.isnan(stats[:, 0])
        return stats, valid


class SSDModel(DenseModel):
    """Sum of squared differences: ``xi = 1 - RMS / 255``. Fast; fooled by shadows (Choi & Park, V.B)."""

    def _score(self, prepared: DensePrepared, states: np.ndarray, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
        stats, valid = self._moments(prepared, states, altitude_m)
        msd = np.maximum(np.where(valid, stats[:, 2], 0.0), 0.0) / prepared.ref.size
        return 1.0 - np.sqrt(msd) / 255.0, valid


class NCCModel(DenseModel):
    """Normalized cross-correlation: gain/offset invariant, ``xi`` in [-1, 1]. A constant camera frame or view
    has no defined correlation: it scores 0 (no evidence either way)."""

    worst_xi: ClassVar[float] = -1.0

    def _prepare_ref(self, ref: np.ndarray) -> tuple[float, float]:
        """The reference's sum and centred sum of squares (float64)."""
        r = ref.astype(np.float64)
        rc = r - r.mean()
        return float(r.sum()), portable.matmul(rc.reshape(-1), rc.reshape(-1))

    def _score(self, prepared: DensePrepared, states: np.ndarray, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
        stats, valid = self._moments(prepared, states, altitude_m)
        r_sum, r_css = prepared.extra
        k = prepared.ref.size
        s = np.where(valid[:, None], stats, 0.0)
        d_sum, d_sq, d_ref = s[:, 0], s[:, 1], s[:, 3]
        var = np.maximum(d_sq - d_sum * d_sum / k, 0.0)                     # sum (p - mean p)^2
        cov = d_ref - d_sum * r_sum / k                                      # sum (p - mean p)(r - mean r)
        ok = (var > 1e-6 * k) & (r_css >= 1e-18)
        xi = np.zeros(len(states))
        xi[ok] = cov[ok] / np.sqrt(var[ok] * r_css)
        return np.clip(xi, -1.0, 1.0), valid


class MIModel(DenseModel):
    """Mutual information normalized by the camera entropy: ``xi = MI / H(I)`` in [0, 1]. Each particle's joint
    histogram of ``bins`` gray levels is counted in integers in the kernel; the entropies come from the counts
    through a ``c log c`` table: ``MI = H_p + H_r - H_joint``, ``H = log K - sum_c c log c / K``."""

    def _prepare_ref(self, ref: np.ndarray) -> tuple[float, np.ndarray]:
        """The camera's entropy and its bins (once per frame)."""
        return entropy(ref, self.config.bins), quantize(ref, self.config.bins)

    def _score(self, prepared: DensePrepared, states: np.ndarray, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
        h_ref, ref_bins = prepared.extra
        bins, k = self.config.bins, prepared.ref.size
        g = self.sampler.geometry
        table = nlogn_table(k)
        stats, valid = self.sampler.score(states, altitude_m, HISTOGRAM, ref_bins=ref_bins.reshape(
            g.height_px, g.width_px), bins=bins, scale=np.float32(bins / 256.0), nlogn=table)
        valid &= ~np.isnan(stats[:, 0])
        if h_ref <= 1e-12:
            return np.zeros(len(states)), valid         # a uniform camera frame carries no information
        sum_r = float(table[np.bincount(ref_bins, minlength=bins)].sum())
        mi = math.log(k) - (stats[:, 1] + sum_r - stats[:, 0]) / k
        return np.where(valid, mi, 0.0) / h_ref, valid


register_model("ssd", SSDModel)
register_model("ncc", NCCModel, sigma=0.2)
register_model("mi", MIModel)
