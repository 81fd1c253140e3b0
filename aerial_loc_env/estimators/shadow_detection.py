"""Shadow detection from the camera image alone, shadow restoration, and detector quality (III.B of the paper).

Detector: a per-pixel shadow index on a reduced copy of the frame, an Otsu threshold, morphology:

- ``"c3_luminance"`` (default): the mean of the colour-invariant ``c3 = arctan(B / max(R, G))`` (Gevers &
  Smeulders; shadows are lit by the bluish sky only, so their ``c3`` rises) scaled to [0, 1] and the darkness
  ``1 - L / 255`` (shadows are dark);
- ``"c3"``: the colour invariant alone; ``"luminance"``: the darkness alone;
- ``"tsai"``: Tsai's (2006) ratio ``(H + 1) / (I + 1)`` of hue and intensity (HSV) scaled to [0, 1].

Otsu always splits an image in two, so a frame without shadows would still get a "shadow" class; the split is
kept only if the shadow class is clearly darker than the rest (mean luminance ratio ``<= max_luminance_ratio``)
and, for the c3 indices, bluer (mean normalized c3 higher by ``>= min_blue_shift``): sky light is blue, so a
dark but neutral or green region (asphalt, trees) is not taken for a shadow.
Small specks are removed by an opening, holes closed by a closing (kernels in reduced pixels).

Restoration maps shadow pixels by a per-channel look-up table (so it costs nothing per sample point):
``"equalize"`` (the paper: histogram equalization of the shadow region; known to over-restore) and ``"gain"``
(better: multiply each channel by the ratio of the lit to the shadow mean, the inverse of the multiplicative
darkening of a cast shadow).

The ``oracle`` detector reads the simulator's ground-truth mask from ``info["shadow_mask"]``, for ablations
only. ``mask_quality`` scores a detected mask against the ground truth (IoU, precision, recall).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.database import DatabaseWindow
from aerial_loc_env.estimators.shadow_detection_kernels import (
    _classify,
    _index8,
    _open_close,
    _quarter,
    _reduce_index8,
    _split_figures,
)

INDICES = ("c3_luminance", "c3", "luminance", "tsai")
RESTORATIONS = ("equalize", "gain")
INFO_KEY = "shadow_mask"


@dataclass(frozen=True)
class ShadowDetectorConfig:
    index: str = field(default="c3_luminance", metadata=rng(choices=INDICES, doc="per-pixel shadow index"))
    scale: float = field(default=0.25, metadata=rng(0.02, 1.0, doc="working resolution / frame resolution"))
    open_px: int = field(default=1, metadata=rng(0, 50, doc="opening radius (reduced px), removes specks"))
    close_px: int = field(default=1, metadata=rng(0, 50, doc="closing radius (reduced px), fills holes"))
    max_luminance_ratio: float = field(default=0.8, metadata=rng(0.0, 1.0, doc="shadow/lit mean luminance "
                                                                                  "above which: no shadow"))
    min_blue_shift: float = field(default=0.01, metadata=rng(-1.0, 1.0, doc="c3 indices: shadow minus lit mean "
                                                                             "c3 below which: no shadow"))


@dataclass(frozen=True)
class ShadowMask:
    """A shadow mask at a reduced resolution, with lookups in full-frame pixel coordinates."""

    mask: np.ndarray                 # (h, w) bool, True = shadow
    frame_shape: tuple[int, int]     # (H, W) of the camera frame

    def at(self, u_px: np.ndarray, v_px: np.ndarray) -> np.ndarray:
        """Mask values at integer frame pixels (any shape)."""
        h, w = self.mask.shape
        H, W = self.frame_shape
        i = np.minimum((np.asarray(v_px) * h) // H, h - 1)
        j = np.minimum((np.asarray(u_px) * w) // W, w - 1)
        return self.mask[i, j]

    def full(self) -> np.ndarray:
        """The mask at the frame's resolution (nearest neighbour)."""
        H, W = self.frame_shape
        if self.mask.shape == (H, W):
            return self.mask
        return cv2.resize(self.mask.astype(np.uint8), (W, H), interpolation=cv2.INTER_NEAREST).astype(bool)

    @property
    def fraction(self) -> float:
        return np.count_nonzero(self.mask) / self.mask.size     # = float(mask.mean()): exact count / size


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _runs(radius: int) -> np.ndarray:
    """The disc of ``radius`` (``_disc``; anchored at its centre, as ``cv2.morphologyEx`` anchors it) as its rows'
    runs (R, 3) int64: row offset, first and last column offset; (0, 3) for radius 0 (no pass)."""
    if radius <= 0:
        return np.zeros((0, 3), np.int64)
    se = _disc(radius)
    runs = []
    for i, row in enumerate(se):
        cols = np.flatnonzero(row)
        if cols.size and cols[-1] - cols[0] + 1 != cols.size:      # never for an ellipse: one run a row
            raise ValueError(f"structuring element row {i} is not one run: {row}")
        if cols.size:
            runs.append((i - radius, cols[0] - radius, cols[-1] - radius))
    return np.array(runs, np.int64)


