"""The paper's intensity-pair measurement models: conventional (eq. 2-5), shadow restoration (III.B) and
shadow-aware information allocation (eq. 6-9, Table 3).

Per frame (``prepare``): K random pixel pairs ``p_i = (x_i1, x_i2)`` on the camera image; for each of the c
channels the bit ``tau_ij = [I_j(x_i1) > I_j(x_i2)]`` (eq. 2). Per particle (``log_likelihood``): the pair points
are mapped into the database at the particle's pose by eq. (3) (``CameraModel.project_pixels``, not
re-derived), the database bits ``tau_hat_ij`` computed alike, and the similarity is the XNOR count (eq. 4)

    xi = 1 / (n) * sum_i sum_j XNOR(tau_ij, tau_hat_ij),   n = (number of pairs used) * c.

Shadow handling (``shadow``):

- ``"ignore"``: the conventional model, all K pairs;
- ``"restore"``: shadows detected in the camera image are restored (histogram equalization as in the paper,
  or gain matching) before the camera bits are taken; all K pairs;
- ``"drop"``: the paper's proposal. The ``lc`` pairs with exactly one point in shadow are dropped (pairs with
  both points in shadow are kept: both intensities changed alike), the similarity is taken over the K - lc kept
  pairs (eq. 6), and the activation ``sigma_m(K, lc) = 1 - 1 / (1 + exp(-a (lc - K/2)))`` (eq. 8), with
  ``a = activation_gain / K`` so that it is one curve of the shadowed fraction lc/K whatever K (as the paper
  says of its slope), allocates the frame's importance.

From similarity to likelihood (eq. 5 leaves it open; ``likelihood``):

- ``"binomial"`` (default): treat the n bits as independent, each agreeing with probability p at the true pose
  and 1/2 at an unrelated one. The likelihood of m = n xi agreements is p^m (1 - p)^(n - m), so
  ``log L = kappa * n * xi + const`` with ``kappa = log(p / (1 - p))``. Neighbouring bits are correlated, so
  ``kappa`` is best read as a tempering constant (default 0.5 ~ p = 0.62). A frame with fewer usable bits (many
  dropped pairs) automatically pulls the filter less.
- ``"gaussian"``: the paper's ``xi ~ N(mu, sigma)``: ``log L = -(xi - mu)^2 / (2 sigma^2)``, mu = 1 (ideal match).
- ``"linear"``: eq. (9) literally, ``w = xi * sigma_m``: ``log L = log xi``.

Activation (``activation``, used with ``shadow = "drop"``):

- ``"multiply"``: the paper literally, ``w = L * sigma_m`` (``log L + log sigma_m``). Since lc comes from the
  camera image, sigma_m is the same for every particle and cancels when the weights are normalized: with
  resampling every step, this is exactly the "drop" model without activation;
- ``"temper"``: the variant in which the activation carries information: ``log w = sigma_m * log L``, so a
  heavily shadowed frame (sigma_m -> 0) flattens the weights and moves the filter less;
- ``"none"``: no activation.

Soft allocation (``shadow_pair_weight`` w > 0, an addition): instead of dropping the lc pairs, keep them with
weight w in the similarity and in the binomial n. At the true pose the bits of pairs with one point in shadow
still agree more often than at an unrelated pose (1/2), though less often than unshadowed pairs' bits: a cast
shadow scales intensities by a constant factor and flips only the comparisons of pairs within that factor. So
they carry information, and the binomial model's per-bit weight logit(p) gives w = logit(p_one) / logit(p_none),
p_one and p_none the agreement rates of one-shadowed and unshadowed pairs (``agents/mcl-shadow-weighted.toml``
uses 0.4, measured on the paper scenario).

Why the paper's ordering (shadow-aware < restoration < conventional) need not hold here (the benchmark's tables
say how the models compare now: ``aerial-loc bench table5``, README): (1) the image-only detector takes dark
asphalt and vegetation for shadow, so eq. (6) drops good pairs; (2) even with the true mask the dropped pairs are
informative (above); (3) the literal activation cancels in the normalization, and tempering by it only slows the
filter down. Weighting those pairs (soft allocation) instead of dropping them keeps their information.

Shadow detector (``detector``): ``"image"``, the camera frame alone (III.B); ``"map"`` (an addition), the
ratio of the frame to the shadow-free database at the particles' mean pose once the cloud is tight (the image
detector before); ``"oracle"``, the simulator's mask (ablations).

Points that fall outside the database or on no-data count as half an agreement (no information).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import build_config, rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.database import DatabaseWindow, derived_once
from aerial_loc_env.estimators.mcl.estimate import yaw_cos_sin
from aerial_loc_env.estimators.mcl.intensity_pairs_kernels import (
    bounded_pairs,
    camera_pairs,
    pair_agreements,
    pose_affines,
)
from aerial_loc_env.estimators.mcl.measurement import MeasurementModel, register_model
from aerial_loc_env.estimators.protocol import parse_observation
from aerial_loc_env.estimators.shadow_detection import (
    MapRatioDetectorConfig,
    MapRatioShadowDetector,
    ShadowDetector,
    ShadowDetectorConfig,
    ShadowMask,
    oracle_mask,
    restoration_lut,
)

if TYPE_CHECKING:
    from aerial_loc_env.env.briefing import Briefing

#: the kernel's no-data layer when the map has none
_NO_NODATA = np.zeros(0, np.bool_)
_NO_MASK = np.zeros((0, 0), np.bool_)
#: ITU-R 601 luma weights of cv2.COLOR_RGB2GRAY, for single-channel (c = 1) comparisons
_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


@dataclass(frozen=True)
class IntensityPairsConfig:
    n_pairs: int = field(default=70, metadata=rng(1, 100000, doc="K, random pixel pairs per frame"))
    channels: int = field(default=3, metadata=rng(choices=(1, 3), doc="c: 1 = luma, 3 = RGB"))
    shadow: str = field(default="ignore", metadata=rng(choices=("ignore", "restore", "drop")))
    detector: str = field(default="image", metadata=rng(choices=("image", "map", "oracle"),
                                                         doc="image: the frame alone (the paper); map: frame / "
                                                             "database ratio at the predicted pose; oracle: truth"))
    detector_params: dict = field(default_factory=dict)   # -> ShadowDetectorConfig
    map_detector_params: dict = field(default_factory=dict)   # -> MapRatioDetectorConfig
    restoration: str = field(default="gain", metadata=rng(choices=("equalize", "gain")))
    likelihood: str = field(default="binomial", metadata=rng(choices=("binomial", "gaussian", "linear")))
    kappa: float = field(default=0.5, metadata=rng(0.0, 50.0, lo_open=True, doc="binomial: log-odds per bit"))
    mu: float = field(default=1.0, metadata=rng(0.0, 1.0, doc="gaussian: similarity at the true pose"))
    sigma: float = field(default=0.1, metadata=rng(0.0, 10.0, lo_open=True, doc="gaussian: spread of xi"))
    activation: str = field(default="none", metadata=rng(choices=("none", "multiply", "temper")))
    activation_gain: float = field(default=10.0, metadata=rng(0.0, 1000.0, doc="a = activation_gain / K"))
    shadow_pair_weight: float = field(default=0.0, metadata=rng(0.0, 1.0, doc="drop: weight of the pairs with "
                                                                            "one point in shadow; 0 = drop them"))

    def validate(self, where: str) -> None:
        if self.activation != "none" and self.shadow != "drop":
            raise ConfigError(f"{where}: activation = {self.activation!r} needs shadow = 'drop' (it is a "
                              "function of the dropped pairs lc)")
        if self.detector == "oracle" and self.shadow == "ignore":
            raise ConfigError(f"{where}: detector = 'oracle' is meaningless with shadow = 'ignore'")
        build_config(ShadowDetectorConfig, self.detector_params, where=f"{where}: detector_params")
        build_config(MapRatioDetectorConfig, self.map_detector_params, where=f"{where}: map_detector_params")


def activation(K: int | np.ndarray, lc: int | np.ndarray, a: float | np.ndarray) -> np.ndarray | float:
    """Eq. (8): ``sigma_m(K, lc) = 1 - 1 / (1 + exp(-a (lc - K / 2)))``, in (0, 1), 1/2 at lc = K/2."""
    if isinstance(K, int) and isinstance(lc, int) and isinstance(a, float):   # one frame's: float64 arithmetic
        return float(1.0 - 1.0 / (1.0 + portable.exp(-a * (float(lc) - K / 2.0))))
    z = -np.asarray(a, dtype=np.float64) * (np.asarray(lc, dtype=np.float64) - np.asarray(K) / 2.0)
    out = 1.0 - 1.0 / (1.0 + portable.exp(z))
    return float(out) if np.ndim(out) == 0 else out


def xnor_similarity(cam_bits: np.ndarray, db_bits: np.ndarray, keep: np.ndarray | None = None,
                    valid: np.ndarray | None = None, channels: int | None = None,
                    pair_weights: np.ndarray | None = None) -> np.ndarray:
    """Eq. (4)/(6): fraction of agreeing bits.

    ``cam_bits`` (K, C) bool; ``db_bits`` (N, K, C) bool; ``keep`` (K,) bool selects the pairs used (eq. 6);
    ``valid`` (N, K) bool marks database pairs with data (an invalid pair counts as half an agreement).
    ``channels`` (default C): the first ``channels`` are real, the others padding (ignored).
    ``pair_weights`` (K,) >= 0 weights the pairs (the soft allocation): a weighted fraction of agreements.
    Returns (N,) in [0, 1]; 1/2 when no pair is kept.
    """
    if keep is not None:
        if not keep.any():
            return np.full(db_bits.shape[0], 0.5)
        cam_bits, db_bits = cam_bits[keep], db_bits[:, keep]
        valid = None if valid is None else valid[:, keep]
        pair_weights = None if pair_weights is None else pair_weights[keep]
    c = db_bits.shape[2] if channels is None else channels
    counts = np.count_nonzero(db_bits[..., :c] == cam_bits[None, :, :c], axis=2)
    return similarity_from_counts(counts, counts.sum(axis=1), valid, c, pair_weights)


def similarity_from_counts(counts: np.ndarray, sums: np.ndarray, valid: np.ndarray | None, channels: int,
                           pair_weights: np.ndarray | None = None) -> np.ndarray:
    """Eq. (4)/(6) from the agreeing bits ``counts`` (N, K) of each pair (of ``channels`` bits) and their sums
    (N,): all pairs valid and unweighted, the exact fraction (float64); else an invalid pair (``valid`` (N, K)
    False) counts as half an agreement and ``pair_weights`` (K,) weight the pairs (float32 counts: the sums of
    halves are exact)."""
    n, k = counts.shape
    c = channels
    if valid is None and pair_weights is None:
        return sums / (k * c)
    f = counts.astype(np.float32)
    if valid is not None:
        f = np.where(valid, f, 0.5 * c)
    if pair_weights is None:
        return f.sum(axis=1) / (k * c)
    total_w = float(np.sum(pair_weights))
    if total_w <= 0:
        return np.full(n, 0.5)
    return portable.matmul(f, pair_weights) / (total_w * c)


def _database_words(rgb: np.ndarray, nodata: np.ndarray | None,
                    channels: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The database's luma bytes for c = 1 (None for c = 3: the kernel reads the RGB bytes of the map itself) and
    the flat no-data mask (None when there is none), read-only. Computed once per map layer and shared by every
    model on it (``database.derived_once``): the 12 agents of a Table 5 episode would otherwise convert the same
    map 12 times."""
    return derived_once(rgb, ("intensity-pair words", channels, id(nodata)),
                        lambda: _convert_database(rgb, nodata, channels), (nodata,))


