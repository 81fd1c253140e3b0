"""The map database as real maps are acquired: another sensor, another viewpoint, a georeference that is off.

A real orthophoto or satellite map is not the ground seen by the drone's camera. It was taken by another sensor
(its own colour response and white balance, coarser ground sampling, optics and atmosphere blur, haze that
lowers the contrast, JPEG compression when delivered), from another viewpoint (a standard, not true, orthophoto
shows buildings leaning away from the satellite's nadir: a roof at height h is displaced by ``h tan(theta)``
along the lean direction and the facade facing the sensor is visible), and it is registered to the world with
an error of a few metres. ``AcquisitionConfig`` (the scenario's ``[database]`` section) describes that;
``acquire(rgb, dsm_m, gsd_x_m, gsd_y_m, config)`` turns the ground's image into the database image.

The database's sun (shadows baked in at another time of day) is ``ShadowConfig.database_sun_deg``; it is baked
before this model runs (shadows lie on the scene; the sensor then sees them). Every field defaults to "off",
and a config with every field off returns its input unchanged (the same array). ``acquire_map`` makes the whole
database (other sun, then sensor) from a map; ``database_city`` does it for the procedural city once, cached on
disk beside the city's bundle (``world/maps/cache.py``), since the building lean alone costs seconds per process.

Order of the pipeline (the physical order of a real acquisition): building lean (the viewpoint), optics blur,
sampling at the sensor's ground sampling distance, colour response (white balance, tone, saturation, contrast,
haze), JPEG at that resolution, resampling back onto the map grid, and the georeference bias last.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import config_to_dict, rng
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.world.maps.cache import cached_bundle, spec_key
from aerial_loc_env.world.maps.orthomap import Orthomap

#: Bump whenever ``acquire``'s output changes for the same inputs (the benchmark's fingerprint, env/fingerprint.py).
GENERATOR_VERSION = 2


@dataclass(frozen=True)
class AcquisitionConfig:
    """How the map database was acquired (the ``[database]`` section); every default means "as the ground is".

    - ``gsd_m``: ground sampling distance of the acquiring sensor (metres/pixel); the image is sampled there and
      resampled back onto the map grid (bicubic). None = the map's own; a value at or below the map's own
      changes nothing (the map cannot gain detail it does not have).
    - ``blur_m``: Gaussian blur sigma on the ground (optics, motion, atmosphere), metres.
    - ``jpeg_quality``: JPEG quality of the delivered product at the sensor's resolution (0 = no JPEG).
    - ``gain_rgb``: white balance, a gain per channel; ``tone_gamma``: output = 255 (input / 255) ** tone_gamma.
    - ``saturation``: 1 keeps colours, 0 is grey; ``contrast``: scales deviations from the image mean.
    - ``haze``: fraction of airlight ``haze_rgb`` mixed into every pixel (0 = clear air).
    - ``georef_bias_m``: (east, north) metres by which the content sits off its stated georeference: the ground
      at world (x, y) appears in the database where the georeference says (x + east, y + north).
    - ``lean_deg``: off-nadir angle of a standard orthophoto's sensor (0 = a true orthophoto);
      ``lean_azimuth_deg``: compass bearing (clockwise from north) towards which tall things lean.
    """

    gsd_m: float | None = None
    blur_m: float = field(default=0.0, metadata=rng(0.0, 20.0))
    jpeg_quality: int = field(default=0, metadata=rng(0, 100, doc="0 = no JPEG"))
    gain_rgb: tuple[float, float, float] = field(default=(1.0, 1.0, 1.0), metadata=rng(0.25, 4.0))
    tone_gamma: float = field(default=1.0, metadata=rng(0.25, 4.0))
    saturation: float = field(default=1.0, metadata=rng(0.0, 3.0))
    contrast: float = field(default=1.0, metadata=rng(0.1, 3.0))
    haze: float = field(default=0.0, metadata=rng(0.0, 1.0))
    haze_rgb: tuple[float, float, float] = field(default=(196.0, 202.0, 212.0), metadata=rng(0.0, 255.0))
    georef_bias_m: tuple[float, float] = field(default=(0.0, 0.0), metadata=rng(-500.0, 500.0))
    lean_deg: float = field(default=0.0, metadata=rng(0.0, 60.0))
    lean_azimuth_deg: float = field(default=0.0, metadata=rng(0.0, 360.0, hi_open=True))

    def validate(self, where: str) -> None:
        if self.gsd_m is not None and not (0.0 < self.gsd_m <= 100.0):
            raise ConfigError(f"{where}: field 'gsd_m' = {self.gsd_m!r} is out of range; allowed (0, 100] metres "
                              "per pixel, or leave it unset for the map's own")
        if len(self.gain_rgb) != 3 or len(self.haze_rgb) != 3:
            raise ConfigError(f"{where}: fields 'gain_rgb' and 'haze_rgb' need three values (R, G, B)")
        if len(self.georef_bias_m) != 2:
            raise ConfigError(f"{where}: field 'georef_bias_m' needs two values (east_m, north_m)")
        if 0 < self.jpeg_quality < 5:
            raise ConfigError(f"{where}: field 'jpeg_quality' = {self.jpeg_quality} is below 5, which no map "
                              "product uses; use 0 (no JPEG) or 5-100")

    @property
    def is_identity(self) -> bool:
        """True when the database is the ground's image itself (every field off)."""
        return (self.gsd_m is None and self.blur_m == 0.0 and self.jpeg_quality == 0
                and tuple(self.gain_rgb) == (1.0, 1.0, 1.0) and self.tone_gamma == 1.0 and self.saturation == 1.0
                and self.contrast == 1.0 and self.haze == 0.0 and tuple(self.georef_bias_m) == (0.0, 0.0)
                and self.lean_deg == 0.0)

    @property
    def needs_dsm(self) -> bool:
        return self.lean_deg > 0.0


