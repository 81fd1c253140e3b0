"""The embedded default map: a procedural city, deterministic from a seed, cached on disk.

The estimators are compared on how they cope with the difference between the map and the camera, so the map
must look like a real city from 200 m: a jittered street network with arterials (20-30 m) and local streets
(8-12 m), a diagonal avenue, a river with a curved riverside road and bridges, lane markings and crosswalks,
sidewalks; blocks subdivided into parcels with houses (tiled gable/hip roofs), mid-rise blocks, downtown
towers on podiums, Korean-style apartment slabs, warehouses, parks, schools with running tracks, parking
lots with painted bays, cars and trees. Heights: buildings 3-60 m (taller downtown), trees 5-20 m, cars
1.5 m. Texture comes at several scales (per-object colour, 6 m and 1 m noise, pixel grain, a 60 m light
field), so no camera footprint is featureless and nothing repeats.

``generate_city(config)`` draws it (seconds for the default 1200 m x 1400 m at 0.25 m/px);
``default_city(config)`` returns it from the cache (``paths.cache_dir("maps")``), memory-mapped, generating
and writing it atomically on the first call.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from aerial_loc_env.config import build_config, config_to_dict
from aerial_loc_env.config import rng as crange
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.pages import small_pages
from aerial_loc_env.paths import cache_dir
from aerial_loc_env.world.city.content import Filler, choose_use, paint_scene
from aerial_loc_env.world.city.layout import build_layout
from aerial_loc_env.world.city.paint import Canvas
from aerial_loc_env.world.city.roads import paint_roads
from aerial_loc_env.world.maps.cache import cached_bundle, spec_key
from aerial_loc_env.world.maps.geo import LocalTangentGeoref
from aerial_loc_env.world.maps.landcover import LandCover
from aerial_loc_env.world.maps.orthomap import Orthomap

#: Largest map generated (pixels): 150 Mpx is ~1.2 GB of layers while drawing.
MAX_PIXELS = 150_000_000

#: Bump whenever the generator's output changes for a given config: it is part of the cache key.
GENERATOR_VERSION = 5



@dataclass(frozen=True)
class CityConfig:
    """Parameters of the procedural city (build with ``aerial_loc_env.config.build_config``).

    The defaults give the paper's 1200 m x 1400 m database at 0.25 m/px (4800 x 5600 px), georeferenced on
    the tangent plane at (origin_lat_deg, origin_lon_deg), which is the map's south-west outer corner, i.e.
    the world-frame origin; the default is near Hanam, Korea, the reference paper's flight site.
    """

    seed: int = field(default=0, metadata=crange(0, 2**63 - 1))
    width_m: float = field(default=1200.0, metadata=crange(200.0, 8000.0, doc="east-west extent"))
    height_m: float = field(default=1400.0, metadata=crange(200.0, 8000.0, doc="north-south extent"))
    gsd_m: float = field(default=0.25, metadata=crange(0.1, 2.0, doc="ground sampling distance"))
    origin_lat_deg: float = field(default=37.54, metadata=crange(-85.0, 85.0))
    origin_lon_deg: float = field(default=127.21, metadata=crange(-180.0, 180.0))
    building_density: float = field(default=1.0, metadata=crange(0.0, 1.2, doc="share of parcels built on"))
    tree_density: float = field(default=1.0, metadata=crange(0.0, 3.0, doc="tree multiplier"))
    car_density: float = field(default=1.0, metadata=crange(0.0, 3.0, doc="traffic and parking multiplier"))
    park_fraction: float = field(default=0.08, metadata=crange(0.0, 0.6, doc="share of blocks that are parks"))
    street_removal: float = field(default=0.12, metadata=crange(0.0, 0.5, doc="share of local streets dropped"))
    downtown_radius_m: float = field(default=350.0, metadata=crange(50.0, 5000.0))
    max_building_height_m: float = field(default=60.0, metadata=crange(6.0, 300.0))
    river: bool = True
    name: str = "city"

    def validate(self, where: str) -> None:
        if self.name.strip() == "" or "/" in self.name:
            raise ConfigError(f"{where}: field 'name' = {self.name!r} must be a non-empty name without '/'")
        w_px, h_px = self.size_px
        if w_px * h_px > MAX_PIXELS:
            raise ConfigError(f"{where}: width_m x height_m at gsd_m = {self.gsd_m} gives {w_px} x {h_px} px, "
                              f"more than the {MAX_PIXELS / 1e6:.0f} Mpx allowed; use a coarser gsd_m or a "
                              "smaller map")

    @property
    def size_px(self) -> tuple[int, int]:
        """(width_px, height_px) of the generated map."""
        return int(round(self.width_m / self.gsd_m)), int(round(self.height_m / self.gsd_m))

    def cache_key(self) -> str:
        return spec_key({"generator": GENERATOR_VERSION, **config_to_dict(self)})


def height_ranges_m(config: CityConfig | None = None) -> dict[LandCover, tuple[float, float]]:
    """Documented dsm_m range (metres above ground) per land-cover class; classes not listed are at 0 m.

    Buildings stand 3 m up to ``max_building_height_m`` (ridges and rooftop units included), tree canopies
    5-20 m (rim to crown), cars 1.5 m, parcel walls 1.2 m.
    """
    hmax = (config if config is not None else CityConfig()).max_building_height_m
    return {LandCover.BUILDING: (3.0, hmax), LandCover.ROOF_EQUIPMENT: (3.0, hmax), LandCover.TREE: (5.0, 20.0),
            LandCover.CAR: (1.5, 1.5), LandCover.WALL: (1.2, 1.2)}


def small_city_config(seed: int = 0, **overrides) -> CityConfig:
    """A 400 m x 400 m city (1600 x 1600 px): small enough for unit tests, still streets, blocks and a river."""
    return build_config(CityConfig, {"seed": seed, "width_m": 400.0, "height_m": 400.0,
                                     "downtown_radius_m": 200.0, **overrides}, where="small_city_config")


def _ground(rng: np.random.Generator, w_px: int, h_px: int, gsd_m: float) -> np.ndarray:
    """Unbuilt land: grass with patches of drier and lusher grass, varying at ~40 m."""
    cell = max(1, int(round(40.0 / gsd_m)))
    ch, cw = h_px // cell + 3, w_px // cell + 3
    mix = rng.random((ch, cw)).astype(np.float32)
    lush = np.array([78, 118, 56], np.float32)
    dry = np.array([150, 146, 96], np.float32)
    coarse = lush + (dry - lush) * (mix[..., None] ** 2)
    big = cv2.resize(np.clip(coarse, 0, 255).astype(np.uint8), ((cw - 1) * cell, (ch - 1) * cell),
                     interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(big[:h_px, :w_px])


def generate_city(config: CityConfig | None = None) -> Orthomap:
    """Draw the city described by ``config`` (uncached); every random draw comes from its seed. Its many
    full-map planes, each filled once, take normal memory pages (``pages.small_pages``)."""
    cfg = config if config is not None else CityConfig()
    if not isinstance(cfg, CityConfig):
        raise ConfigError(f"generate_city: expected a CityConfig, got {type(cfg).__name__}; build one with "
                       "aerial_loc_env.config.build_config(CityConfig, {...})")
    with small_pages():
        return _generate(cfg)


def _generate(cfg: CityConfig) -> Orthomap:
    w_px, h_px = cfg.size_px
    seeds = np.random.SeedSequence([cfg.seed, 0xC17]).spawn(5)
    r_layout, r_content, r_roads, r_ground, r_texture = (np.random.default_rng(s) for s in seeds)

    layout = build_layout(r_layout, cfg.width_m, cfg.height_m, river=cfg.river,
                          downtown_radius_m=cfg.downtown_radius_m, street_removal=cfg.street_removal)
    uses: dict[int, str] = {}
    for b in layout.blocks:
        if b.group not in uses:
            members = np.vstack([bb.inner for bb in layout.blocks if bb.group == b.group])
            uses[b.group] = choose_use(r_layout, layout.downtown(members.mean(axis=0)), cfg.park_fraction)
            b.use = uses[b.group]
        elif uses[b.group] == "school":     # a school has one sports ground: the rest of it is its park
            b.use = "park"
        elif uses[b.group] in ("parking", "construction"):   # never a whole superblock of these
            b.use = choose_use(r_layout, layout.downtown(b.inner.mean(axis=0)), cfg.park_fraction)
        else:                               # merged blocks share the use (apartment complexes, parks)
            b.use = uses[b.group]

    canvas = Canvas(_ground(r_ground, w_px, h_px, cfg.gsd_m), cfg.gsd_m)
    filler = Filler(layout, r_content, building_density=cfg.building_density, tree_density=cfg.tree_density,
                    car_density=cfg.car_density, max_height_m=cfg.max_building_height_m)
    for b in layout.blocks:
        filler.fill(b)
    paint_scene(canvas, filler.scene, r_content)
    paint_roads(canvas, layout, filler, r_roads)

    rgb = canvas.textured_rgb(r_texture)
    classes = canvas.classes()
    georef = LocalTangentGeoref(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.gsd_m, cfg.gsd_m,
                                origin_u_px=-0.5, origin_v_px=h_px - 0.5)
    return Orthomap(rgb=rgb, gsd_x_m=cfg.gsd_m, gsd_y_m=cfg.gsd_m, georef=georef, dsm_m=canvas.dsm_m,
                    classes=classes, name=cfg.name,
                    source=f"procedural city v{GENERATOR_VERSION} seed={cfg.seed}")


def city_cache_path(config: CityConfig | None = None) -> Path:
    """Where ``default_city(config)`` keeps its bundle (under $XDG_CACHE_HOME/aerial_loc_env/maps)."""
    cfg = config if config is not None else CityConfig()
    return cache_dir("maps") / f"{cfg.name}-{cfg.cache_key()}.alm"


def default_city(config: CityConfig | None = None) -> Orthomap:
    """The procedural city for ``config`` (default: the paper-sized default city), memory-mapped from the cache.

    The first call generates and saves the bundle atomically; later calls (any process) only map it
    (``maps.cache.cached_bundle``: a corrupt or foreign entry is rebuilt with a warning).
    """
    cfg = config if config is not None else CityConfig()
    return cached_bundle(city_cache_path(cfg), lambda: generate_city(cfg),
                         {"generator": "aerial_loc_env.world.city", "generator_version": GENERATOR_VERSION,
                          "config": config_to_dict(cfg)}, cfg.size_px)


__all__ = ["CityConfig", "GENERATOR_VERSION", "city_cache_path", "default_city",
           "generate_city", "height_ranges_m", "small_city_config"]