def _convert_database(rgb: np.ndarray, nodata: np.ndarray | None,
                      channels: int) -> tuple[np.ndarray, np.ndarray | None]:
    arr = np.ascontiguousarray(rgb)
    words = cv2.cvtColor(arr, cv2.COLOR_RGB2GRAY).reshape(-1) if channels == 1 else None
    flat_nodata = None if nodata is None or not np.any(nodata) else \
        np.array(nodata, dtype=bool).reshape(-1)
    for a in (words, flat_nodata):
        if a is not None:
            a.flags.writeable = False
    return words, flat_nodata


def pair_pixels(rng: np.random.Generator, width: int, height: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``rng.integers(0, width, n)`` and then ``rng.integers(0, height, n)``: the same numbers and the generator left
    as they leave it. For NumPy's default PCG64 with no 32-bit half kept from an earlier draw, and an even ``n``,
    the values come from ``n`` raw words by NumPy's own arithmetic in one compiled pass (``bounded_pairs``), without
    the two calls' fixed costs; where that pass meets a half NumPy rejects, the generator is set back and NumPy
    draws (tests/estimators/test_intensity_pairs.py compares both over many seeds and sizes)."""
    bitgen = rng.bit_generator
    if type(bitgen) is np.random.PCG64 and n % 2 == 0 and 1 < width < 2 ** 32 and 1 < height < 2 ** 32:
        state = bitgen.state
        if not state["has_uint32"]:
            u, v = np.empty(n, np.int64), np.empty(n, np.int64)
            if bounded_pairs(bitgen.random_raw(n), width, height, u, v):
                return u, v
            bitgen.state = state
    return rng.integers(0, width, n), rng.integers(0, height, n)


@dataclass(frozen=True)
class PreparedPairs:
    """What one frame leaves for all particles."""

    uv: np.ndarray           # (2K, 2) camera pixels: first K = x_i1, last K = x_i2
    cam_bits: np.ndarray     # (K, c) bool
    keep: np.ndarray | None  # (K,) bool for shadow = "drop", else None
    log_scale: float         # multiplies log L (tempering by the activation; 1 otherwise)
    log_offset: float        # added to log L (the literal multiplied activation; 0 otherwise)
    pair_weights: np.ndarray | None = None   # (K,) soft allocation (shadow_pair_weight > 0), else None
    pairs: np.ndarray | None = None          # the indices of the used pairs (``keep``'s), when at hand

    @property
    def n_pairs_used(self) -> float:
        """Effective number of pairs (the binomial likelihood's n / c)."""
        if self.pair_weights is not None:
            w = self.pair_weights if self.keep is None else self.pair_weights[self.keep]
            return float(np.sum(w))
        if self.keep is None:
            return float(self.cam_bits.shape[0])
        return float(self.pairs.size if self.pairs is not None else np.count_nonzero(self.keep))


@dataclass
class _PendingPairs:
    """A frame whose shadow mask waits for the predicted pose (``detector = "map"``)."""

    image: np.ndarray
    u: np.ndarray
    v: np.ndarray
    altitude_m: float
    small: np.ndarray | None = None


class IntensityPairsModel(MeasurementModel):
    """Binary intensity-pair descriptor with XNOR similarity, optionally shadow-restoring or shadow-aware."""

    Config = IntensityPairsConfig

    def __init__(self, config: IntensityPairsConfig | None = None) -> None:
        super().__init__(config or IntensityPairsConfig())
        cfg: IntensityPairsConfig = self.config
        self.uses_ground_truth = cfg.detector == "oracle"
        self.detector = ShadowDetector(build_config(ShadowDetectorConfig, cfg.detector_params,
                                                    where="intensity pairs: detector_params"))
        self.map_detector = MapRatioShadowDetector(build_config(
            MapRatioDetectorConfig, cfg.map_detector_params, where="intensity pairs: map_detector_params"))
        self._db: np.ndarray | None = None
        self._terms: tuple[float, tuple[float, ...]] | None = None

    # ---------------------------------------------------------------- per map
    def reset(self, briefing: Briefing, rng: np.random.Generator) -> None:
        """Keep the database as the bytes the kernel compares: the map's own RGB bytes (a view: no copy, and the
        lines a frame of the same place brought into the cache), or the luma byte per pixel for c = 1. (Not an RGBA
        copy, one 4-byte word a pixel: a third more bytes to keep in the cache, and a slower step.)"""
        m = briefing.orthomap
        self.orthomap, self.camera = m, briefing.camera
        self._terms: tuple[float, tuple[float, ...]] | None = None
        if isinstance(m, DatabaseWindow):   # a window of a map read by window: bytes at the whole map's indices
            self._H, self._W = m.height_px, m.width_px
            self._db, self._nodata = m.pixel_bytes(self.config.channels)
            if self.config.detector == "map" and self.config.shadow != "ignore":
                self.map_detector.reset(briefing)
            return
        rgb = np.asarray(m.rgb)
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ConfigError(f"{m.name}: the database must be (H, W, 3) uint8 RGB, got {rgb.shape} {rgb.dtype}")
        self._H, self._W = rgb.shape[:2]
        words, self._nodata = _database_words(m.rgb, m.nodata, self.config.channels)
        self._db = words if words is not None else np.ascontiguousarray(rgb).reshape(-1)
        if self.config.detector == "map" and self.config.shadow != "ignore":
            self.map_detector.reset(briefing)

    # ---------------------------------------------------------------- per frame
    def prepare(self, observation: Mapping[str, np.ndarray], rng: np.random.Generator,
                info: Mapping[str, Any] | None = None) -> PreparedPairs | _PendingPairs:
        """Draw the K pairs, detect the shadows, take the camera bits. With ``detector = "map"`` the mask needs
        the predicted pose, so the frame is finished by the first ``log_likelihood`` call (which has it)."""
        cfg: IntensityPairsConfig = self.config
        obs = parse_observation(observation)
        img = obs.image
        H, W = img.shape[:2]
        K = cfg.n_pairs
        u, v = pair_pixels(rng, W, H, 2 * K)
        pending = _PendingPairs(img, u, v, obs.altitude_m)
        if cfg.shadow == "ignore":
            return self._finish(pending, None)
        if cfg.detector == "oracle":
            return self._finish(pending, oracle_mask(info, (H, W)))
        if cfg.detector == "map":
            pending.small = self.detector.reduce(img)
            return pending
        pending.small, smask = self.detector.detect_reduced(img)
        return self._finish(pending, smask)

    def _finish(self, p: _PendingPairs, smask: ShadowMask | None) -> PreparedPairs:
        cfg: IntensityPairsConfig = self.config
        img, u, v = p.image, p.u, p.v
        K = cfg.n_pairs
        vals = np.empty((u.size, img.shape[2]), np.float32)                   # (2K, 3) the pixels
        uv = np.empty((u.size, 2))
        in_mask = np.zeros(u.size, np.bool_)                                   # (2K,) in shadow
        cam_bits = np.empty((K, img.shape[2]), np.bool_)                       # (K, 3) eq. (2) on the pixels
        kept = np.empty(K, np.intp)                                            # pairs not split by the mask
        n_kept = camera_pairs(img, u, v, _NO_MASK if smask is None else smask.mask, vals, in_mask, uv, cam_bits,
                              kept)
        mask_pts = None if smask is None else in_mask
        stats: dict[str, Any] = {"K": K, "num_pairs": K}
        if smask is not None:
            stats["shadow_fraction"] = smask.fraction
            if cfg.shadow == "restore" and mask_pts.any():
                small = p.small if p.small is not None else self.detector.reduce(img)
                sm = smask.mask if smask.mask.shape == small.shape[:2] else cv2.resize(
                    smask.mask.astype(np.uint8), small.shape[1::-1], interpolation=cv2.INTER_NEAREST).astype(bool)
                lut = restoration_lut(small, sm, cfg.restoration)              # (3, 256)
                restored = lut[np.arange(3)[None, :], vals.astype(np.int64)]       # (2K, 3)
                vals = np.where(mask_pts[:, None], restored, vals)
                cam_bits = vals[:K] > vals[K:]                                # (the restored pixels' bits)
        if cfg.channels == 1:
            vals = portable.matmul(vals, _LUMA[:, None])
            cam_bits = vals[:K] > vals[K:]                                    # (K, 1) eq. (2)
        keep, log_scale, log_offset, pair_weights, pairs = None, 1.0, 0.0, None, None
        if cfg.shadow == "drop":
            one_in_shadow = mask_pts[:K] ^ mask_pts[K:]
            if cfg.shadow_pair_weight > 0:   # soft allocation: keep them, with less weight
                pair_weights = np.where(one_in_shadow, cfg.shadow_pair_weight, 1.0)
            else:                            # eq. (6): drop them
                keep = ~one_in_shadow
                pairs = kept[:n_kept]
            lc = K - n_kept
            act = activation(K, lc, cfg.activation_gain / K)
            stats.update(shadow_pairs=lc, kept_pairs=K - lc, activation=act)
            if cfg.activation == "multiply":
                log_offset = math.log(max(act, 1e-300))
            elif cfg.activation == "temper":
                log_scale = act
        elif mask_pts is not None:
            stats["shadow_pairs"] = int(np.count_nonzero(mask_pts[:K] ^ mask_pts[K:]))
        self.last_stats = stats
        return PreparedPairs(uv, cam_bits, keep, log_scale, log_offset, pair_weights, pairs)

    def _finish_with_map(self, p: _PendingPairs, states: np.ndarray) -> PreparedPairs:
        """The map-ratio mask at the particles' mean pose when the cloud is tight, else the image-only one."""
        xy = states[:, :2]
        std = float(np.sqrt(np.max(xy.var(axis=0))))
        if std <= self.map_detector.config.max_std_m:
            yaw = math.atan2(np.sin(states[:, 2]).mean(), np.cos(states[:, 2]).mean())
            mx, my = xy.mean(axis=0)
            smask = self.map_detector.detect(p.image, float(mx), float(my), yaw, p.altitude_m, small=p.small)
            source = "map"
        else:
            smask, source = self.detector.detect(p.image, small=p.small), "image"
        prepared = self._finish(p, smask)
        self.last_stats["detector"] = source
        return prepared

    # ---------------------------------------------------------------- per particle (vectorized)
    def _affine_terms(self, altitude_m: float) -> tuple[float, ...]:
        """``CameraModel.affine_terms`` at ``altitude_m``, kept for the last altitude (the same every step)."""
        alt = float(altitude_m)
        if self._terms is None or self._terms[0] != alt:
            self._terms = (alt, self.camera.affine_terms(self.orthomap, alt))
        return self._terms[1]

    def _affine_rows(self, states: np.ndarray, altitude_m: float, offset_px: float) -> np.ndarray:
        """Eq. (3)'s affines (``CameraModel.camera_to_map``'s floats, as ``pair_agreements`` computes them) as
        (2N, 3) float32 rows: every particle's column row first, then every particle's row row, ``offset_px`` added
        to the translations (in float32)."""
        states = np.asarray(states, dtype=np.float64)
        yaw = states[:, 2]
        a = pose_affines(self._affine_terms(altitude_m), states, np.cos(yaw), np.sin(yaw),
                         np.empty((states.shape[0], 2, 3)))
        a2 = a.transpose(1, 0, 2).reshape(2 * a.shape[0], 3).astype(np.float32)
        a2[:, 2] += np.float32(offset_px)
        return a2

    def map_pixels(self, uv: np.ndarray, states: np.ndarray, altitude_m: float,
                   offset_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Map pixel columns and rows (N, P) (plus ``offset_px``) of the camera pixels ``uv`` (P, 2) at every
        particle's pose, float32 (1e-3 px precision on a 10^4 px map): ``(a0 u + a1 v) + a2`` per affine row,
        the arithmetic ``pair_agreements`` does point by point."""
        a2 = self._affine_rows(states, altitude_m, offset_px)
        u, v = (uv[:, i].astype(np.float32)[None] for i in (0, 1))
        pts = (a2[:, :1] * u + a2[:, 1:2] * v) + a2[:, 2:]
        return pts[:a2.shape[0] // 2], pts[a2.shape[0] // 2:]

    def similarity(self, prepared: PreparedPairs | _PendingPairs, states: np.ndarray, altitude_m: float) -> np.ndarray:
        """xi (N,) of eq. (4) (or eq. (6) over the kept pairs) for every particle."""
        if self._db is None:
            raise ConfigError("intensity pairs: call reset(briefing, rng) before scoring particles")
        if isinstance(prepared, _PendingPairs):
            prepared = self._finish_with_map(prepared, states)
        keep = prepared.keep
        pairs = prepared.pairs
        if pairs is None:
            pairs = np.arange(prepared.cam_bits.shape[0]) if keep is None else np.flatnonzero(keep)
        weights = prepared.pair_weights if prepared.pair_weights is None or keep is None else \
            prepared.pair_weights[keep]
        K, c = pairs.size, prepared.cam_bits.shape[1]
        if K == 0:
            return np.full(states.shape[0], 0.5)
        states = np.asarray(states, dtype=np.float64)
        n = states.shape[0]
        counts = np.empty((K, n), np.int8)
        valid = np.empty((K, n), np.bool_)
        nodata = _NO_NODATA if self._nodata is None else self._nodata
        cos, sin = yaw_cos_sin(states)      # camera_to_map's cos and sin: NumPy's, of the same column
        sums, outside = pair_agreements(states, cos, sin, self._affine_terms(altitude_m),
                                        prepared.uv, pairs, self._W, self._H, self._db, c, c, nodata,
                                        prepared.cam_bits, counts, valid)
        if not outside and self._nodata is None and weights is None:
            return sums / (K * c)                                   # every pair valid: the exact fraction
        return similarity_from_counts(np.ascontiguousarray(counts.T), sums,
                                      np.ascontiguousarray(valid.T) if outside or self._nodata is not None else None,
                                      c, weights)

    def log_likelihood(self, prepared: PreparedPairs | _PendingPairs, states: np.ndarray,
                       altitude_m: float) -> np.ndarray:
        cfg: IntensityPairsConfig = self.config
        if isinstance(prepared, _PendingPairs):
            prepared = self._finish_with_map(prepared, states)
        xi = self.similarity(prepared, states, altitude_m)
        n_pairs = prepared.n_pairs_used
        if cfg.likelihood == "binomial":
            log_l = cfg.kappa * (n_pairs * prepared.cam_bits.shape[1]) * xi
        elif cfg.likelihood == "gaussian":
            log_l = -0.5 * ((xi - cfg.mu) / cfg.sigma) ** 2
        else:
            log_l = portable.log(np.maximum(xi, 1e-12))
        if prepared.log_scale != 1.0:       # (1.0 x: the same floats)
            log_l = prepared.log_scale * log_l
        return log_l + prepared.log_offset


register_model("intensity_pairs", IntensityPairsModel)
register_model("intensity_pairs_restoration", IntensityPairsModel, shadow="restore")
register_model("intensity_pairs_shadow_aware", IntensityPairsModel, shadow="drop", activation="multiply")