# ------------------------------------------------------------------------------------------- viewpoint
def lean_offsets_px(gsd_x_m: float, gsd_y_m: float, lean_deg: float, lean_azimuth_deg: float,
                    height_m: float) -> tuple[float, float]:
    """(du, dv) map pixels by which a point ``height_m`` up is displaced in a standard orthophoto."""
    d = height_m * math.tan(math.radians(lean_deg))
    az = math.radians(lean_azimuth_deg)
    return d * math.sin(az) / gsd_x_m, -d * math.cos(az) / gsd_y_m


def _march_tile(dsm: np.ndarray, best: np.ndarray, wall: np.ndarray, tile: tuple[int, int, int, int], ux: float,
                uy: float, dz: float, top_m: float) -> None:
    """The ray march of ``lean_buildings`` over one tile of the output, up to the height ``top_m`` it can meet."""
    h, w = dsm.shape
    y0, y1, x0, x1 = tile
    for k in range(1, int(math.ceil(top_m / dz + 0.5)) + 1):
        du, dv = int(round(k * ux)), int(round(k * uy))
        # the point k steps back towards the sensor: dst[v, u] looks at dsm[v - dv, u - du] (off the map: nothing)
        a0, a1 = max(y0, dv), min(y1, h + dv)
        b0, b1 = max(x0, du), min(x1, w + du)
        if a0 >= a1 or b0 >= b1:
            break
        src = dsm[a0 - dv:a1 - dv, b0 - du:b1 - du]
        z = k * dz
        c = src >= z - 0.5 * dz
        np.copyto(best[a0:a1, b0:b1], k, where=c)
        np.copyto(wall[a0:a1, b0:b1], src >= z + 0.5 * dz, where=c)


