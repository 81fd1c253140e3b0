"""The appearance gap: how unlike are the camera frame and the map database at the true pose?

A benchmark ranks localization methods the way a real flight would only if its map and camera differ as much
as real acquisitions do. This module measures that difference with six statistics (and the camera window's
colours with two more, and the two windows' luma photometry with three), on

- a scenario (``scenario_gap``): the env's camera frame against the database patch rendered at the frame's
  *true* pose (the estimators' map, ``briefing.orthomap``), at every ``stride``-th frame of several seeds. Like
  is compared with like: a co-registered pair cannot show a map's georeference bias (``database.georef_bias_m``)
  nor a gimbal's attitude error, so the patch is rendered where the map shows the ground the tilted camera
  sees (the bias added, the frame centre's shift under the gimbal's roll and pitch applied); the statistics
  then measure appearance alone (how large the bias is, the scenario states);
- a pair of co-registered real images of the same ground at two dates (``pair_gap``): the later epoch plays the
  camera, the earlier the database, tiled into camera-sized windows. The two go onto one grid first
  (``world.maps.pairs.load_pair``: each through its own georeference, square pixels, at the pair's own sampling;
  a stated sampling only for images without a georeference), and their residual misregistration is measured and
  reported (refused beyond ``max_shift_m``).

Both go through the same per-window function (``window_stats``) at an **analysis ground sampling**
(``GapConfig.gsd_m``, default 0.5 m/px, the coarsest of the usual sources: the LEVIR-CD pairs' sampling; camera
frames, database patches and pairs are box-filtered down to it, never up: a source coarser than it is analysed at
its own, and the report says which) over a **window** the size of the camera
footprint (scenarios: the camera's footprint at the true altitude; pairs: ``GapConfig.window_m``, default
150 m x 100 m, the paper's 600 x 400 camera at 200 m). The "database" window carries a margin of
``search_m`` on every side for the search statistics. All statistics are on luma (ITU-R 601).

Statistics of one window (C = camera window, D = database window at the true alignment, D+ = D with the
search margin):

``ncc``
    Pearson correlation of the luma of C and D over the whole window (1 = identical up to gain and offset,
    0 = unrelated). A constant window gives 0.
``bit_agreement``
    The paper's intensity-pair descriptor (eq. 2, c = 1): ``n_bits`` pixel pairs (p1, p2) drawn uniformly over
    the window (fixed ``seed``, the same pairs for every window of a size); the bit is ``[I(p1) > I(p2)]``;
    agreement = the fraction of pairs whose bit is the same in C and in D (the XNOR similarity xi of eq. 4 at
    the true pose). 1 = identical order, 0.5 = unrelated.
``psr``
    NCC peak-to-sidelobe ratio over the +-``search_m`` search: the surface S = ``cv2.matchTemplate(D+, C,
    TM_CCOEFF_NORMED)`` (one value per integer shift up to +-``search_m``); the side lobe is S outside a disc
    of radius ``success_radius_m`` around S's peak; ``psr = (max S - mean side) / std side`` (the MOSSE
    tracker's definition). How much the best match stands out of the clutter.
``peak_margin``
    ``max S - max side``: the peak's lead over the strongest competing shift (as in the pairs' README).
``orb_inlier_ratio``
    ORB keypoints (``orb_features``) on C and on D+, brute-force Hamming matches kept by Lowe's ratio test
    (``orb_ratio``), a RANSAC similarity (``cv2.estimateAffinePartial2D``, ``ransac_px`` reprojection
    threshold) as the feature-matching baseline fits; ratio = RANSAC inliers / ratio-test matches; 0 with
    fewer than 4 matches or no model.
``template_within``
    1 when S's peak lies within ``success_radius_m`` (2 m) of the true shift (the centre of S), else 0; its
    mean over windows is the fraction of frames on which template matching would find the truth.

Two more statistics describe the camera window alone, in colour (``camera_colour_stats``), because the image
shadow detectors of the MCL models (``estimators.shadow_detection``) decide from them whether a frame holds a
shadow: the paper's shadow index (c3 and luminance) quantized to 8 bits and split in two classes by Otsu's
threshold, as the detector splits a frame,

``dark_c3_shift``
    mean c3 = ``arctan(B / max(R, G))`` (scaled to [0, 1]) of the dark class minus that of the lit class: how
    much bluer the dark part of the view is (shadow lit by the sky is bluer; dark vegetation and warm soil are
    not). The detector sees no shadow in a frame whose shift is below its ``min_blue_shift``.
``dark_luma_ratio``
    mean luminance of the dark class / that of the lit class.

Both are NaN for a grey camera window. They are reported beside the gap statistics, and are not part of the
presets' calibration (``STATS``). A single real image (``image_colour_windows``, ``aerial-loc gap --image``: no
second epoch, so these two only) shows them for imagery of other places and sensors than the pairs'.

Three more compare the two windows' luma at the truth (``photometric_stats``), the photometric part of the gap
that the sum-of-squared-differences model sees and the correlation-based statistics do not (reported, not
calibrated either):

``luma_ratio``
    mean luma of C / mean luma of D: the exposure and brightness difference.
``contrast_ratio``
    standard deviation of C's luma / that of D: the contrast difference (tone curves, haze, shadows, blur).
``ssd_residual``
    mean of (C - D)^2 / variance of D: the squared difference at the true pose, in units of the map's variance
    (0 = identical; 1 - 2 rho k + k^2 + (mean difference / std D)^2 for correlation rho and contrast ratio k).

Summaries (``summarize``) give the median, the quartiles and the mean of each statistic over windows. The
**spread of the real pairs** is the range (min..max) over pairs of each pair's median (of its mean, for
``template_within``); ``aerial-loc gap`` marks a scenario's statistic that lies inside it. How far a headline
figure can move from sampling alone: ``headline_interval`` (distribution-free, for i.i.d. windows: order
statistics for a median, Clopper-Pearson for the template fraction); tests/benchmark/test_gap_calibration.py checks
with it that every realistic preset stays inside the real spread.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from aerial_loc_env.benchmark.store import finite_or_null
from aerial_loc_env.config import build_config, parse_assignments, rng
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.estimators.feature_matching import make_detector
from aerial_loc_env.estimators.patches import to_gray
from aerial_loc_env.estimators.shadow_detection import dark_class
from aerial_loc_env.world.maps.pairs import DEFAULT_MAX_SHIFT_M

#: the statistics of one window, in table order
STATS = ("ncc", "bit_agreement", "psr", "peak_margin", "orb_inlier_ratio", "template_within")
#: the camera window's own colour statistics (reported, not calibrated)
CAMERA_STATS = ("dark_c3_shift", "dark_luma_ratio")
#: the camera window's luma against the database's at the truth (reported, not calibrated)
PHOTO_STATS = ("luma_ratio", "contrast_ratio", "ssd_residual")
#: every statistic of a window, in table order
ALL_STATS = STATS + CAMERA_STATS + PHOTO_STATS
#: column titles of the printed table
TITLES = {"ncc": "NCC", "bit_agreement": "bit agreement", "psr": "PSR", "peak_margin": "peak margin",
          "orb_inlier_ratio": "ORB inliers", "template_within": "template <= 2 m",
          "dark_c3_shift": "dark c3 shift", "dark_luma_ratio": "dark / lit luma",
          "luma_ratio": "camera / map luma", "contrast_ratio": "camera / map contrast",
          "ssd_residual": "SSD residual"}


@dataclass(frozen=True)
class GapConfig:
    """How the gap is measured (see the module docstring for the definitions)."""

    gsd_m: float = field(default=0.5, metadata=rng(0.01, 100.0, doc="analysis ground sampling, m/px"))
    window_m: tuple[float, float] = (150.0, 100.0)     # pairs: window width, height in metres
    search_m: float = field(default=10.0, metadata=rng(0.5, 1000.0, doc="search half-width, m"))
    success_radius_m: float = field(default=2.0, metadata=rng(0.01, 100.0, doc="template success radius"))
    n_bits: int = field(default=4000, metadata=rng(10, 10**7, doc="random pixel pairs per window"))
    orb_features: int = field(default=2000, metadata=rng(10, 100000))
    orb_ratio: float = field(default=0.8, metadata=rng(0.0, 1.0, lo_open=True, doc="Lowe's ratio test"))
    ransac_px: float = field(default=3.0, metadata=rng(0.1, 100.0))
    seed: int = field(default=0, metadata=rng(0, 2**63 - 1, doc="seed of the bit pairs"))

    def validate(self, where: str) -> None:
        w, h = self.window_m
        if not (w > 0 and h > 0 and math.isfinite(w) and math.isfinite(h)):
            raise ConfigError(f"{where}: window_m = {self.window_m} must be two positive sizes in metres")

    def margin_px(self, gsd_m: float) -> int:
        return int(math.ceil(self.search_m / gsd_m - 1e-9))


def gap_config(**overrides: Any) -> GapConfig:
    """A validated ``GapConfig`` (unknown keys and out-of-range values are ``ConfigError``)."""
    return build_config(GapConfig, overrides, where="gap config")


# ------------------------------------------------------------------------------------------ one window
def _luma(image: np.ndarray) -> np.ndarray:
    arr = np.asarray(image)
    return arr.astype(np.float32) if arr.ndim == 2 else to_gray(arr)


def ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of two equal-shape grey images (0 when either is constant)."""
    x = a.astype(np.float64).ravel() - a.mean()
    y = b.astype(np.float64).ravel() - b.mean()
    den = math.sqrt(float(x @ x) * float(y @ y))
    return float(x @ y / den) if den > 0.0 else 0.0


