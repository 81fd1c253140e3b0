"""Cast shadows from a height model, cloud shadows, and photographic shading.

The estimators are judged on shadows the map database lacks (Choi & Park 2020, sections III-IV), so the
shadows here follow the physics of a sunlit scene rather than painting dark rectangles:

* **Cast shadows** (`cast_shadow_mask`, `sun_occlusion`): exact for a height field sampled on the pixel
  grid, in O(pixels), by a sweep that carries the running horizon along digital lines towards the sun.
* **Penumbrae**: the sun is a disc of 0.53 deg; the soft field is the fraction of that disc hidden behind the
  horizon, from the sweep's height margin and the distance to the occluder (so penumbrae widen with the
  shadow length), plus a small anti-aliasing blur for the lateral edges (documented in `sun_occlusion`).
* **Shading** (`apply_shading`): shadowed ground keeps only the diffuse sky light, which is dimmer and bluer;
  done in linear light through a power-law gamma, which turns into one per-channel gain in encoded space.
* **Clouds** (`CloudField`): soft periodic noise thresholded to a cover fraction, drifting with the wind,
  for real imagery that has no height model.

Conventions (docs/ARCHITECTURE.md): rows grow south, columns grow east, the sun azimuth is the compass
bearing towards the sun, shadows fall towards azimuth + 180.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import lru_cache
from typing import NamedTuple

import cv2
import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import check_value
from aerial_loc_env.config import rng as rng_meta
from aerial_loc_env.errors import ConfigError, MapError

#: bumped when the output changes for the same inputs (env.fingerprint); 2: an episode's cloud field spans the
#: window it flies plus the drift, not the whole map
GENERATOR_VERSION = 2

SUN_ANGULAR_DIAMETER_DEG = 0.53
"""Apparent diameter of the solar disc; sets the physical penumbra width (about 9.3 mm per metre)."""

REC709_LUMA = (0.2126, 0.7152, 0.0722)
"""Luminance weights of linear RGB (Rec. 709 / sRGB primaries)."""


# --------------------------------------------------------------------------------------------------- sun


@dataclass(frozen=True)
class Sun:
    """Sun direction: ``azimuth_deg`` is the compass bearing towards the sun (clockwise from north, 180 = south),
    ``elevation_deg`` the angle above the horizon."""

    azimuth_deg: float
    elevation_deg: float

    def __post_init__(self) -> None:
        az, el = float(self.azimuth_deg), float(self.elevation_deg)
        if not (math.isfinite(az) and 0.0 <= az < 360.0):
            raise ConfigError(f"Sun.azimuth_deg = {self.azimuth_deg!r} is out of range; allowed [0, 360) "
                              "(compass bearing towards the sun, clockwise from north)")
        if not (math.isfinite(el) and 0.0 < el <= 90.0):
            raise ConfigError(f"Sun.elevation_deg = {self.elevation_deg!r} is out of range; allowed (0, 90] "
                              "(degrees above the horizon)")

    @property
    def towards_sun_en(self) -> tuple[float, float]:
        """Unit horizontal vector (east, north) pointing towards the sun."""
        a = math.radians(self.azimuth_deg)
        return math.sin(a), math.cos(a)

    def shadow_length_m(self, height_m: float) -> float:
        """Horizontal length of the shadow of a vertical edge of ``height_m`` on flat ground."""
        return height_m / math.tan(math.radians(self.elevation_deg))


def sun_from_ranges(rng: np.random.Generator, azimuth_range_deg: tuple[float, float],
                    elevation_range_deg: tuple[float, float]) -> Sun:
    """Draw a sun uniformly in azimuth and elevation.

    An azimuth range with lo > hi wraps through north (e.g. (300, 60)); elevation must satisfy 0 < lo <= hi <= 90.
    """
    az_lo, az_hi = (float(v) for v in azimuth_range_deg)
    el_lo, el_hi = (float(v) for v in elevation_range_deg)
    if not (0.0 <= az_lo <= 360.0 and 0.0 <= az_hi <= 360.0):
        raise ConfigError(f"sun_from_ranges: azimuth_range_deg = {azimuth_range_deg!r}; both ends must be in "
                          "[0, 360] (lo > hi wraps through north)")
    if not (0.0 < el_lo <= el_hi <= 90.0):
        raise ConfigError(f"sun_from_ranges: elevation_range_deg = {elevation_range_deg!r}; need "
                          "0 < lo <= hi <= 90")
    span = az_hi - az_lo if az_lo <= az_hi else az_hi + 360.0 - az_lo
    az = (az_lo + span * rng.random()) % 360.0
    el = el_lo + (el_hi - el_lo) * rng.random()
    return Sun(float(az), float(el))


# ------------------------------------------------------------------------------------------- geometry


class _RayGeometry(NamedTuple):
    """The sun ray in pixel steps along the dominant ("major") image axis."""

    major_axis: int      # 0: rows are swept, 1: columns are swept
    sun_dir: int         # +1: the sun lies towards larger major index, -1 towards smaller
    mu: float            # minor-axis pixels per +1 major index along the ray (|mu| <= 1)
    step_m: float        # horizontal metres per major step along the ray
    tan_el: float


def _ray_geometry(gsd_x_m: float, gsd_y_m: float, sun: Sun) -> _RayGeometry:
    east, north = sun.towards_sun_en
    dc = east / gsd_x_m            # columns per metre towards the sun
    dr = -north / gsd_y_m          # rows per metre towards the sun (rows grow south)
    tan_el = math.tan(math.radians(sun.elevation_deg))
    if abs(dc) >= abs(dr):
        sun_dir = 1 if dc > 0 else -1
        mu = dr / dc
        step = math.hypot(gsd_x_m, mu * gsd_y_m)
        return _RayGeometry(1, sun_dir, mu, step, tan_el)
    sun_dir = 1 if dr > 0 else -1
    mu = dc / dr
    step = math.hypot(gsd_y_m, mu * gsd_x_m)
    return _RayGeometry(0, sun_dir, mu, step, tan_el)


def _round_half_up(x: np.ndarray) -> np.ndarray:
    return np.floor(x + 0.5).astype(np.int64)


def _check_inputs(dsm_m: np.ndarray, gsd_x_m: float, gsd_y_m: float, sun: Sun, where: str) -> np.ndarray:
    if not isinstance(sun, Sun):
        raise ConfigError(f"{where}: sun must be a Sun(azimuth_deg, elevation_deg), got {type(sun).__name__}")
    for name, g in (("gsd_x_m", gsd_x_m), ("gsd_y_m", gsd_y_m)):
        if not (isinstance(g, (int, float, np.floating, np.integer)) and math.isfinite(g) and g > 0):
            raise MapError(f"{where}: {name} = {g!r} must be a positive finite number of metres per pixel")
    dsm = np.asarray(dsm_m)
    if dsm.ndim != 2 or dsm.shape[0] < 1 or dsm.shape[1] < 1:
        raise MapError(f"{where}: dsm_m must be a non-empty (H, W) height array in metres, got shape {dsm.shape}")
    if not np.issubdtype(dsm.dtype, np.number) or np.issubdtype(dsm.dtype, np.complexfloating):
        raise MapError(f"{where}: dsm_m must hold real numbers (metres), got dtype {dsm.dtype}")
    dtype = np.float64 if dsm.dtype == np.float64 else np.float32
    dsm = np.ascontiguousarray(dsm, dtype=dtype)
    if not np.isfinite(dsm.min() + dsm.max()):  # min/max propagate NaN and +-inf
        raise MapError(f"{where}: dsm_m contains NaN or infinite heights; fill no-data (e.g. with the ground "
                       "height) before casting shadows")
    return dsm


def _to_major(a: np.ndarray, major_axis: int) -> np.ndarray:
    """The array with the swept axis first, contiguous (cv2.transpose is much faster than numpy's copy)."""
    if major_axis == 0:
        return a
    if a.dtype in (np.float32, np.float64, np.uint8):
        return cv2.transpose(a)
    return np.ascontiguousarray(a.T)


def _from_major(a: np.ndarray, major_axis: int) -> np.ndarray:
    if major_axis == 0:
        return a
    if a.dtype == np.bool_:
        return cv2.transpose(a.view(np.uint8)).view(np.bool_)
    return _to_major(a, 1)


# ------------------------------------------------------------------------------------------ the sweep


def _sweep(a: np.ndarray, geo: _RayGeometry, soft: bool):
    """Running horizon along the digital lines {(i', j + s(i') - s(i))}, s(i) = round(i * mu), towards the sun.

    ``hor[j]`` at slice i is max over the slices i' beyond i (towards the sun) of h(i', line) - |i' - i| * step *
    tan(el): the highest shadow line cast onto pixel (i, j). Pixel (i, j) is in cast shadow iff a[i, j] < hor[j].
    Moving one slice away from the sun updates it as hor <- shift(max(hor, a[prev]) - step * tan(el)), where the
    shift (-1, 0 or +1 pixel) follows the digital line; so the whole map costs a handful of operations per pixel
    (one compiled loop, ``world.shadows_kernels.sweep``). With ``soft`` the sweep also returns the height margin hor - a
    and the distance to the occluder that set the horizon (for penumbrae).
    """
    from aerial_loc_env.world.shadows_kernels import sweep

    n0, n1 = a.shape
    dtype = a.dtype
    s = _round_half_up(np.arange(n0, dtype=np.float64) * geo.mu)
    drop = dtype.type(geo.step_m * geo.tan_el)
    step = dtype.type(geo.step_m)
    a = np.ascontiguousarray(a)
    if soft:
        margin, dist_out = np.empty((n0, n1), dtype=dtype), np.empty((n0, n1), dtype=dtype)
        sweep(a, s, geo.sun_dir > 0, drop, step, True, np.empty((1, 1), bool), margin, dist_out)
        return margin, dist_out
    mask = np.empty((n0, n1), dtype=bool)
    sweep(a, s, geo.sun_dir > 0, drop, step, False, mask, np.empty((1, 1), dtype), np.empty((1, 1), dtype))
    return mask


class ShadowGrid(NamedTuple):
    """A shadow layer on a possibly coarser grid than the map: ``data`` (h, w) and its ground sample distance."""

    data: np.ndarray
    gsd_x_m: float
    gsd_y_m: float
    factor: int          # map pixels per grid pixel along each axis


def max_pool(dsm: np.ndarray, factor: int) -> np.ndarray:
    """Block maximum: keeps the height of every occluder (thin poles and roof edges still cast shadows).

    Blocks start at multiples of ``factor``; a partial last block takes the maximum of the pixels it has.
    """
    kernel = np.ones((factor, factor), np.uint8)
    grown = cv2.dilate(dsm, kernel, anchor=(0, 0), borderType=cv2.BORDER_REPLICATE)
    return np.ascontiguousarray(grown[::factor, ::factor])


def _check_factor(downsample: int, where: str) -> int:
    if isinstance(downsample, bool) or not isinstance(downsample, (int, np.integer)) or not 1 <= downsample <= 64:
        raise ConfigError(f"{where}: downsample = {downsample!r} must be an integer in [1, 64] "
                          "(map pixels per shadow-grid pixel)")
    return int(downsample)


def cast_shadow_mask(dsm_m: np.ndarray, gsd_x_m: float, gsd_y_m: float, sun: Sun) -> np.ndarray:
    """Boolean (H, W) mask of cast shadows of the height field ``dsm_m`` (metres), in O(pixels).

    Pixel p is shadowed iff some pixel q on the digital line from p towards the sun rises above the sun ray:
    h(q) - dist(p, q) * tan(elevation) > h(p). The digital line takes one pixel per step along the dominant
    axis, at most one pixel off the geometric ray (the tests bound the sweep between ray marches over the
    occluders eroded/dilated by one pixel across the ray). Outside the map nothing casts shadows. Self-shading of
    sloped surfaces is not included (only cast shadows).
    """
    dsm = _check_inputs(dsm_m, gsd_x_m, gsd_y_m, sun, "cast_shadow_mask")
    if sun.elevation_deg >= 90.0:
        return np.zeros(dsm.shape, dtype=bool)
    geo = _ray_geometry(float(gsd_x_m), float(gsd_y_m), sun)
    return _from_major(_sweep(_to_major(dsm, geo.major_axis), geo, soft=False), geo.major_axis)


def cast_shadows(dsm_m: np.ndarray, gsd_x_m: float, gsd_y_m: float, sun: Sun, *,
                 downsample: int = 1) -> ShadowGrid:
    """`cast_shadow_mask` on a grid ``downsample`` times coarser (block maximum of the heights).

    The cost falls with downsample**2; shadow edges move by at most one coarse pixel.
    """
    factor = _check_factor(downsample, "cast_shadows")
    dsm = _check_inputs(dsm_m, gsd_x_m, gsd_y_m, sun, "cast_shadows")
    gx, gy = float(gsd_x_m) * factor, float(gsd_y_m) * factor
    coarse = max_pool(dsm, factor) if factor > 1 else dsm
    return ShadowGrid(cast_shadow_mask(coarse, gx, gy, sun), gx, gy, factor)


def cast_shadow_bruteforce(dsm_m: np.ndarray, gsd_x_m: float, gsd_y_m: float, sun: Sun, *,
                           lines: str = "ray", occluders_m: np.ndarray | None = None) -> np.ndarray:
    """Reference ray march, one pixel per step along the dominant axis (O(pixels * length): small maps only).

    ``lines="ray"`` samples the geometric ray from each pixel centre at the nearest pixel; ``lines="digital"``
    follows the digital lines of the fast sweep (so it must agree exactly). ``occluders_m`` (default ``dsm_m``)
    are the heights tested against the ray, ``dsm_m`` those of the receiving pixels.
    """
    dsm = _check_inputs(dsm_m, gsd_x_m, gsd_y_m, sun, "cast_shadow_bruteforce").astype(np.float64)
    occ = dsm if occluders_m is None else np.asarray(occluders_m, dtype=np.float64)
    if occ.shape != dsm.shape:
        raise MapError(f"cast_shadow_bruteforce: occluders_m shape {occ.shape} != dsm_m shape {dsm.shape}")
    if lines not in ("ray", "digital"):
        raise ConfigError(f"cast_shadow_bruteforce: lines = {lines!r}; use 'ray' or 'digital'")
    if sun.elevation_deg >= 90.0:
        return np.zeros(dsm.shape, dtype=bool)
    geo = _ray_geometry(float(gsd_x_m), float(gsd_y_m), sun)
    a, o = _to_major(dsm, geo.major_axis), _to_major(occ, geo.major_axis)
    n0, n1 = a.shape
    out = np.zeros((n0, n1), dtype=bool)
    cols = np.arange(n1)
    mu_ray = geo.mu * geo.sun_dir    # minor pixels per step along the ray
    for i in range(n0):
        k = 1
        while 0 <= i + geo.sun_dir * k < n0:
            ii = i + geo.sun_dir * k
            if lines == "ray":
                off = int(np.floor(k * mu_ray + 0.5))
            else:
                off = int(np.floor(ii * geo.mu + 0.5) - np.floor(i * geo.mu + 0.5))
            jj = cols + off
            ok = (jj >= 0) & (jj < n1)
            hit = np.zeros(n1, dtype=bool)
            hit[ok] = o[ii, jj[ok]] - k * geo.step_m * geo.tan_el > a[i, ok]
            out[i] |= hit
            k += 1
    return _from_major(out, geo.major_axis)


# ---------------------------------------------------------------------------------------- soft shadows


def _disc_fraction(x: np.ndarray) -> np.ndarray:
    """Fraction of a unit-radius disc below a horizontal line at height x (x in disc radii, float32, no NaN).

    Only the penumbra (-1 < x < 1, well under 1 % of an episode's grid) needs the arcsine: the rest is 0 (x <= -1,
    lit or no occluder) or 1 (x >= 1, umbra), one threshold; the formula runs on the penumbra's pixels alone,
    the same floats as over the whole grid (tests/world/test_shadows.py), and a reset pays the arcsine only there."""
    ends = _disc_formula(np.array([-1.0, 1.0], dtype=x.dtype))
    out = cv2.threshold(x, 0.0, 1.0, cv2.THRESH_BINARY)[1]        # 1 where x > 0, else 0
    if ends[0] != 0.0 or ends[1] != 1.0:                          # (they are 0 and 1 in IEEE arithmetic)
        out = np.where(out > 0, ends[1], ends[0]).astype(x.dtype)
    lo, hi = np.nextafter(x.dtype.type(-1.0), x.dtype.type(0.0)), np.nextafter(x.dtype.type(1.0), x.dtype.type(0.0))
    inner = cv2.findNonZero(cv2.inRange(x, float(lo), float(hi)))
    if inner is not None:
        inner = inner.reshape(-1, 2)                              # (column, row) points ((n, 1, 2) in OpenCV 4)
        cols, rows = inner[:, 0], inner[:, 1]
        out[rows, cols] = _disc_formula(x[rows, cols])
    return out


def _disc_formula(x: np.ndarray) -> np.ndarray:
    """``(x sqrt(1 - x^2) + arcsin x) / pi + 1/2`` for x in [-1, 1]: the disc fraction below height x."""
    root = np.sqrt(1.0 - x * x)
    out = x * root
    out += portable.arcsin(x)
    out *= 1.0 / math.pi
    out += 0.5
    return out


def _angle_above(coarse: np.ndarray, gx: float, gy: float, azimuth_deg: float, el_rad: float) -> np.ndarray:
    """Per pixel, how far (radians, first order) the highest occluder towards ``azimuth_deg`` stands above the
    elevation ``el_rad``: e * cos(el)**2 / D from the sweep's height margin e and occluder distance D. Pixels
    with no occluder get -inf. Returned in map orientation, float32."""
    geo = _ray_geometry(gx, gy, Sun(azimuth_deg % 360.0, math.degrees(el_rad)))
    margin, dist = _sweep(_to_major(coarse, geo.major_axis), geo, soft=True)
    margin *= np.float32(math.cos(el_rad) ** 2)
    np.divide(margin, dist, out=margin)
    return _from_major(margin, geo.major_axis)


def sun_occlusion(dsm_m: np.ndarray, gsd_x_m: float, gsd_y_m: float, sun: Sun, *, downsample: int = 1,
                  penumbra_scale: float = 1.0, antialias_px: float = 0.7, azimuth_samples: int = 1) -> ShadowGrid:
    """Soft cast shadows: float32 field in [0, 1], the fraction of the solar disc hidden (1 = full umbra).

    Approximation (first order in the sun's angular radius rho = 0.265 deg * penumbra_scale): a sweep for the
    lowest limb of the disc (elevation el - rho) gives, per pixel, the height margin e of the highest shadow line
    and the horizontal distance D to the occluder that cast it; that occluder stands e * cos(el - rho)**2 / D
    radians above the limb (sweeping for the limb, not the centre, makes the occluder that wins the running max
    one that actually hides part of the disc), and the hidden fraction is the area of the disc below that
    horizon. This yields the physical penumbra along the sun direction, D * 2 rho / (sin(el) cos(el)) metres on
    flat ground, widening with the shadow length. The lateral edges (parallel to the sun azimuth; physically
    D * 2 rho / cos(el) wide, narrower) are, by default, softened by a Gaussian blur of ``antialias_px`` grid
    pixels only, which also removes the staircase of the digital lines. ``azimuth_samples`` = n > 1 integrates
    the disc over n vertical strips instead (one sweep per strip, at the strip's azimuth, so also the lateral
    penumbrae grow with D; n times the cost). ``penumbra_scale`` > 1 widens penumbrae (haze, camera blur);
    0 gives the hard mask (before the blur). Returns the field on the (possibly coarser) grid; `upsample` brings
    it back to map pixels.
    """
    factor = _check_factor(downsample, "sun_occlusion")
    dsm = _check_inputs(dsm_m, gsd_x_m, gsd_y_m, sun, "sun_occlusion")
    if not (math.isfinite(penumbra_scale) and 0.0 <= penumbra_scale <= 100.0):
        raise ConfigError(f"sun_occlusion: penumbra_scale = {penumbra_scale!r} must be in [0, 100]")
    if not (math.isfinite(antialias_px) and 0.0 <= antialias_px <= 50.0):
        raise ConfigError(f"sun_occlusion: antialias_px = {antialias_px!r} must be in [0, 50]")
    if isinstance(azimuth_samples, bool) or not isinstance(azimuth_samples, (int, np.integer)) \
            or not 1 <= azimuth_samples <= 15:
        raise ConfigError(f"sun_occlusion: azimuth_samples = {azimuth_samples!r} must be an integer in [1, 15]")
    gx, gy = float(gsd_x_m) * factor, float(gsd_y_m) * factor
    coarse = (max_pool(dsm, factor) if factor > 1 else dsm).astype(np.float32, copy=False)
    if sun.elevation_deg >= 90.0:
        return ShadowGrid(np.zeros(coarse.shape, np.float32), gx, gy, factor)
    el = math.radians(sun.elevation_deg)
    rho = math.radians(SUN_ANGULAR_DIAMETER_DEG / 2.0) * penumbra_scale
    if rho == 0.0:
        occ = (_angle_above(coarse, gx, gy, sun.azimuth_deg, el) > 0).astype(np.float32)
    elif azimuth_samples == 1:
        el_low = max(el - rho, 0.5 * el)
        x = _angle_above(coarse, gx, gy, sun.azimuth_deg, el_low)
        x -= np.float32(el - el_low)           # horizon above the disc centre ...
        x *= np.float32(1.0 / rho)             # ... in disc radii
        occ = _disc_fraction(x).astype(np.float32, copy=False)
    else:
        # vertical strips of the disc: centre offset u (radii), half-height c, area weight ~ c
        n = int(azimuth_samples)
        us = -1.0 + (2.0 * np.arange(n) + 1.0) / n
        cs = np.sqrt(1.0 - us * us)
        occ = np.zeros(coarse.shape, np.float32)
        for u, c in zip(us, cs, strict=True):
            el_low = max(el - c * rho, 0.5 * el)
            az = sun.azimuth_deg + math.degrees(u * rho / math.cos(el))
            x = _angle_above(coarse, gx, gy, az, el_low)
            x -= np.float32(el - c * rho - el_low)     # horizon above the strip's bottom ...
            x *= np.float32(1.0 / (2.0 * c * rho))     # ... as a fraction of the strip's height
            np.clip(x, 0.0, 1.0, out=x)
            occ += np.float32(c / cs.sum()) * x
    if antialias_px > 0:
        occ = cv2.GaussianBlur(occ, (0, 0), antialias_px, borderType=cv2.BORDER_REPLICATE)
    return ShadowGrid(occ, gx, gy, factor)


def upsample(grid: ShadowGrid, shape: tuple[int, int]) -> np.ndarray:
    """Bring a coarse shadow field back to map pixels (bilinear, pixel centres aligned) as float32 (H, W)."""
    h, w = int(shape[0]), int(shape[1])
    data = grid.data.astype(np.float32, copy=False)
    if grid.factor == 1:
        if data.shape != (h, w):
            raise MapError(f"upsample: grid shape {data.shape} does not match the map shape {(h, w)}")
        return data
    f = grid.factor
    # coarse pixel centre c covers map pixels [c f, (c+1) f): map pixel u sits at coarse (u + 0.5) / f - 0.5.
    m = np.float32([[1.0 / f, 0.0, 0.5 / f - 0.5], [0.0, 1.0 / f, 0.5 / f - 0.5]])
    return cv2.warpAffine(data, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


# -------------------------------------------------------------------------------------------- shading


def _shadow_gains(strength: float, shadow_ratio: float, sky_tint_rgb: tuple[float, float, float]) -> np.ndarray:
    """Linear-light per-channel gains of full-occlusion pixels: sky light only, with luminance shadow_ratio."""
    tint = np.asarray(sky_tint_rgb, dtype=np.float64)
    luma = float(np.dot(REC709_LUMA, tint))
    sky = np.minimum(shadow_ratio * tint / luma, 1.0)
    return 1.0 - strength * (1.0 - sky)


def _check_shading(strength: float, shadow_ratio: float, sky_tint_rgb, gamma: float, where: str) -> None:
    if not (math.isfinite(strength) and 0.0 <= strength <= 1.0):
        raise ConfigError(f"{where}: strength = {strength!r} must be in [0, 1] (0 = no visible shadow)")
    if not (math.isfinite(shadow_ratio) and 0.0 < shadow_ratio <= 1.0):
        raise ConfigError(f"{where}: shadow_ratio = {shadow_ratio!r} must be in (0, 1] (shadow/sun luminance, "
                          "typically 0.2-0.5)")
    if len(sky_tint_rgb) != 3 or not all(math.isfinite(t) and 0.0 < t <= 1.0 for t in sky_tint_rgb):
        raise ConfigError(f"{where}: sky_tint_rgb = {sky_tint_rgb!r} must be three numbers in (0, 1]")
    if not (math.isfinite(gamma) and 1.0 <= gamma <= 3.0):
        raise ConfigError(f"{where}: gamma = {gamma!r} must be in [1, 3] (2.2 for sRGB-like images)")


def apply_shading(rgb: np.ndarray, occlusion: np.ndarray, strength: float, *, shadow_ratio: float = 0.15,
                  sky_tint_rgb: tuple[float, float, float] = (0.55, 0.65, 0.85), gamma: float = 2.2,
                  out: np.ndarray | None = None) -> np.ndarray:
    """Darken and blue-shift ``rgb`` (H, W, 3) uint8 where the direct sun is occluded; returns uint8.

    Model (linear light): pixel = albedo * (sun + sky). Where a fraction ``occlusion * strength`` of the direct
    sun is removed, channel c is multiplied by 1 - occ * strength * (1 - g_c), where g_c is the sky-only
    fraction: luminance ``shadow_ratio`` with colour ``sky_tint_rgb`` (sky light is bluer). With a power-law
    encoding v = lin ** (1 / gamma), a gain in linear light is the gain ** (1 / gamma) on encoded values, so
    the image is never decoded: the per-channel gains at the occlusion's 256 quantized levels are one table
    (``shading_lut``, cached per strength), and ``shade`` looks each pixel's gain up and multiplies it in, rounded,
    in one compiled pass. ``occlusion`` is (H, W) float in [0, 1] or uint8 (255 = full).
    The sRGB linear toe below 1 % is ignored (error below one grey level).
    """
    _check_shading(strength, shadow_ratio, sky_tint_rgb, gamma, "apply_shading")
    lut = shading_lut(float(strength), shadow_ratio=float(shadow_ratio),
                      sky_tint_rgb=tuple(float(t) for t in sky_tint_rgb), gamma=float(gamma))
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ConfigError(f"apply_shading: rgb must be an (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    occ = np.asarray(occlusion)
    if occ.shape != img.shape[:2]:
        raise ConfigError(f"apply_shading: occlusion shape {occ.shape} must equal the image shape {img.shape[:2]}")
    if occ.dtype != np.uint8:
        if not np.issubdtype(occ.dtype, np.floating):
            raise ConfigError(f"apply_shading: occlusion must be float in [0, 1] or uint8, got {occ.dtype}")
        occ = occ.astype(np.float32, copy=False)
    return shade(img, occ, lut, out=out)


@lru_cache(maxsize=64)
def shading_lut(strength: float, *, shadow_ratio: float = 0.15,
                sky_tint_rgb: tuple[float, float, float] = (0.55, 0.65, 0.85), gamma: float = 2.2) -> np.ndarray:
    """The encoded per-channel shading gains of ``apply_shading`` (read-only (3, 256) uint8, 255 = unchanged):
    row c, column q is channel c's gain at occlusion q / 255. Cached: an episode draws one strength."""
    _check_shading(strength, shadow_ratio, sky_tint_rgb, gamma, "shading_lut")
    q = np.arange(256, dtype=np.float64) / 255.0
    gains = _shadow_gains(strength, shadow_ratio, sky_tint_rgb)
    lin = 1.0 - q[None, :] * (1.0 - gains[:, None])          # (3, 256) linear-light gains
    lut = np.clip(np.rint(255.0 * portable.power(lin, 1.0 / gamma)), 0, 255).astype(np.uint8)
    lut.flags.writeable = False
    return lut


def shade(rgb: np.ndarray, occ: np.ndarray, lut: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """``rgb * lut[c, q] / 255`` per channel, rounded (uint8 (H, W, 3) in, uint8 out; ``out`` may be ``rgb``).

    ``occ`` (H, W): the occlusion quantized to uint8 (q, 255 = no direct sun), or float32 in [0, 1], quantized as
    ``cv2.convertScaleAbs(occ, alpha=255)`` does. One compiled pass (``jit``), bit-identical to
    the OpenCV passes it replaced (three 1-channel LUTs of q, merged, one multiply with scale 1/255). An (H, W, 4)
    ``rgb`` with alpha 255 (the renderer's RGBA map) comes back with q as its alpha (``255 q / 255``): the shaded
    colour and the occlusion in one pass, as ``CameraRenderer.bake`` stores them. Views (map tiles) are fine."""
    from aerial_loc_env.world.shadows_kernels import shade_rows

    _check_shade_args(rgb, occ, lut, out)
    h, w, cn = rgb.shape
    target = np.empty_like(rgb) if out is None else out
    rows = _row_view(target)
    dst = rows if rows is not None else np.empty((h, w * cn), np.uint8)
    src = _row_view(rgb)
    quantized = occ.dtype == np.uint8
    shade_rows(np.ascontiguousarray(rgb).reshape(h, w * cn) if src is None else src,
               occ if quantized else occ.astype(np.float32, copy=False), quantized, lut, dst)
    if rows is None:
        target[...] = dst.reshape(h, w, cn)
    return target


def _check_shade_args(rgb: np.ndarray, occ: np.ndarray, lut: np.ndarray, out: np.ndarray | None) -> None:
    """``shade``'s contract, checked: its kernel (no bounds checks) would read or write out of bounds, or compute
    garbage, on anything else."""
    if not (isinstance(rgb, np.ndarray) and rgb.dtype == np.uint8 and rgb.ndim == 3 and rgb.shape[2] in (3, 4)):
        raise ConfigError(f"shade: rgb must be an (H, W, 3 or 4) uint8 array, got {np.shape(rgb)} "
                          f"{getattr(rgb, 'dtype', type(rgb).__name__)}")
    if not (isinstance(occ, np.ndarray) and occ.shape == rgb.shape[:2]
            and (occ.dtype == np.uint8 or np.issubdtype(occ.dtype, np.floating))):
        raise ConfigError(f"shade: occ must be uint8 or float of shape {rgb.shape[:2]}, got {np.shape(occ)} "
                          f"{getattr(occ, 'dtype', type(occ).__name__)}")
    if not (isinstance(lut, np.ndarray) and lut.dtype == np.uint8 and lut.shape == (3, 256)):
        raise ConfigError(f"shade: lut must be a (3, 256) uint8 array, got {np.shape(lut)} "
                          f"{getattr(lut, 'dtype', type(lut).__name__)}")
    if out is not None and not (isinstance(out, np.ndarray) and out.dtype == np.uint8 and out.shape == rgb.shape
                                and out.flags.writeable):
        raise ConfigError(f"shade: out must be a writeable uint8 array of shape {rgb.shape}, got {np.shape(out)} "
                          f"{getattr(out, 'dtype', type(out).__name__)}")


def _row_view(a: np.ndarray) -> np.ndarray | None:
    """(H, W, C) as an (H, W C) view without a copy (rows may be strided), or None where the pixels of a row are
    not contiguous."""
    if a.strides[2] != a.itemsize or a.strides[1] != a.shape[2] * a.itemsize:
        return None
    return a.reshape(a.shape[0], -1)   # the merged axes are contiguous: numpy reshapes without a copy


def combine_occlusion(*fields: np.ndarray) -> np.ndarray:
    """Occlusion of independent occluders (cast shadow, clouds): the visible sun fractions multiply."""
    if not fields:
        raise ConfigError("combine_occlusion: give at least one occlusion field")
    vis = 1.0 - np.asarray(fields[0], dtype=np.float32)
    for f in fields[1:]:
        vis = vis * (1.0 - np.asarray(f, dtype=np.float32))
    return (1.0 - vis).astype(np.float32, copy=False)


def bake_shadows(rgb: np.ndarray, dsm_m: np.ndarray, gsd_x_m: float, gsd_y_m: float, sun: Sun, strength: float,
                 *, downsample: int = 1, penumbra_scale: float = 1.0, antialias_px: float = 0.7,
                 azimuth_samples: int = 1, shadow_ratio: float = 0.15,
                 sky_tint_rgb: tuple[float, float, float] = (0.55, 0.65, 0.85), gamma: float = 2.2) -> np.ndarray:
    """A copy of the map image with the shadows of ``sun`` (time-of-day mismatch: a database taken at another
    hour than the flight). Same occlusion and shading as the camera frames."""
    img = np.asarray(rgb)
    if img.ndim != 3 or img.shape[:2] != np.shape(dsm_m):
        raise MapError(f"bake_shadows: rgb shape {img.shape} does not match dsm_m shape {np.shape(dsm_m)}")
    grid = sun_occlusion(dsm_m, gsd_x_m, gsd_y_m, sun, downsample=downsample, penumbra_scale=penumbra_scale,
                         antialias_px=antialias_px, azimuth_samples=azimuth_samples)
    occ = upsample(grid, img.shape[:2])
    return apply_shading(img, occ, strength, shadow_ratio=shadow_ratio, sky_tint_rgb=sky_tint_rgb, gamma=gamma)


# --------------------------------------------------------------------------------------------- clouds


class CloudField:
    """Drifting cloud shadows on a coarse periodic world grid (for imagery without a height model).

    Band-limited noise (Gaussian spectra at ``scale_m``, /2, /4: large shapes with ragged edges) made periodic by
    construction (FFT), thresholded at the quantile that gives ``cover``, with a smoothstep ramp about ``edge_m``
    wide across the edges (a cloud 1-2 km up has a 9-19 m penumbra, and its own edges are diffuse; default
    min(20 m, scale_m / 4) so that small clouds keep a core), so the
    covered fraction (occlusion >= 0.5) equals ``cover`` up to one grid cell. The field moves with
    ``drift_mps`` (east, north): occlusion_t(x, y) = occlusion_0(x - vx t, y - vy t).
    Grid pixel (i, j) has its centre at world x = (j + 0.5) cell_m, y = (rows - 0.5 - i) cell_m (north up, like a
    map) and the grid wraps around with a period of at least the extent and 4 * scale_m.
    """

    def __init__(self, rng: np.random.Generator, extent_x_m: float, extent_y_m: float, *, cover: float = 0.4,
                 scale_m: float = 150.0, drift_mps: tuple[float, float] = (3.0, 1.0), edge_m: float | None = None,
                 cell_m: float = 2.0):
        where = "CloudField"
        if edge_m is None:
            edge_m = min(20.0, 0.25 * scale_m)
        for name, v, lo, hi in (("extent_x_m", extent_x_m, 0.0, 1e6), ("extent_y_m", extent_y_m, 0.0, 1e6),
                                ("scale_m", scale_m, 0.0, 1e5), ("cell_m", cell_m, 0.0, 1e3),
                                ("edge_m", edge_m, 0.0, 1e4)):
            if not (math.isfinite(v) and lo < v <= hi):
                raise ConfigError(f"{where}: {name} = {v!r} must be in ({lo}, {hi}]")
        if not (math.isfinite(cover) and 0.0 <= cover <= 1.0):
            raise ConfigError(f"{where}: cover = {cover!r} must be in [0, 1] (fraction of the ground in shadow)")
        if len(drift_mps) != 2 or not all(math.isfinite(v) and abs(v) <= 100.0 for v in drift_mps):
            raise ConfigError(f"{where}: drift_mps = {drift_mps!r} must be (east, north) m/s, |v| <= 100")
        self.cell_m = float(cell_m)
        self.cover = float(cover)
        self.drift_mps = (float(drift_mps[0]), float(drift_mps[1]))
        period = max(4.0 * scale_m, 1.0)
        nx = max(int(math.ceil(max(extent_x_m, period) / cell_m)), 8)
        ny = max(int(math.ceil(max(extent_y_m, period) / cell_m)), 8)
        noise = rng.standard_normal((ny, nx))
        ky = np.fft.fftfreq(ny, d=cell_m)[:, None]
        kx = np.fft.rfftfreq(nx, d=cell_m)[None, :]
        k2 = kx * kx + ky * ky
        spectrum = np.zeros_like(k2)
        for octave in range(3):
            s = scale_m / 2.0 ** octave / 4.0                   # spatial sigma of the octave's kernel
            spectrum += 0.5 ** octave * portable.exp(-2.0 * math.pi ** 2 * s * s * k2)
        spectrum[0, 0] = 0.0
        f = np.fft.irfft2(np.fft.rfft2(noise) * spectrum, s=(ny, nx))
        f = (f - f.mean()) / max(float(f.std()), 1e-12)
        if cover <= 0.0:
            occ = np.zeros_like(f)
        elif cover >= 1.0:
            occ = np.ones_like(f)
        else:
            thr = float(np.quantile(f, 1.0 - cover))
            gy, gx = np.gradient(f, cell_m)
            ramp = edge_m * max(float(np.median(np.hypot(gx, gy))), 1e-12)   # field units across edge_m
            x = np.clip((f - thr) / ramp + 0.5, 0.0, 1.0)
            occ = x * x * (3.0 - 2.0 * x)                        # smoothstep: soft cloud edges
        self.grid = occ.astype(np.float32)

    @property
    def shape(self) -> tuple[int, int]:
        return self.grid.shape

    def _world_to_grid(self, t_s: float) -> np.ndarray:
        """2x3 affine (x_m, y_m, 1) -> grid (col, row) at time t_s."""
        c = self.cell_m
        vx, vy = self.drift_mps
        rows = self.grid.shape[0]
        return np.array([[1.0 / c, 0.0, -vx * t_s / c - 0.5],
                         [0.0, -1.0 / c, rows - 0.5 + vy * t_s / c]])

    def occlusion_image(self, t_s: float, image_to_world: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Occlusion (h, w) float32 seen through an affine ``image_to_world`` (2x3: image (u, v, 1) -> world
        metres), e.g. a camera footprint (CameraModel.camera_to_world) or a map's pixel grid. One cv2.warpAffine
        with BORDER_WRAP."""
        m = np.asarray(image_to_world, dtype=np.float64)
        if m.shape != (2, 3) or not np.isfinite(m).all():
            raise ConfigError(f"CloudField.occlusion_image: image_to_world must be a finite 2x3 affine, got {m.shape}")
        h, w = int(shape[0]), int(shape[1])
        a = self._world_to_grid(float(t_s))
        full = a[:, :2] @ m
        full[:, 2] += a[:, 2]
        ny, nx = self.grid.shape
        full[0, 2] %= nx          # the grid is periodic: keep the offsets small for OpenCV's fixed-point maths
        full[1, 2] %= ny
        return cv2.warpAffine(self.grid, full, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_WRAP)

    def occlusion_at(self, t_s: float, x_m: np.ndarray, y_m: np.ndarray) -> np.ndarray:
        """Occlusion at world points (any matching shapes), bilinear on the periodic grid."""
        x = np.asarray(x_m, dtype=np.float64)
        y = np.asarray(y_m, dtype=np.float64)
        a = self._world_to_grid(float(t_s))
        u = a[0, 0] * x + a[0, 2]
        v = a[1, 1] * y + a[1, 2]
        ny, nx = self.grid.shape
        u0, v0 = np.floor(u), np.floor(v)
        fu, fv = (u - u0).astype(np.float32), (v - v0).astype(np.float32)
        i0 = np.mod(v0.astype(np.int64), ny)
        j0 = np.mod(u0.astype(np.int64), nx)
        i1, j1 = (i0 + 1) % ny, (j0 + 1) % nx
        g = self.grid
        top = g[i0, j0] * (1 - fu) + g[i0, j1] * fu
        bot = g[i1, j0] * (1 - fu) + g[i1, j1] * fu
        return (top * (1 - fv) + bot * fv).astype(np.float32)


# --------------------------------------------------------------------------------------------- config


@dataclass(frozen=True)
class ShadowConfig:
    """Scenario knobs for shadows; build with aerial_loc_env.config.build_config(ShadowConfig, mapping)."""

    sun_azimuth_range_deg: tuple[float, float] = field(
        default=(90.0, 270.0), metadata=rng_meta(0.0, 360.0, doc="towards the sun; lo > hi wraps through north"))
    sun_elevation_range_deg: tuple[float, float] = field(
        default=(25.0, 65.0), metadata=rng_meta(0.0, 90.0, lo_open=True))
    # Clear sky: diffuse light is 10-20 % of the global irradiance at these sun elevations, less where buildings
    # hide part of the sky, so shadowed ground receives about 0.15 of the sunlit irradiance (linear light; about
    # 0.42 of the grey level after a 2.2 gamma, as in ordinary aerial photographs). Haze lowers the contrast.
    strength_range: tuple[float, float] = field(default=(0.8, 1.0), metadata=rng_meta(0.0, 1.0))
    shadow_ratio: float = field(default=0.15, metadata=rng_meta(0.0, 1.0, lo_open=True,
                                                                doc="shadow/sun luminance (linear light)"))
    sky_tint_rgb: tuple[float, float, float] = field(default=(0.55, 0.65, 0.85),
                                                     metadata=rng_meta(0.0, 1.0, lo_open=True))
    gamma: float = field(default=2.2, metadata=rng_meta(1.0, 3.0))
    penumbra_scale: float = field(default=1.0, metadata=rng_meta(0.0, 100.0))
    antialias_px: float = field(default=0.7, metadata=rng_meta(0.0, 50.0))
    penumbra_azimuth_samples: int = field(default=1, metadata=rng_meta(1, 15, doc="n sweeps: lateral penumbrae"))
    downsample: int = field(default=2, metadata=rng_meta(1, 64))
    # time-of-day mismatch: the database carries the shadows of this (azimuth, elevation) sun; None = shadow-free
    database_sun_deg: tuple[float, float] | None = None
    database_strength: float = field(default=1.0, metadata=rng_meta(0.0, 1.0))
    cloud_cover: float = field(default=0.0, metadata=rng_meta(0.0, 1.0, doc="0 disables clouds"))
    cloud_scale_m: float = field(default=150.0, metadata=rng_meta(5.0, 1e5))
    cloud_edge_m: float | None = None    # soft edge width; None = min(20 m, cloud_scale_m / 4)
    cloud_speed_range_mps: tuple[float, float] = field(default=(2.0, 8.0), metadata=rng_meta(0.0, 100.0))
    cloud_cell_m: float = field(default=2.0, metadata=rng_meta(0.0, 1e3, lo_open=True))

    def validate(self, where: str) -> None:
        for name in ("sun_elevation_range_deg", "strength_range", "cloud_speed_range_mps"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ConfigError(f"{where}: field '{name}' = {(lo, hi)!r} needs lo <= hi")
        if len(self.sun_azimuth_range_deg) != 2 or len(self.sun_elevation_range_deg) != 2:
            raise ConfigError(f"{where}: sun ranges must be (lo, hi) pairs")
        if len(self.sky_tint_rgb) != 3:
            raise ConfigError(f"{where}: field 'sky_tint_rgb' must have three values (R, G, B)")
        if self.cloud_edge_m is not None:
            check_value("cloud_edge_m", self.cloud_edge_m, rng_meta(0.0, 1e4, lo_open=True), where)
        if self.database_sun_deg is not None:
            try:
                Sun(*self.database_sun_deg)
            except (ConfigError, TypeError) as exc:
                raise ConfigError(f"{where}: field 'database_sun_deg' = {self.database_sun_deg!r} must be "
                                  f"[azimuth in [0, 360), elevation in (0, 90]] or absent ({exc})") from None

    def draw_sun(self, rng: np.random.Generator) -> Sun:
        return sun_from_ranges(rng, self.sun_azimuth_range_deg, self.sun_elevation_range_deg)

    def draw_strength(self, rng: np.random.Generator) -> float:
        lo, hi = self.strength_range
        return float(lo + (hi - lo) * rng.random())

    def draw_clouds(self, rng: np.random.Generator, extent_x_m: float, extent_y_m: float,
                    duration_s: float = 0.0) -> CloudField | None:
        """A cloud field with a random drift direction and speed, or None when cloud_cover is 0.

        The (periodic) field spans at least the extent plus the drift over ``duration_s``, so that a window of
        that extent (where an episode flies, not the whole map) sees no repeat while the clouds drift."""
        if self.cloud_cover <= 0.0:
            return None
        lo, hi = self.cloud_speed_range_mps
        speed = lo + (hi - lo) * rng.random()
        heading = 2.0 * math.pi * rng.random()
        vx, vy = speed * math.cos(heading), speed * math.sin(heading)
        return CloudField(rng, extent_x_m + abs(vx) * duration_s, extent_y_m + abs(vy) * duration_s,
                          cover=self.cloud_cover, scale_m=self.cloud_scale_m, drift_mps=(vx, vy),
                          edge_m=self.cloud_edge_m, cell_m=self.cloud_cell_m)

    def database_image(self, rgb: np.ndarray, dsm_m: np.ndarray | None, gsd_x_m: float,
                       gsd_y_m: float) -> np.ndarray:
        """The database image: ``rgb`` itself, or a copy with the shadows of ``database_sun_deg`` baked in."""
        if self.database_sun_deg is None:
            return rgb
        if dsm_m is None:
            raise MapError("ShadowConfig.database_sun_deg needs a map with a height model (dsm_m); this map has "
                           "none: remove database_sun_deg or use a map with a DSM")
        return bake_shadows(rgb, dsm_m, gsd_x_m, gsd_y_m, Sun(*self.database_sun_deg), self.database_strength,
                            downsample=self.downsample, penumbra_scale=self.penumbra_scale,
                            antialias_px=self.antialias_px, azimuth_samples=self.penumbra_azimuth_samples,
                            **self.shading_kwargs())

    def shading_kwargs(self) -> dict:
        """Keyword arguments of apply_shading / bake_shadows taken from this config."""
        return {"shadow_ratio": self.shadow_ratio, "sky_tint_rgb": self.sky_tint_rgb, "gamma": self.gamma}