def lean_buildings(rgb: np.ndarray, dsm_m: np.ndarray, gsd_x_m: float, gsd_y_m: float, lean_deg: float,
                   lean_azimuth_deg: float, *, facade_gain: float = 0.62,
                   floor_m: float = 3.0) -> tuple[np.ndarray, np.ndarray]:
    """The image as an oblique sensor ``lean_deg`` off nadir maps it onto the ground (a standard orthophoto).

    Each output pixel shows the first surface its view ray meets coming down from the sensor: the highest step
    ``k`` along the ray with ``dsm(p - k * step) >= z_k`` (a march over the height field, one shifted comparison
    per step of one pixel, vectorized over the map). A surface met well above the ray's height there is a wall:
    it gets the colour of the roof edge above it, darkened, with a darker band per floor. Returns the image and
    the boolean facade mask.
    """
    img = np.asarray(rgb)
    dsm = np.asarray(dsm_m, dtype=np.float32)
    if img.ndim != 3 or img.shape[:2] != dsm.shape:
        raise MapError(f"lean_buildings: rgb shape {img.shape} does not match dsm_m shape {dsm.shape}")
    tan_t = math.tan(math.radians(lean_deg))
    if tan_t <= 0.0 or float(dsm.max(initial=0.0)) <= 0.0:
        return img, np.zeros(dsm.shape, bool)
    g = min(gsd_x_m, gsd_y_m)
    az = math.radians(lean_azimuth_deg)
    ux, uy = math.sin(az) * g / gsd_x_m, -math.cos(az) * g / gsd_y_m      # pixels per step (one step = g metres)
    dz = g / tan_t                                                        # ray height gained per step
    n_steps = int(math.ceil(float(dsm.max()) * tan_t / g)) + 1
    h, w = dsm.shape
    best = np.zeros((h, w), np.int32)
    wall = dsm >= 0.5 * dz           # met at the ground by no higher surface: the ray ends inside a wall
    tile = 256
    reach_u, reach_v = int(round(n_steps * ux)), int(round(n_steps * uy))
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(h, y0 + tile), min(w, x0 + tile)
            # the tallest thing a ray into this tile can meet (the tile and its reach towards the sensor)
            box = dsm[max(0, min(y0, y0 - reach_v)):min(h, max(y1, y1 - reach_v)),
                      max(0, min(x0, x0 - reach_u)):min(w, max(x1, x1 - reach_u))]
            _march_tile(dsm, best, wall, (y0, y1, x0, x1), ux, uy, dz, float(box.max(initial=0.0)))
    steps = np.arange(n_steps + 1)
    du_k = np.array([round(k * ux) for k in steps], np.float32)      # the march's own rounding, per step
    dv_k = np.array([round(k * uy) for k in steps], np.float32)
    map_u = np.arange(w, dtype=np.float32)[None, :] - du_k[best]
    map_v = np.arange(h, dtype=np.float32)[:, None] - dv_k[best]
    out = cv2.remap(np.ascontiguousarray(img), map_u, map_v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    ks = best
    if np.any(wall):
        z = np.maximum(ks * dz, 0.5 * floor_m)[wall]
        banded = np.where(np.mod(z, floor_m) < 0.35 * floor_m, 0.72, 1.0)
        out[wall] = np.clip(out[wall].astype(np.float32) * (facade_gain * banded)[:, None], 0, 255).astype(
            np.uint8)
    return out, wall


# ------------------------------------------------------------------------------------------- sensor
def _colour_response(img: np.ndarray, cfg: AcquisitionConfig) -> np.ndarray:
    x = img.astype(np.float32) / 255.0
    if cfg.gain_rgb != (1.0, 1.0, 1.0):
        x *= np.asarray(cfg.gain_rgb, np.float32)
    if cfg.tone_gamma != 1.0:
        x = portable.power(np.clip(x, 0.0, 1.0), np.float32(cfg.tone_gamma))
    if cfg.saturation != 1.0:
        grey = portable.matmul(x.reshape(-1, 3), np.array([0.299, 0.587, 0.114], np.float32)).reshape(x.shape[:-1])
        x = grey[..., None] + np.float32(cfg.saturation) * (x - grey[..., None])
    if cfg.contrast != 1.0:
        mean = x.reshape(-1, 3).mean(axis=0)
        x = mean + np.float32(cfg.contrast) * (x - mean)
    if cfg.haze > 0.0:
        air = np.asarray(cfg.haze_rgb, np.float32) / 255.0
        x = (1.0 - np.float32(cfg.haze)) * x + np.float32(cfg.haze) * air
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


def _jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:       # pragma: no cover - OpenCV always encodes a uint8 RGB image
        raise MapError("acquire: JPEG encoding failed")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def shift_image(img: np.ndarray, east_m: float, north_m: float, gsd_x_m: float, gsd_y_m: float, *,
                interpolation: int = cv2.INTER_LINEAR) -> np.ndarray:
    """The content moved ``east_m``, ``north_m`` on the map grid (rows grow south); borders replicate."""
    m = np.array([[1.0, 0.0, east_m / gsd_x_m], [0.0, 1.0, -north_m / gsd_y_m]])
    h, w = img.shape[:2]
    return cv2.warpAffine(np.ascontiguousarray(img), m, (w, h), flags=interpolation,
                          borderMode=cv2.BORDER_REPLICATE)


def acquire(rgb: np.ndarray, dsm_m: np.ndarray | None, gsd_x_m: float, gsd_y_m: float,
            config: AcquisitionConfig) -> np.ndarray:
    """The database image of the ground image ``rgb`` (uint8 (H, W, 3)) as ``config``'s sensor delivers it."""
    cfg = config
    img = np.asarray(rgb)
    if cfg.is_identity:
        return rgb
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
        raise MapError(f"acquire: expected a uint8 (H, W, 3) image, got {img.dtype} {img.shape}")
    h, w = img.shape[:2]
    if cfg.lean_deg > 0.0:
        if dsm_m is None:
            raise MapError("database.lean_deg needs a map with a height model (dsm_m); this map has none: set "
                           "lean_deg = 0 or use a map with a DSM")
        img, _ = lean_buildings(img, dsm_m, gsd_x_m, gsd_y_m, cfg.lean_deg, cfg.lean_azimuth_deg)
    g = math.sqrt(gsd_x_m * gsd_y_m)
    if cfg.blur_m > 0.0:
        img = cv2.GaussianBlur(np.ascontiguousarray(img), (0, 0), sigmaX=cfg.blur_m / gsd_x_m,
                               sigmaY=cfg.blur_m / gsd_y_m)
    coarse = cfg.gsd_m is not None and cfg.gsd_m > g * 1.0001
    if coarse:
        f = cfg.gsd_m / g
        cw, ch = max(1, int(round(w / f))), max(1, int(round(h / f)))
        img = cv2.resize(np.ascontiguousarray(img), (cw, ch), interpolation=cv2.INTER_AREA)
    img = _colour_response(img, cfg)
    if cfg.jpeg_quality > 0:
        img = _jpeg(img, cfg.jpeg_quality)
    if coarse:
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC)
    bx, by = cfg.georef_bias_m
    if bx != 0.0 or by != 0.0:
        img = shift_image(img, bx, by, gsd_x_m, gsd_y_m)
    return img