def _pairs(shape: tuple[int, int], n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` random pixel pairs over a window (flat indices of both points), fixed by ``seed``."""
    gen = np.random.default_rng(seed)
    size = shape[0] * shape[1]
    return gen.integers(0, size, n), gen.integers(0, size, n)


def bit_agreement(a: np.ndarray, b: np.ndarray, n_bits: int, seed: int) -> float:
    """The fraction of random pixel pairs whose intensity order (eq. 2) is the same in ``a`` and ``b``."""
    p1, p2 = _pairs(a.shape[:2], n_bits, seed)
    fa, fb = a.ravel(), b.ravel()
    return float(np.mean((fa[p1] > fa[p2]) == (fb[p1] > fb[p2])))


def ncc_surface(camera: np.ndarray, database: np.ndarray) -> np.ndarray:
    """TM_CCOEFF_NORMED of ``camera`` at every shift inside ``database`` (non-finite values -> 0)."""
    s = cv2.matchTemplate(database.astype(np.float32), camera.astype(np.float32), cv2.TM_CCOEFF_NORMED)
    return np.nan_to_num(s, nan=0.0, posinf=0.0, neginf=0.0)


def surface_stats(surface: np.ndarray, gsd_m: float, radius_m: float) -> dict[str, float]:
    """PSR, peak margin and whether the peak is within ``radius_m`` of the surface's centre (the truth)."""
    h, w = surface.shape
    i, j = np.unravel_index(int(np.argmax(surface)), surface.shape)
    peak = float(surface[i, j])
    yy, xx = np.mgrid[0:h, 0:w]
    side = surface[np.hypot(yy - i, xx - j) * gsd_m > radius_m]
    if side.size < 2:
        raise ConfigError(f"gap: the search surface ({w} x {h} shifts) has no side lobe beyond "
                          f"{radius_m} m; make search_m larger than success_radius_m")
    std = float(side.std())
    within = math.hypot(i - (h - 1) / 2, j - (w - 1) / 2) * gsd_m <= radius_m
    return {"psr": (peak - float(side.mean())) / std if std > 0 else 0.0,
            "peak_margin": peak - float(side.max()), "template_within": float(within)}


def camera_colour_stats(camera: np.ndarray) -> dict[str, float]:
    """The camera window's dark-class statistics (module docstring): the c3 shift and luminance ratio of the
    two Otsu classes of the paper's shadow index, as the detector computes them (``shadow_detection.dark_class``);
    NaN for a grey window or one Otsu cannot split."""
    arr = np.asarray(camera)
    if arr.ndim != 3 or arr.shape[2] != 3:
        return {s: math.nan for s in CAMERA_STATS}
    figures = dark_class(arr if arr.dtype == np.uint8 else np.clip(np.rint(arr), 0, 255).astype(np.uint8))
    if figures is None:
        return {s: math.nan for s in CAMERA_STATS}
    ratio, shift = figures
    return {"dark_c3_shift": shift, "dark_luma_ratio": ratio}


def orb_inlier_ratio(camera: np.ndarray, database: np.ndarray, cfg: GapConfig) -> float:
    """RANSAC-similarity inliers / ratio-test matches of ORB features (0 without 4 matches or a model)."""
    detector, norm = make_detector("orb", cfg.orb_features)
    kc, dc = detector.detectAndCompute(np.clip(camera, 0, 255).astype(np.uint8), None)
    kd, dd = detector.detectAndCompute(np.clip(database, 0, 255).astype(np.uint8), None)
    if dc is None or dd is None or len(kc) < 2 or len(kd) < 2:
        return 0.0
    good = [m[0] for m in cv2.BFMatcher(norm).knnMatch(dc, dd, k=2)
            if len(m) == 2 and m[0].distance < cfg.orb_ratio * m[1].distance]
    if len(good) < 4:
        return 0.0
    src = np.float32([kc[m.queryIdx].pt for m in good])
    dst = np.float32([kd[m.trainIdx].pt for m in good])
    model, inliers = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=cfg.ransac_px)
    return 0.0 if model is None else float(inliers.sum()) / len(good)


def window_stats(camera: np.ndarray, database: np.ndarray, cfg: GapConfig, gsd_m: float | None = None
                 ) -> dict[str, float]:
    """The statistics of one window: ``camera`` (h, w) and ``database`` (h + 2m, w + 2m) with the search
    margin m = ``cfg.margin_px(gsd_m)`` on every side, both at ``gsd_m`` (default ``cfg.gsd_m``) metres per
    pixel, RGB or grey (the camera's colour statistics need RGB)."""
    gsd = cfg.gsd_m if gsd_m is None else gsd_m
    cam, db = _luma(camera), _luma(database)
    m = cfg.margin_px(gsd)
    h, w = cam.shape
    if db.shape != (h + 2 * m, w + 2 * m):
        raise ConfigError(f"gap: the database window is {db.shape[1]} x {db.shape[0]} px; with a "
                          f"{w} x {h} camera window and a {m} px search margin it must be "
                          f"{w + 2 * m} x {h + 2 * m}")
    for name, window in (("camera", cam), ("database", db)):
        bad = window.size - int(np.count_nonzero(np.isfinite(window)))
        if bad:   # NaN compares false: the statistics would come out plausible and wrong (bit agreement 1)
            raise ConfigError(f"gap: the {name} window has {bad} of {window.size} pixels that are not finite "
                              "(NaN or inf); leave out windows that touch no-data (as pair_gap does) or fill them")
    core = db[m:m + h, m:m + w]
    return {"ncc": ncc(cam, core), "bit_agreement": bit_agreement(cam, core, cfg.n_bits, cfg.seed),
            **surface_stats(ncc_surface(cam, db), gsd, cfg.success_radius_m),
            "orb_inlier_ratio": orb_inlier_ratio(cam, db, cfg), **camera_colour_stats(camera),
            **photometric_stats(cam, core)}


def photometric_stats(camera: np.ndarray, database: np.ndarray) -> dict[str, float]:
    """The camera window's luma against the database window's at the truth (module docstring): mean ratio,
    standard deviation ratio and the SSD residual (mean squared difference / the database's variance); NaN where
    the database window is constant (or black)."""
    c, d = np.asarray(camera, dtype=np.float64), np.asarray(database, dtype=np.float64)
    mean_d, var_d = float(d.mean()), float(d.var())
    if mean_d <= 0.0 or var_d <= 0.0:
        return {s: math.nan for s in PHOTO_STATS}
    return {"luma_ratio": float(c.mean()) / mean_d, "contrast_ratio": math.sqrt(float(c.var()) / var_d),
            "ssd_residual": float(np.mean((c - d) ** 2)) / var_d}


# ------------------------------------------------------------------------------------------ summaries
def summarize(windows: Sequence[Mapping[str, float]]) -> dict[str, dict[str, float]]:
    """Per statistic over windows: median, p25, p75, mean and the count of windows that have it (the colour
    statistics are NaN on grey windows: left out; all NaN when none has them)."""
    out = {}
    for s in ALL_STATS:
        v = np.asarray([w.get(s, math.nan) for w in windows], dtype=float)
        v = v[np.isfinite(v)]
        if v.size == 0:
            out[s] = {"median": math.nan, "p25": math.nan, "p75": math.nan, "mean": math.nan, "n": 0}
            continue
        out[s] = {"median": float(np.median(v)), "p25": float(np.percentile(v, 25)),
                  "p75": float(np.percentile(v, 75)), "mean": float(v.mean()), "n": int(v.size)}
    return out


def headline(summary: Mapping[str, Mapping[str, float]], stat: str) -> float:
    """The one figure of a statistic: the fraction for ``template_within``, the median otherwise."""
    return summary[stat]["mean" if stat == "template_within" else "median"]


def median_interval(values: Sequence[float], confidence: float = 0.99) -> tuple[float, float]:
    """A distribution-free confidence interval of the median of i.i.d. ``values``: the order statistics
    ``(x_(k), x_(n+1-k))`` with the largest k for which ``P(Binomial(n, 1/2) <= k - 1) <= (1 - confidence) / 2``
    (each bound falls on the wrong side of the true median only if fewer than k values do). Its coverage is at
    least ``confidence`` whatever the distribution."""
    x = np.sort(np.asarray(values, dtype=float))
    n = x.size
    tail, k, cdf = (1.0 - confidence) / 2.0, 0, 0.0
    while k < n and cdf + math.comb(n, k) / 2.0 ** n <= tail:
        cdf += math.comb(n, k) / 2.0 ** n
        k += 1
    if k == 0:
        need = math.ceil(math.log2(1.0 / tail))
        raise ConfigError(f"gap: {n} values cannot bound a median at {confidence:.0%} confidence; measure at "
                          f"least {need}")
    return float(x[k - 1]), float(x[n - k])


def proportion_interval(successes: int, n: int, confidence: float = 0.99) -> tuple[float, float]:
    """The exact (Clopper-Pearson) confidence interval of a binomial proportion: the p whose binomial tails
    put ``successes`` out of ``n`` at probability ``(1 - confidence) / 2`` (found by bisection)."""
    if not 0 <= successes <= n or n < 1:
        raise ConfigError(f"gap: {successes} successes out of {n} trials is not a proportion")
    tail = (1.0 - confidence) / 2.0

    def cdf(k: int, p: float) -> float:          # P(X <= k), X ~ Binomial(n, p)
        return sum(math.comb(n, i) * p ** i * (1.0 - p) ** (n - i) for i in range(k + 1))

    def solve(f) -> float:                       # the root of a decreasing f on [0, 1]
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if f(mid) > 0.0 else (lo, mid)
        return 0.5 * (lo + hi)

    lower = 0.0 if successes == 0 else solve(lambda p: tail - (1.0 - cdf(successes - 1, p)))
    upper = 1.0 if successes == n else solve(lambda p: cdf(successes, p) - tail)
    return lower, upper


def headline_interval(windows: Sequence[Mapping[str, float]], stat: str, confidence: float = 0.99
                      ) -> tuple[float, float]:
    """How far a source's headline figure (``headline``) can move from sampling alone, given i.i.d. windows:
    ``proportion_interval`` for the template fraction, ``median_interval`` otherwise."""
    v = [w[stat] for w in windows]
    if stat == "template_within":
        return proportion_interval(int(round(sum(v))), len(v), confidence)
    return median_interval(v, confidence)


def spread(summaries: Iterable[Mapping[str, Mapping[str, float]]]) -> dict[str, tuple[float, float]]:
    """The spread of several sources (the real pairs): min..max of their headline figures per statistic (NaN
    where no source has it)."""
    items = list(summaries)
    if not items:
        raise ConfigError("gap: no real pairs to take a spread over")
    out = {}
    for s in ALL_STATS:
        v = [headline(x, s) for x in items if s in x and math.isfinite(headline(x, s))]
        out[s] = (min(v), max(v)) if v else (math.nan, math.nan)
    return out


# ------------------------------------------------------------------------------------------ real pairs
def _resample(rgb: np.ndarray, scale: float) -> np.ndarray:
    if abs(scale - 1.0) < 1e-6:
        return np.asarray(rgb)
    h, w = rgb.shape[:2]
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return cv2.resize(np.asarray(rgb), size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)


def pair_windows(earlier: np.ndarray, later: np.ndarray, cfg: GapConfig, src_gsd_m: float
                 ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Tile a co-registered pair (same pixel grid, ``src_gsd_m`` m/px) into (camera, database) windows at
    the analysis sampling: the later epoch is the camera window, the earlier the database window with the
    search margin; non-overlapping camera windows on a regular grid that keeps every margin inside."""
    if earlier.shape[:2] != later.shape[:2]:
        raise ConfigError(f"gap: the pair's images are {earlier.shape[1]} x {earlier.shape[0]} and "
                          f"{later.shape[1]} x {later.shape[0]} px; co-registered images share one pixel grid")
    gsd = max(cfg.gsd_m, src_gsd_m)
    a, b = _resample(earlier, src_gsd_m / gsd), _resample(later, src_gsd_m / gsd)
    w, h = round(cfg.window_m[0] / gsd), round(cfg.window_m[1] / gsd)
    m = cfg.margin_px(gsd)
    H, W = a.shape[:2]
    origins = _window_origins(W, H, w, h, m)
    if not origins:
        raise ConfigError(f"gap: the pair covers {W * gsd:.0f} x {H * gsd:.0f} m, too small for one "
                          f"{cfg.window_m[0]:g} x {cfg.window_m[1]:g} m window plus the +-{cfg.search_m:g} m "
                          f"search; use a smaller window (aerial-loc gap --window-m W H, at most "
                          f"{max(0.0, W * gsd - 2 * cfg.search_m):.0f} x {max(0.0, H * gsd - 2 * cfg.search_m):.0f} m "
                          "here; GapConfig.window_m in Python)")
    return [(b[y:y + h, x:x + w], a[y - m:y + h + m, x - m:x + w + m]) for x, y in origins]


def _window_origins(W: int, H: int, w: int, h: int, margin: int = 0) -> list[tuple[int, int]]:
    """The top-left corners (x, y) of non-overlapping w x h windows on a regular grid centred in a W x H image,
    every window with ``margin`` px of the image around it (row by row; empty when not one fits)."""
    nx, ny = (W - 2 * margin) // w, (H - 2 * margin) // h
    if nx < 1 or ny < 1:
        return []
    x0, y0 = (W - nx * w) // 2, (H - ny * h) // 2
    return [(x, y) for y in range(y0, y0 + ny * h, h) for x in range(x0, x0 + nx * w, w)]


def _with_valid_channel(om: Any) -> np.ndarray:
    """An orthomap's RGB with its no-data as a fourth channel (255 = valid), so that resampling and tiling carry
    it exactly like the pixels."""
    valid = np.full(om.rgb.shape[:2], 255, np.uint8) if om.nodata is None else \
        np.where(om.nodata, 0, 255).astype(np.uint8)
    return np.dstack([om.rgb[..., :3], valid])


@dataclass(frozen=True)
class PairGap:
    """The statistics of a real pair's windows and how they were measured."""

    windows: list[dict[str, float]]
    gsd_m: float                 # the analysis sampling (the coarser of GapConfig.gsd_m and the pair's grid)
    pair_gsd_m: float            # the pair's common grid (world.maps.pairs: square pixels, georeferences honoured)
    registration: str            # the residual misregistration measured on it


def measure_pair(earlier: str | Path, later: str | Path, cfg: GapConfig | None = None, *,
                 gsd_m: float | None = None, max_shift_m: float | None = DEFAULT_MAX_SHIFT_M) -> PairGap:
    """The statistics of every window of a co-registered real pair given by path. The two images go onto one
    grid first (``world.maps.pairs.load_pair``: each through its own georeference, square pixels at the finer
    sampling, never compared pixel for pixel), each pair at its own sampling; ``gsd_m`` is only for images
    without a georeference. A residual misregistration beyond ``max_shift_m`` is refused (None: measured only).
    Windows touching no-data in either image are left out."""
    from aerial_loc_env.world.maps.pairs import load_pair

    cfg = cfg or GapConfig()
    a, b = Path(earlier), Path(later)
    pair = load_pair(a, b, gsd_m=gsd_m, max_shift_m=max_shift_m, where=f"gap: pair {a} / {b}")
    src = pair.grid.gsd_m
    imgs = [_with_valid_channel(om) for om in (pair.surveyed, pair.ground)]
    valid = [(c[..., :3], d[..., :3]) for c, d in pair_windows(imgs[0], imgs[1], cfg, src)
             if c[..., 3].min() == 255 and d[..., 3].min() == 255]
    if not valid:
        raise MapError(f"gap: every window of {earlier} / {later} touches no-data")
    gsd = max(cfg.gsd_m, src)
    return PairGap([window_stats(c, d, cfg, gsd) for c, d in valid], gsd, src, pair.registration.describe())


def pair_gap(earlier: str | Path, later: str | Path, cfg: GapConfig | None = None, *,
             gsd_m: float | None = None, max_shift_m: float | None = DEFAULT_MAX_SHIFT_M) -> list[dict[str, float]]:
    """The statistics of every window of a co-registered real pair (``measure_pair``'s windows)."""
    return measure_pair(earlier, later, cfg, gsd_m=gsd_m, max_shift_m=max_shift_m).windows


def image_colour_windows(path: str | Path, cfg: GapConfig | None = None, *, gsd_m: float | None = None
                         ) -> tuple[list[dict[str, float]], float]:
    """(the camera colour statistics of every window, the analysis sampling) of one real image given by path: read
    through its georeference (``gsd_m`` only for an image without one), its pixels squared at the analysis sampling
    (the coarser of ``cfg.gsd_m`` and its own), tiled into ``cfg.window_m`` windows on a regular grid; windows
    touching no-data are left out."""
    from aerial_loc_env.world.maps.pairs import read_image

    cfg = cfg or GapConfig()
    p = Path(path).expanduser()
    if not p.is_file():
        raise ConfigError(f"gap: --image {p}: no such image file")
    om = read_image(p, gsd_m)
    gsd = max(cfg.gsd_m, om.gsd_x_m, om.gsd_y_m)
    size = (max(1, round(om.width_px * om.gsd_x_m / gsd)), max(1, round(om.height_px * om.gsd_y_m / gsd)))
    img = cv2.resize(_with_valid_channel(om), size, interpolation=cv2.INTER_AREA)
    w, h = round(cfg.window_m[0] / gsd), round(cfg.window_m[1] / gsd)
    origins = _window_origins(size[0], size[1], w, h)
    if not origins:
        raise ConfigError(f"gap: --image {p.name} covers {size[0] * gsd:.0f} x {size[1] * gsd:.0f} m, too small "
                          f"for one {cfg.window_m[0]:g} x {cfg.window_m[1]:g} m window; use a smaller window "
                          "(aerial-loc gap --window-m W H)")
    windows = [img[y:y + h, x:x + w] for x, y in origins]
    out = [camera_colour_stats(win[..., :3]) for win in windows if win[..., 3].min() == 255]
    if not out:
        raise MapError(f"gap: every {cfg.window_m[0]:g} x {cfg.window_m[1]:g} m window of {p} touches no-data; "
                       "use a smaller window (aerial-loc gap --window-m W H) or an image with more valid ground")
    return out, gsd


def pairs_in(folder: str | Path) -> list[tuple[Path, Path]]:
    """The pairs of a folder laid out as ``A/<name>`` (earlier) and ``B/<name>`` (later), sorted by name
    (``world.maps.pairs.pairs_in``)."""
    from aerial_loc_env.world.maps.pairs import pairs_in as found

    try:
        return found(folder)
    except MapError as exc:
        raise ConfigError(f"gap: {exc}") from None


# ------------------------------------------------------------------------------------------ scenarios
def scenario_gap(scenario: str, overrides: Mapping[str, Any] | None = None, *, seeds: Sequence[int] = range(5),
                 stride: int = 20, cfg: GapConfig | None = None,
                 frames_per_seed: int | None = None) -> list[dict[str, float]]:
    """The statistics of every ``stride``-th frame of ``seeds`` episodes of ``scenario``: the camera frame
    against the estimators' database rendered at the frame's true pose. With ``frames_per_seed`` an episode
    stops after that many measured frames (1: the first frame of each seed, i.i.d. over seeds)."""
    from aerial_loc_env.env import AerialLocEnv, load_scenario
    from aerial_loc_env.sensors.camera import Pose
    from aerial_loc_env.sensors.render import CameraRenderer, Photometry

    cfg = cfg or GapConfig()
    if stride < 1:
        raise ConfigError(f"gap: stride = {stride} must be >= 1 (every stride-th frame is measured)")
    if frames_per_seed is not None and frames_per_seed < 1:
        raise ConfigError(f"gap: frames_per_seed = {frames_per_seed} must be >= 1 (or None: the whole episode)")
    env = AerialLocEnv(load_scenario(scenario, dict(overrides or {})))
    renderers: dict[int, CameraRenderer] = {}
    out = []
    try:
        for seed in seeds:
            obs, info = env.reset(seed=int(seed))
            db = env.briefing.orthomap
            bias_m = tuple(float(v) for v in env.scenario.database.georef_bias_m)
            if id(db) not in renderers:
                renderers[id(db)] = CameraRenderer(db, env.camera, Photometry.ideal(), strict=False)
            renderer = renderers[id(db)]
            step, done, measured = 0, False, 0
            while True:
                if step % stride == 0:
                    pose = Pose(*(float(v) for v in info["true_pose"]))
                    out.append(_frame_stats(obs["image"], pose, env.camera, renderer, cfg, bias_m,
                                            info.get("gimbal_roll_pitch_rad")))
                    measured += 1
                if done or measured == frames_per_seed:
                    break
                obs, _r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
                done = terminated or truncated
                step += 1
    finally:
        env.close()
    return out


def _frame_stats(image: np.ndarray, pose: Any, camera: Any, renderer: Any, cfg: GapConfig,
                 bias_m: tuple[float, float] = (0.0, 0.0), tilt_rad: Any = None) -> dict[str, float]:
    """One frame's statistics against the database patch where the map shows the ground the camera sees: at
    the true pose moved by the map's georeference bias ``bias_m`` (east, north), the patch shifted by the frame
    centre's displacement under the gimbal's (roll, pitch) ``tilt_rad``."""
    from aerial_loc_env.sensors.perspective import tilt_homography

    fw, fh = camera.footprint_m(pose.altitude_m)
    gsd = max(cfg.gsd_m, camera.gsd_m(pose.altitude_m))
    w, h = max(8, round(fw / gsd)), max(8, round(fh / gsd))
    m = cfg.margin_px(gsd)
    small = camera.resized(w, h)
    if bias_m != (0.0, 0.0):
        pose = pose._replace(x_m=pose.x_m + bias_m[0], y_m=pose.y_m + bias_m[1])
    affine = renderer.camera_to_map(pose, small)
    hom = None if tilt_rad is None else tilt_homography(small, float(tilt_rad[0]), float(tilt_rad[1]))
    if hom is not None:                     # the nadir pixel the tilted frame's centre shows
        c = np.array([w / 2.0, h / 2.0, 1.0])
        q = hom @ c
        affine[:, 2] += affine[:, :2] @ (q[:2] / q[2] - c[:2])
    affine[:, 2] -= affine[:, :2] @ np.array([m, m], dtype=np.float64)
    database = renderer.warp_map(affine, (w + 2 * m, h + 2 * m))
    cam = cv2.resize(np.asarray(image), (w, h), interpolation=cv2.INTER_AREA)
    return window_stats(cam, database, cfg, gsd)


# ------------------------------------------------------------------------------------------ report
def _cell(summary: Mapping[str, Mapping[str, float]], stat: str, inside: bool | None) -> str:
    s = summary.get(stat)
    if s is None or not math.isfinite(s["median"]):
        return "-"
    mark = "" if inside is None else (" *" if inside else "")
    if stat == "template_within":
        return f"{s['mean']:.0%}{mark}"
    if stat == "dark_c3_shift":          # signed: "to" between the quartiles
        q = [round(s[k], 3) + 0.0 for k in ("median", "p25", "p75")]     # + 0.0: no "-0.000"
        return f"{q[0]:+.3f} ({q[1]:+.3f} to {q[2]:+.3f}){mark}"
    digits = 1 if stat == "psr" else 2
    return f"{s['median']:.{digits}f} ({s['p25']:.{digits}f}-{s['p75']:.{digits}f}){mark}"


def gap_table(rows: Sequence[tuple[str, Mapping[str, Mapping[str, float]]]],
              real: Mapping[str, tuple[float, float]] | None = None, *, unmarked: Iterable[str] = (),
              stats: Sequence[str] = STATS + CAMERA_STATS) -> str:
    """A Markdown table of ``stats``: one row per source (label, summary), median (p25-p75) per statistic (the
    fraction for template matching); with ``real`` (the real pairs' spread) a spread row, and '*' marks a figure
    inside it (except on the ``unmarked`` rows: the real pairs themselves)."""
    unmarked = set(unmarked)
    head = "| source | windows | " + " | ".join(TITLES[s] for s in stats) + " |"
    lines = [head, "|" + "---|" * (len(stats) + 2)]
    for label, summary in rows:
        cells = []
        for s in stats:
            inside = None if real is None or label in unmarked or s not in summary else \
                real[s][0] <= headline(summary, s) <= real[s][1]
            cells.append(_cell(summary, s, inside))
        n = max(summary[s]["n"] for s in stats if s in summary)
        lines.append(f"| {label} | {n} | " + " | ".join(cells) + " |")
    if real is not None:
        def rng_cell(s: str) -> str:
            lo, hi = real[s]
            if not math.isfinite(lo):
                return "-"
            if s == "dark_c3_shift":
                return f"{lo:+.3f} to {hi:+.3f}"
            return f"{lo:.0%}-{hi:.0%}" if s == "template_within" else f"{lo:.2f}-{hi:.2f}"
        lines.append("| **real pairs: spread** | | " + " | ".join(rng_cell(s) for s in stats) + " |")
    return "\n".join(lines)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="aerial-loc gap", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenarios", nargs="*", metavar="SCENARIO",
                    help="scenario ids (or short names) to measure: camera frame vs database at the true pose")
    ap.add_argument("--pair", nargs="+", action="append", default=[], metavar="PATH",
                    help="a co-registered real pair by path: EARLIER LATER [GSD] (repeatable; GSD: ground metres "
                         "per pixel of its images if they have no georeference)")
    ap.add_argument("--pairs-dir", nargs="+", action="append", default=[], metavar="DIR",
                    help="a folder of pairs laid out as DIR/A/<name> (earlier) and DIR/B/<name> (later): DIR [GSD] "
                         "(repeatable; GSD as for --pair)")
    ap.add_argument("--pair-gsd", type=float, metavar="M",
                    help="ground metres per pixel of pair images without a georeference and without their own GSD "
                         "after --pair/--pairs-dir (LEVIR-CD: 0.5); images with a georeference (GeoTIFF tags, "
                         "world file + .prj) are always read at their own")
    ap.add_argument("--image", nargs="+", action="append", default=[], metavar="PATH",
                    help="a single real image by path: PATH [GSD] (repeatable; GSD as for --pair): the camera "
                         "window's colour statistics only (no second epoch), for imagery of other places")
    ap.add_argument("--window-m", type=float, nargs=2, metavar=("W", "H"), default=None,
                    help="pairs and images: window width and height in metres (default 150 100, the paper's "
                         "footprint)")
    ap.add_argument("--max-shift-m", type=float, default=DEFAULT_MAX_SHIFT_M, metavar="M",
                    help="refuse a pair whose residual misregistration (measured at load) exceeds this, metres "
                         f"(default {DEFAULT_MAX_SHIFT_M:g}; 0: measure and report only)")
    ap.add_argument("--seeds", type=int, default=5, help="episodes per scenario (seeds 0..N-1; default 5)")
    ap.add_argument("--stride", type=int, default=20, help="measure every N-th frame (default 20)")
    ap.add_argument("--frames-per-seed", type=int, metavar="N",
                    help="stop each episode after N measured frames (1: the first frame of each seed, as the "
                         "calibration test does; default: the whole episode)")
    ap.add_argument("--gsd", type=float, default=0.5, help="analysis ground sampling, m/px (default 0.5)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scenario override for every scenario (JSON value), e.g. flight.altitude_m=150")
    ap.add_argument("--json", metavar="PATH", help="also write every summary and window as JSON ('-': stdout)")
    return ap


def _overrides(items: Sequence[str]) -> dict[str, Any]:
    return parse_assignments(items, where="gap: --set", example="flight.altitude_m=150")


def _gsd_arg(value: str, what: str) -> float:
    try:
        out = float(value)
    except ValueError:
        out = float("nan")
    if not (math.isfinite(out) and out > 0):
        raise ConfigError(f"gap: {what}: {value!r} is not a ground sampling in metres per pixel (> 0)")
    return out


def _pair_sources(args: argparse.Namespace) -> list[tuple[Path, Path, float | None]]:
    """(earlier, later, GSD for images without a georeference) of every --pair and --pairs-dir."""
    out: list[tuple[Path, Path, float | None]] = []
    for item in args.pair:
        if len(item) not in (2, 3):
            raise ConfigError(f"gap: --pair {' '.join(item)}: give EARLIER LATER [GSD] (two image paths, then "
                              "optionally their ground metres per pixel)")
        gsd = _gsd_arg(item[2], f"--pair {item[0]} {item[1]} GSD") if len(item) == 3 else args.pair_gsd
        out.append((Path(item[0]), Path(item[1]), gsd))
    for item in args.pairs_dir:
        if len(item) not in (1, 2):
            raise ConfigError(f"gap: --pairs-dir {' '.join(item)}: give DIR [GSD]")
        gsd = _gsd_arg(item[1], f"--pairs-dir {item[0]} GSD") if len(item) == 2 else args.pair_gsd
        out += [(a, b, gsd) for a, b in pairs_in(item[0])]
    return out


def _image_sources(args: argparse.Namespace) -> list[tuple[Path, float | None]]:
    """(path, GSD for an image without a georeference) of every --image."""
    out = []
    for item in args.image:
        if len(item) not in (1, 2):
            raise ConfigError(f"gap: --image {' '.join(item)}: give PATH [GSD] (an image path, then optionally its "
                              "ground metres per pixel)")
        gsd = _gsd_arg(item[1], f"--image {item[0]} GSD") if len(item) == 2 else args.pair_gsd
        out.append((Path(item[0]), gsd))
    return out


def scenario_gsd_m(scenario: str, overrides: Mapping[str, Any], cfg: GapConfig) -> float:
    """The analysis sampling of a scenario's frames at its nominal altitude (``_frame_stats``: never finer than
    the camera's pixels)."""
    from aerial_loc_env.env import load_scenario

    sc = load_scenario(scenario, dict(overrides))
    cam = sc.camera
    w, h = sc.observation.width_px or cam.width_px, sc.observation.height_px or cam.height_px
    cam = cam if (w, h) == (cam.width_px, cam.height_px) else cam.resized(w, h)
    return max(cfg.gsd_m, float(cam.gsd_m(sc.flight.altitude_m)))


def sampling_note(gsds: Mapping[str, float]) -> str:
    """'at 0.5 m/px' when every source was analysed at one sampling, else each source's."""
    values = sorted({round(g, 3) for g in gsds.values()})
    if len(values) <= 1:
        return f"at {values[0] if values else 0.5:g} m/px"
    return "at each source's sampling (" + ", ".join(f"{k} {g:.3g}" for k, g in gsds.items()) + " m/px)"


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    if args.json and args.json != "-" and Path(args.json).exists():    # before any measuring
        raise ConfigError(f"gap: --json {args.json} exists; give a new path (results are never overwritten)")
    pairs = _pair_sources(args)
    images = _image_sources(args)
    if not args.scenarios and not pairs and not images:
        ap.error("give at least one SCENARIO, --pair, --pairs-dir or --image "
                 "(e.g. aerial-loc gap AerialLoc/PaperShadows-v2 --pairs-dir ../shared/data/pairs/levir-cd 0.5)")
    if args.seeds < 1:
        ap.error("--seeds must be >= 1")
    extra = {} if args.window_m is None else {"window_m": tuple(args.window_m)}
    cfg = gap_config(gsd_m=args.gsd, **extra)
    max_shift = args.max_shift_m if args.max_shift_m > 0 else None
    result: dict[str, Any] = {"config": asdict(cfg), "pairs": {}, "images": {}, "scenarios": {}}
    rows: list[tuple[str, Mapping]] = []
    gsds: dict[str, float] = {}
    for a, b, pair_gsd in pairs:
        measured = measure_pair(a, b, cfg, gsd_m=pair_gsd, max_shift_m=max_shift)
        label = f"{a.parent.parent.name}/{a.name}" if a.parent.name == "A" else f"{a.name} -> {b.name}"
        summary = summarize(measured.windows)
        result["pairs"][label] = {"earlier": str(a), "later": str(b), "summary": summary, "windows": measured.windows,
                                  "analysis_gsd_m": measured.gsd_m, "pair_gsd_m": measured.pair_gsd_m,
                                  "registration": measured.registration}
        rows.append((label, summary))
        gsds[label] = measured.gsd_m
    for path, image_gsd in images:
        windows, gsd = image_colour_windows(path, cfg, gsd_m=image_gsd)
        label = f"{path.name} (image)"
        summary = summarize(windows)
        result["images"][label] = {"path": str(path), "summary": summary, "windows": windows, "analysis_gsd_m": gsd}
        rows.append((label, summary))
        gsds[label] = gsd
    real = spread(s["summary"] for s in result["pairs"].values()) if pairs else None
    overrides = _overrides(args.set)
    for sid in args.scenarios:
        windows = scenario_gap(sid, overrides, seeds=range(args.seeds), stride=args.stride, cfg=cfg,
                               frames_per_seed=args.frames_per_seed)
        summary = summarize(windows)
        gsds[sid] = scenario_gsd_m(sid, overrides, cfg)
        result["scenarios"][sid] = {"overrides": overrides, "seeds": args.seeds, "stride": args.stride,
                                    "frames_per_seed": args.frames_per_seed, "summary": summary,
                                    "windows": windows, "analysis_gsd_m": gsds[sid]}
        rows.append((sid, summary))
    if real is not None:
        result["real_spread"] = {s: list(v) for s, v in real.items()}
    print(gap_table(rows, real, unmarked=[*result["pairs"], *result["images"]]))
    print(f"\nmedian (p25-p75) over windows {sampling_note(gsds)}, +-{cfg.search_m:g} m search; "
          "template <= 2 m: fraction of windows; dark c3 shift and dark / lit luma: the camera window alone, "
          "the two Otsu classes of the shadow index (not calibrated)"
          + ("; * = inside the real pairs' spread" if real else ""))
    photo_rows = [(label, summary) for label, summary in rows if label not in result["images"]]
    if photo_rows:
        print("\ncamera against map luma at the truth (the exposure, contrast and squared-difference part of the "
              "gap; not calibrated):\n")
        print(gap_table(photo_rows, real, unmarked=list(result["pairs"]), stats=PHOTO_STATS))
        print()
    for label, info in result["pairs"].items():
        print(f"{label}: {info['registration']}")
    if args.json:
        text = json.dumps(finite_or_null(result), indent=1, sort_keys=True)
        if args.json == "-":
            print(text)
        else:
            from aerial_loc_env.paths import atomic_write_bytes

            if Path(args.json).exists():
                raise ConfigError(f"gap: --json {args.json} exists; give a new path (results are never "
                                  "overwritten)")
            atomic_write_bytes(Path(args.json), (text + "\n").encode())
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