class _OpenClose:
    """An opening by the disc of ``open_px`` then a closing by that of ``close_px`` (reduced pixels; 0 skips
    one) of a 0/1 mask, as a bool mask: ``cv2.morphologyEx``'s results (the borders never count: its default
    border value) from one compiled call (``_open_close``) instead of two OpenCV calls and a conversion, each of
    whose fixed costs exceeded the work on a 150 x 100 mask (tests compare both)."""

    def __init__(self, open_px: int, close_px: int) -> None:
        self.open_runs, self.close_runs = _runs(open_px), _runs(close_px)

    def __call__(self, binary: np.ndarray) -> np.ndarray:
        return _open_close(binary, self.open_runs, self.close_runs).view(np.bool_)


def c3_invariant(rgb: np.ndarray) -> np.ndarray:
    """``arctan(B / max(R, G))`` scaled to [0, 1] (float32)."""
    f = rgb.astype(np.float32)
    c3 = portable.arctan2(f[..., 2], np.maximum(np.maximum(f[..., 0], f[..., 1]), np.float32(1.0)))
    return c3 * np.float32(2.0 / np.pi)


def shadow_index(small_rgb: np.ndarray, index: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(index in [0, 1], luminance in [0, 255], c3 or None) as float32 images of an RGB uint8 image."""
    lum = cv2.cvtColor(small_rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    if index == "luminance":
        return 1.0 - lum / 255.0, lum, None
    if index == "tsai":
        hsv = cv2.cvtColor(small_rgb, cv2.COLOR_RGB2HSV).astype(np.float32)   # H in [0, 180), V in [0, 255]
        ratio = (hsv[..., 0] / 180.0 * 255.0 + 1.0) / (hsv[..., 2] + 1.0)
        return ratio / (1.0 + ratio), lum, None
    c3 = c3_invariant(small_rgb)
    if index == "c3":
        return c3, lum, c3
    return 0.5 * (c3 + 1.0 - lum / 255.0), lum, c3


class ShadowDetector:
    """Detects shadows in a camera frame (RGB uint8) from the image alone."""

    def __init__(self, config: ShadowDetectorConfig | None = None) -> None:
        self.config = config or ShadowDetectorConfig()
        self._open_close = _OpenClose(self.config.open_px, self.config.close_px)

    def reduce(self, image: np.ndarray) -> np.ndarray:
        s = self.config.scale
        if s >= 1.0:
            return np.ascontiguousarray(image)
        if self._quarters(image):
            return _quarter(image)                   # the default scale: cv2.resize's bytes, without its set-up
        H, W = image.shape[:2]
        # bilinear, not area: much faster, and shadows are large compared with the 1/scale pixels it skips
        return cv2.resize(image, (max(1, round(W * s)), max(1, round(H * s))), interpolation=cv2.INTER_LINEAR)

    def _quarters(self, image: np.ndarray) -> bool:
        """Whether ``reduce`` takes the compiled quarter (the default scale on a contiguous RGB frame whose sides
        are multiples of 4)."""
        H, W = image.shape[:2]
        return self.config.scale == 0.25 and H % 4 == 0 and W % 4 == 0 and image.shape[2:] == (3,) \
            and image.dtype == np.uint8 and image.flags.c_contiguous

    def detect(self, image: np.ndarray, small: np.ndarray | None = None) -> ShadowMask:
        """The shadow mask of ``image``; ``small`` may pass an already reduced copy."""
        return self.detect_reduced(image, small)[1]

    def detect_reduced(self, image: np.ndarray, small: np.ndarray | None = None) -> tuple[np.ndarray, ShadowMask]:
        """(the reduced frame, its shadow mask) of ``image``; ``small`` may pass an already reduced copy.

        The reduction, the luminance, the index and its 8-bit quantization are one compiled pass at the default
        scale (``_reduce_index8``; else ``reduce``, ``cvtColor`` and ``_index8``), then Otsu's threshold (OpenCV's),
        the two classes' statistics, the decision and the morphology in one more (``_classify``): the same
        floats as NumPy's element-wise float32 arithmetic, exact integer luminance sums, and NumPy's pairwise
        float32 sums for the c3 means (tests/estimators/test_shadow_detection.py checks the masks against the
        NumPy path over many frames)."""
        img = _rgb8(image, "frame")
        index = self.config.index
        if small is None and index != "tsai" and self._quarters(img):
            small, lum8, c3, idx8 = _reduce_index8(img, _c3_table(), _INDEX_MODES[index])
        else:
            small = self.reduce(img) if small is None else _rgb8(small, "reduced frame")   # (c3 table: bytes)
            lum8 = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
            c3 = np.empty(lum8.shape, np.float32) if index in ("c3_luminance", "c3") else _NO_C3
            if index == "tsai":
                idx8 = np.clip(shadow_index(small, index)[0] * 255.0, 0, 255).astype(np.uint8)
            else:
                idx8 = _index8(np.ascontiguousarray(small), lum8, _c3_table(), _INDEX_MODES[index], c3)
        if index not in ("c3_luminance", "c3"):
            c3 = _NO_C3
        oc = self._open_close
        mask = _classify(idx8, lum8, c3, idx8.size * 255 >= 2 ** 24, self.config.max_luminance_ratio,
                         self.config.min_blue_shift, oc.open_runs, oc.close_runs)
        return small, ShadowMask(mask.view(np.bool_), img.shape[:2])


def dark_class(image: np.ndarray) -> tuple[float, float] | None:
    """(the dark class's mean luminance over the lit one's, its mean c3 minus the lit one's) of the two classes the
    detector's ``c3_luminance`` index splits ``image`` (RGB uint8, taken as already reduced) into: the figures its
    decision compares with ``max_luminance_ratio`` and ``min_blue_shift``; None when Otsu leaves a class empty."""
    small = np.ascontiguousarray(_rgb8(image, "image"))
    lum8 = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY)
    c3 = np.empty(lum8.shape, np.float32)
    idx8 = _index8(small, lum8, _c3_table(), _INDEX_MODES["c3_luminance"], c3)
    _, split, ratio, shift = _split_figures(idx8, lum8, c3, idx8.size * 255 >= 2 ** 24)
    return (float(ratio), float(shift)) if split else None


def _rgb8(image: np.ndarray, what: str) -> np.ndarray:
    """``image`` as an array, refused unless (H, W, 3) uint8 with at least one pixel."""
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
        raise ConfigError(f"shadow detector: expected an (H, W, 3) uint8 RGB {what}, got {a.shape} {a.dtype}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise ConfigError(f"shadow detector: the {what} is empty ({a.shape[1]} x {a.shape[0]} px); pass an image "
                          "of at least 1 x 1 px (a camera frame, or its reduced copy)")
    return a


_NO_C3 = np.zeros((0, 0), np.float32)
#: ``_index8`` modes: the index from c3 and the luminance, c3 alone, the darkness alone
_INDEX_MODES = {"c3_luminance": 0, "c3": 1, "luminance": 2}


@functools.lru_cache(maxsize=1)
def _c3_table() -> np.ndarray:
    """``c3_invariant`` of every 8-bit (B, max(R, G)) pair (256, 256) float32: its own floats (``portable.arctan2``
    is a function of the two values alone, tested), looked up per pixel instead of recomputed."""
    b, m = np.meshgrid(np.arange(256, dtype=np.uint8), np.arange(256, dtype=np.uint8), indexing="ij")
    return np.ascontiguousarray(c3_invariant(np.stack([m, m, b], axis=-1)))


def oracle_mask(info: Mapping[str, Any] | None, frame_shape: tuple[int, int]) -> ShadowMask:
    """The simulator's ground-truth shadow mask from ``info['shadow_mask']`` (ablations only)."""
    if info is None or INFO_KEY not in info:
        raise ConfigError(f"shadow detector 'oracle' needs info[{INFO_KEY!r}] from the env (the ground-truth "
                          "mask); the runner passes info only to agents with uses_ground_truth = True")
    m = np.asarray(info[INFO_KEY]).astype(bool)
    if m.shape != tuple(frame_shape):
        raise ConfigError(f"info[{INFO_KEY!r}] has shape {m.shape}, the frame is {tuple(frame_shape)}")
    return ShadowMask(m, tuple(frame_shape))


def restoration_lut(small_rgb: np.ndarray, mask: np.ndarray, method: str) -> np.ndarray:
    """(3, 256) float32 per-channel map of shadow-pixel intensities to restored ones (identity if no shadow)."""
    if method not in RESTORATIONS:
        raise ConfigError(f"restoration: unknown method {method!r}; use one of {RESTORATIONS}")
    lut = np.tile(np.arange(256, dtype=np.float32), (3, 1))
    if not mask.any() or mask.all():
        return lut
    if method == "equalize":   # all three channel histograms of the shadow pixels in one bincount
        shadow8 = small_rgb.reshape(-1, 3)[mask.reshape(-1)].astype(np.intp)
        shadow8 += np.arange(0, 768, 256)
        hist = np.bincount(shadow8.ravel(), minlength=768).reshape(3, 256).astype(np.float64)
        cdf = np.cumsum(hist, axis=1) / hist.sum(axis=1, keepdims=True)   # exact counts: the same floats
        return np.round(255.0 * cdf).astype(np.float32)
    if small_rgb.shape[0] * small_rgb.shape[1] * 255 < 2 ** 24:
        lit_mean, shadow_mean = _masked_channel_means(small_rgb, mask)
        for ch in range(3):
            gain = float(lit_mean[ch]) / max(float(shadow_mean[ch]), 1.0)
            lut[ch] = np.clip(lut[ch] * gain, 0.0, 255.0)
        return lut
    shadow = small_rgb[mask].astype(np.float32)          # (n, 3); large images: NumPy's float32 means
    lit = small_rgb[~mask].astype(np.float32)
    for ch in range(3):
        gain = float(lit[:, ch].mean()) / max(float(shadow[:, ch].mean()), 1.0)
        lut[ch] = np.clip(lut[ch] * gain, 0.0, 255.0)
    return lut


def restoration_lut_reference(small_rgb: np.ndarray, mask: np.ndarray, method: str) -> np.ndarray:
    """``restoration_lut`` the direct way (masked copies, one channel at a time): the tests' reference."""
    lut = np.tile(np.arange(256, dtype=np.float32), (3, 1))
    if not mask.any() or mask.all():
        return lut
    shadow = small_rgb[mask].astype(np.float32)
    lit = small_rgb[~mask].astype(np.float32)
    for ch in range(3):
        if method == "equalize":
            hist = np.bincount(shadow[:, ch].astype(np.int64), minlength=256).astype(np.float64)
            cdf = np.cumsum(hist) / hist.sum()
            lut[ch] = np.round(255.0 * cdf).astype(np.float32)
        else:
            gain = float(lit[:, ch].mean()) / max(float(shadow[:, ch].mean()), 1.0)
            lut[ch] = np.clip(lut[ch] * gain, 0.0, 255.0)
    return lut


def _masked_channel_means(small_rgb: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel float32 means outside and inside ``mask``, the same floats as
    ``small_rgb[~mask].astype(np.float32).mean(axis=0)`` (and ``[mask]``) without the two masked copies: the
    sums of 8-bit values below 2^24 are exact integers in any order (float64 products here, float32 pairwise
    sums in NumPy), then divided as NumPy's mean divides (a float32 sum by the count). Any number of channels
    (an (h, w) image is one), integer-valued."""
    flat = small_rgb.reshape(mask.size, -1).astype(np.float64)
    inside = mask.reshape(-1)
    n_in = int(np.count_nonzero(inside))
    s_in = inside.astype(np.float64) @ flat
    s_out = flat.sum(axis=0) - s_in
    return _f32_mean(s_out, inside.size - n_in), _f32_mean(s_in, n_in)


def _f32_mean(exact_sums: np.ndarray, count: int) -> np.ndarray:
    """NumPy's float32 mean from an exact float32 sum: ``ret.dtype.type(ret / count)`` as ``_methods._mean``."""
    out = np.empty(len(exact_sums), np.float32)
    for i, s in enumerate(exact_sums):
        ret = np.float32(s)
        out[i] = ret.dtype.type(ret / count)
    return out


def restore(image: np.ndarray, mask: ShadowMask, method: str, small: np.ndarray | None = None) -> np.ndarray:
    """The frame with its shadow pixels restored (uint8); for pictures and checks. The MCL model applies the
    same look-up table at its sample points only."""
    small = small if small is not None else cv2.resize(image, mask.mask.shape[::-1], interpolation=cv2.INTER_AREA)
    lut = restoration_lut(small, mask.mask, method)
    full = mask.full()
    out = image.copy()
    for ch in range(3):
        out[..., ch][full] = np.round(lut[ch][image[..., ch][full]]).astype(np.uint8)
    return out


def mask_quality(predicted: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """IoU, precision and recall of a predicted boolean mask against the ground truth (same shape).

    Conventions for empty sets: IoU, precision and recall are 1 when both masks are empty. An empty prediction
    of a frame with shadows scores precision 0 (not 1: a detector that gives up must not look precise), and a
    frame without shadows scores recall 1 (nothing was missed; its false detections show in the precision).
    """
    p, t = np.asarray(predicted, bool), np.asarray(truth, bool)
    if p.shape != t.shape:
        raise ConfigError(f"mask_quality: predicted mask {p.shape} and truth {t.shape} differ in shape")
    tp = int(np.count_nonzero(p & t))
    n_p, n_t = int(np.count_nonzero(p)), int(np.count_nonzero(t))
    union = n_p + n_t - tp
    return {"iou": tp / union if union else 1.0,
            "precision": tp / n_p if n_p else (0.0 if n_t else 1.0),
            "recall": tp / n_t if n_t else 1.0,
            "fraction_true": n_t / t.size, "fraction_predicted": n_p / p.size}


@dataclass(frozen=True)
class MapRatioDetectorConfig:
    """The map-ratio detector (an addition to the paper; see ``MapRatioShadowDetector``)."""

    scale: float = field(default=0.25, metadata=rng(0.02, 1.0, doc="working resolution / frame resolution"))
    max_std_m: float = field(default=4.0, metadata=rng(0.0, 1e4, doc="use it only when the particle cloud is "
                                                                        "this tight (1 sigma); else the image one"))
    blur_px: float = field(default=1.0, metadata=rng(0.0, 20.0, doc="Gaussian blur (reduced px) of both images"))
    min_darkening: float = field(default=0.8, metadata=rng(0.0, 1.0, doc="shadow/lit ratio of the two Otsu "
                                                                          "classes above which: no shadow"))
    open_px: int = field(default=1, metadata=rng(0, 50))
    close_px: int = field(default=1, metadata=rng(0, 50))


def _luma(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)


class MapRatioShadowDetector:
    """Shadows as the regions where the camera is darker than the shadow-free database at the estimated pose.

    Not the paper's (III.B works from the camera image alone) but what an estimator that holds the database and
    a converged pose estimate can do: the log-luminance ratio camera / database-patch is ~log(exposure) in sun
    and ~log(exposure x 0.6) in shadow, two modes that an Otsu threshold separates far better than any
    per-pixel colour index separates dark asphalt from shadowed grass. The database is downsampled once (area
    filter) to the reduced camera resolution at the nominal altitude; each frame costs one small warp.

    With a pose about a metre off it is about twice as precise as the image detector at a similar recall, and
    takes far less of a shadow-free frame for shadow (docs/perf-log.md has the figures). The darkening guard
    (``min_darkening``) trades the two: weak shadows (strength 0.7, a darkening ~0.76) can be turned down on a
    frame.
    """

    def __init__(self, config: MapRatioDetectorConfig | None = None) -> None:
        self.config = config or MapRatioDetectorConfig()
        self._open_close = _OpenClose(self.config.open_px, self.config.close_px)

    def reset(self, briefing: Any) -> None:
        m, cam = briefing.orthomap, briefing.camera
        self.orthomap, self.camera = m, cam
        # map pixels per reduced camera pixel at the nominal altitude: downsample the database by that much
        f = max(1.0, cam.gsd_m(briefing.altitude_m) / self.config.scale / min(m.gsd_x_m, m.gsd_y_m))
        self.factor = f
        if isinstance(m, DatabaseWindow):   # a window of a map read by window: the whole map's level grid, filled there
            size = (max(1, round(m.width_px / f)), max(1, round(m.height_px / f))) if f > 1.0 else \
                (m.width_px, m.height_px)
            self._lum = m.level_of(_luma, size, np.uint8, key="MapRatioShadowDetector").array
            self._sx, self._sy = size[0] / m.width_px, size[1] / m.height_px
            return
        rgb = np.asarray(m.rgb)
        if f > 1.0:
            size = (max(1, round(rgb.shape[1] / f)), max(1, round(rgb.shape[0] / f)))
            self._lum = cv2.resize(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), size,
                                   interpolation=cv2.INTER_AREA)
        else:
            self._lum = cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)
        self._sx = self._lum.shape[1] / rgb.shape[1]
        self._sy = self._lum.shape[0] / rgb.shape[0]

    def detect(self, image: np.ndarray, x_m: float, y_m: float, yaw_rad: float, altitude_m: float,
               small: np.ndarray | None = None) -> ShadowMask:
        """The shadow mask of ``image`` taken at (about) the given pose."""
        c = self.config
        H, W = image.shape[:2]
        if small is None:
            small = cv2.resize(image, (max(1, round(W * c.scale)), max(1, round(H * c.scale))),
                               interpolation=cv2.INTER_LINEAR)
        h, w = small.shape[:2]
        a = self.camera.camera_to_map(self.orthomap, x_m, y_m, yaw_rad, altitude_m)     # full cam px -> map px
        # reduced camera px -> full camera px, then map px -> downsampled map px (pixel centres at integers)
        su, sv = W / w, H / h
        to_full = np.array([[su, 0.0, 0.5 * su - 0.5], [0.0, sv, 0.5 * sv - 0.5], [0.0, 0.0, 1.0]])
        to_low = np.array([[self._sx, 0.0, 0.5 * self._sx - 0.5], [0.0, self._sy, 0.5 * self._sy - 0.5],
                           [0.0, 0.0, 1.0]])
        aff = (to_low @ np.vstack([a, [0.0, 0.0, 1.0]]) @ to_full)[:2]
        db = cv2.warpAffine(self._lum, aff, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
        cam = cv2.cvtColor(small, cv2.COLOR_RGB2GRAY).astype(np.float32)
        if c.blur_px > 0:
            db = cv2.GaussianBlur(db, (0, 0), c.blur_px)
            cam = cv2.GaussianBlur(cam, (0, 0), c.blur_px)
        lr = cv2.log((cam + 4.0) / (db + 4.0))                       # log ratio; +4 tames near-black pixels
        # a fixed quantization range: ratios 0.22 .. 1.65 (a shadow is ~0.5-0.75, exposure jitter ~+-10 %)
        q = cv2.convertScaleAbs(lr, alpha=255.0 / 2.0, beta=1.5 * 255.0 / 2.0)
        _, binary = cv2.threshold(q, 0, 1, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)      # 1 = darker class
        mask = binary.astype(bool)
        if mask.all() or not mask.any():
            return ShadowMask(np.zeros((h, w), bool), (H, W))
        if portable.exp(float(lr[mask].mean() - lr[~mask].mean())) > c.min_darkening:
            return ShadowMask(np.zeros((h, w), bool), (H, W))
        return ShadowMask(self._open_close(binary), (H, W))