def acquire_layer(layer: np.ndarray, gsd_x_m: float, gsd_y_m: float, config: AcquisitionConfig) -> np.ndarray:
    """A map layer (DSM, classes, no-data) carried along with the image's georeference bias (nearest)."""
    bx, by = config.georef_bias_m
    if bx == 0.0 and by == 0.0:
        return layer
    a = np.asarray(layer)
    src = a.view(np.uint8) if a.dtype == bool else a
    out = shift_image(src, bx, by, gsd_x_m, gsd_y_m, interpolation=cv2.INTER_NEAREST)
    return out.astype(bool) if a.dtype == bool else out


# ------------------------------------------------------------------------------------------- the database map
def database_is_identity(shadows: Any, config: AcquisitionConfig | None) -> bool:
    """True when the database is the surveyed map itself: no other sun baked in, no acquisition model."""
    return shadows.database_sun_deg is None and (config is None or config.is_identity)


def acquire_map(orthomap: Orthomap, shadows: Any, config: AcquisitionConfig | None) -> Orthomap:
    """The map database made from ``orthomap`` (the surveyed ground, epoch A): with
    ``shadows.database_sun_deg`` (a ``ShadowConfig``) the shadows of that other sun baked in, then as
    ``config``'s sensor acquired it; the height, class and no-data layers carry the georeference bias along.
    ``orthomap`` itself when both are off."""
    if database_is_identity(shadows, config):
        return orthomap
    gx, gy = orthomap.gsd_x_m, orthomap.gsd_y_m
    rgb = shadows.database_image(orthomap.rgb, orthomap.dsm_m, gx, gy)
    layers: dict[str, np.ndarray] = {}
    if config is not None and not config.is_identity:
        rgb = acquire(rgb, orthomap.dsm_m, gx, gy, config)
        layers = {name: acquire_layer(getattr(orthomap, name), gx, gy, config)
                  for name in ("dsm_m", "classes", "nodata") if getattr(orthomap, name) is not None}
    return dataclasses.replace(orthomap, rgb=rgb, name=f"{orthomap.name}-database", **layers)


def _database_spec(city_config: Any, shadows: Any, config: AcquisitionConfig | None) -> dict[str, Any]:
    """Everything the database of a procedural city depends on (its cache key and provenance). The other sun's
    shadows depend on the whole ``[shadows]`` section and the shadow generator only when that sun is set."""
    from aerial_loc_env.world import shadows as shadow_module
    from aerial_loc_env.world.city.generator import GENERATOR_VERSION as CITY_VERSION

    sun = shadows.database_sun_deg is not None
    return {"generator": "aerial_loc_env.world.maps.acquisition", "generator_version": GENERATOR_VERSION,
            "city_generator_version": CITY_VERSION, "city": config_to_dict(city_config),
            "shadow_generator_version": shadow_module.GENERATOR_VERSION if sun else None,
            "shadows": config_to_dict(shadows) if sun else None,
            "database": None if config is None else config_to_dict(config)}


def database_cache_path(city_config: Any, shadows: Any, config: AcquisitionConfig | None) -> Path:
    """Where ``database_city`` keeps the database of the city ``city_config`` (beside the city's bundle)."""
    from aerial_loc_env.paths import cache_dir

    key = spec_key(_database_spec(city_config, shadows, config))
    return cache_dir("maps") / f"{city_config.name}-{city_config.cache_key()}-database-{key}.alm"


def database_city(city_config: Any, shadows: Any, config: AcquisitionConfig | None) -> Orthomap:
    """The map database of the procedural city ``city_config`` (``acquire_map`` of its epoch A), memory-mapped
    from the cache: built once on first use by any process (lean, other sun, sensor: seconds), then only mapped.
    The key holds the city spec, the ``[database]`` section, the ``[shadows]`` section when the database has its
    own sun, and the generator versions of the city, the shadows and this module; the epoch flown (``[epoch]``)
    does not enter: the database is the surveyed epoch A whatever the camera sees."""
    from aerial_loc_env.world.city import default_city

    base = default_city(city_config)
    if database_is_identity(shadows, config):
        return base
    return cached_bundle(database_cache_path(city_config, shadows, config),
                         lambda: acquire_map(base, shadows, config),
                         _database_spec(city_config, shadows, config), size_px=(base.width_px, base.height_px))


__all__ = ["AcquisitionConfig", "acquire", "acquire_layer", "acquire_map", "database_cache_path", "database_city",
           "database_is_identity", "lean_buildings", "lean_offsets_px", "shift_image"]
