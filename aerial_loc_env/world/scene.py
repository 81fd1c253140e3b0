"""The world a scenario flies over, assembled in one place and cached by content.

A scenario names its world by five configs (``WorldSpec``): the map source (the procedural city or a file),
the city's parameters, the epoch the camera flies in, the shadow settings (the database may carry another
sun's shadows) and the map database's acquisition. ``build_world(spec)`` turns them into a ``World``:

- ``surveyed``: epoch A, the ground when the map was made;
- ``ground``: the ground the camera sees (epoch B of it, or ``surveyed`` itself);
- ``database``: the map the estimators get (``surveyed`` itself, or with another sun's shadows baked in and/or
  as another sensor acquired it);
- the height model's derived products (its maximum, its block maxima on a shadow grid) and the flyable region
  for a clearance, each made once per world.

Every piece is cached per process under a key made of what it is built from (the configs' values, and for a
map file its resolved path, size and modification time), never of object identities: two scenarios with the
same city share one memory-mapped copy of it, and a map file changed on disk is read again. The procedural
city, its epochs and its acquired databases are also cached on disk (``maps/cache.py``), so other processes
(vectorized workers) map the same files.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from aerial_loc_env.config import check_value, config_to_dict, rng
from aerial_loc_env.errors import ConfigError, MapError

if TYPE_CHECKING:   # the scenario specs import this module: the maps load on first use
    from aerial_loc_env.world.maps.orthomap import Orthomap
    from aerial_loc_env.world.maps.region import FlyableRegion


@dataclass(frozen=True)
class MapConfig:
    """Which map the vehicle flies over: the procedural city, a file (``path`` required), or a real two-epoch
    pair (``kind = "pair"``: ``path_a`` the map database's epoch, ``path_b`` the camera's; ``world/maps/pairs.py``).

    For a pair, ``gsd_m`` is the ground sampling of images without a georeference (``gsd_b_m``: B's, when it
    differs), ``max_shift_m`` the largest residual misregistration accepted (None: ``pairs.DEFAULT_MAX_SHIFT_M``)
    and ``correct_shift = true`` removes a small constant one from A. The pair fields are None unless set, so
    the other scenarios' specs (and their fingerprints) do not change."""

    kind: str = field(default="city", metadata=rng(choices=("city", "file", "pair")))
    path: str | None = None
    gsd_m: float | None = None          # metres per pixel, for files without a georeference; (0, 1000]
    crs: str | None = None
    use_dsm: bool = True   # cast shadows from the map's height model (when it has one)
    # how a map file is read: "window" (opened, each episode's window read at reset: a COG or tiled GeoTIFF),
    # "whole" (loaded), "auto" (by window when it is such a file of at least raster.WINDOW_MIN_BYTES of RGB)
    read: str = field(default="auto", metadata=rng(choices=("auto", "window", "whole")))
    path_a: str | None = None           # pair: epoch A, the map database
    path_b: str | None = None           # pair: epoch B, the ground the camera sees
    gsd_b_m: float | None = None        # pair: B's metres per pixel when it has no georeference and differs
    max_shift_m: float | None = None    # pair: largest residual misregistration accepted, metres; (0, 1000]
    correct_shift: bool | None = None   # pair: remove a constant misregistration from A (None: false)

    def validate(self, where: str) -> None:
        if self.kind == "file" and not self.path:
            raise ConfigError(f"{where}: map.kind = 'file' needs map.path, the map file to fly over "
                              "(PNG/TIFF/GeoTIFF or a bundle); e.g. gym.make(id, path='tile.tif')")
        for name in ("gsd_m", "gsd_b_m", "max_shift_m"):
            if getattr(self, name) is not None:
                check_value(name, getattr(self, name), rng(0.0, 1000.0, lo_open=True), where)
        if self.kind == "city" and self.path:
            raise ConfigError(f"{where}: map.path is only used with map.kind = 'file'")
        if self.kind == "city" and self.read != "auto":
            raise ConfigError(f"{where}: map.read is only used with map.kind = 'file' (the city is always in memory)")
        pair_fields = [n for n in ("path_a", "path_b", "gsd_b_m", "max_shift_m", "correct_shift")
                       if getattr(self, n) is not None]
        if self.kind != "pair" and pair_fields:
            raise ConfigError(f"{where}: map.{pair_fields[0]} is only used with map.kind = 'pair' (a real "
                              "two-epoch pair, e.g. gym.make('AerialLoc/RealPair-v2', path_a=..., path_b=...))")
        if self.kind == "pair":
            missing = [n for n in ("path_a", "path_b") if not getattr(self, n)]
            if missing:
                raise ConfigError(
                    f"{where}: map.kind = 'pair' needs map.path_a (epoch A, the map database) and map.path_b "
                    f"(epoch B, the ground the camera sees); {' and '.join('map.' + m for m in missing)} "
                    "missing: e.g. gym.make('AerialLoc/RealPair-v2', path_a='A/test_1.png', "
                    "path_b='B/test_1.png', map={'gsd_m': 0.5}) (gsd_m: for images without a georeference)")
            if self.path:
                raise ConfigError(f"{where}: map.path is for map.kind = 'file'; a pair's images are map.path_a "
                                  "and map.path_b")


@dataclass(frozen=True)
class WorldSpec:
    """What a world is built from: the scenario's ``map``, ``city``, ``epoch``, ``shadows`` and ``database``
    sections (``city`` is read only when ``map.kind == "city"``)."""

    map: MapConfig
    city: Any           # world.city.CityConfig
    epoch: Any          # world.city.epochs.EpochConfig
    shadows: Any        # world.shadows.ShadowConfig
    database: Any       # world.maps.acquisition.AcquisitionConfig
    where: str = "scenario"   # names the scenario in errors

    def map_key(self) -> str:
        """The content key of the surveyed map: the city's parameters, or the file's identity on disk."""
        cfg = self.map
        if cfg.kind == "city":
            return _key("city", config_to_dict(self.city))
        if cfg.kind == "pair":
            files = [(str(p.resolve()), p.stat().st_size, p.stat().st_mtime_ns) for p in self.pair_paths()]
            return _key("pair", files, cfg.gsd_m, cfg.gsd_b_m, cfg.crs, cfg.max_shift_m, bool(cfg.correct_shift))
        path = self.map_path()
        stat = path.stat() if path.is_file() else _folder_stat(path)
        return _key("file", str(path.resolve()), stat, cfg.gsd_m, cfg.crs, cfg.read)

    def map_path(self) -> Path:
        """The map file of a ``kind = "file"`` map, checked to exist."""
        path = Path(str(self.map.path)).expanduser()
        if not path.exists():
            raise MapError(f"{self.where}: map.path '{self.map.path}' does not exist (resolved to "
                           f"{path.resolve()}); give an existing PNG/TIFF/GeoTIFF file or bundle folder")
        return path

    def pair_paths(self) -> tuple[Path, Path]:
        """The two images of a ``kind = "pair"`` map (A, B), checked to exist."""
        out = []
        for name, what in (("path_a", "epoch A, the map database"), ("path_b", "epoch B, the camera's ground")):
            path = Path(str(getattr(self.map, name))).expanduser()
            if not path.is_file():
                raise MapError(f"{self.where}: map.{name} '{getattr(self.map, name)}' ({what}) does not exist or "
                               f"is not a file (resolved to {path.resolve()}); give an existing PNG/TIFF/GeoTIFF")
            out.append(path)
        return out[0], out[1]


@dataclass(frozen=True, eq=False)
class World:
    """The world of one ``WorldSpec``: the maps and what is derived from them (see the module doc)."""

    spec: WorldSpec
    key: str
    surveyed: Orthomap
    ground: Orthomap
    database: Orthomap

    @property
    def dsm_max_m(self) -> float:
        """The tallest height of the ground's height model (it bounds how far shadows reach)."""
        return _cached(("dsm_max", self.key), lambda: float(np.max(self.ground.dsm_m)))

    def coarse_dsm(self, factor: int) -> np.ndarray:
        """The ground's height model pooled to its block maximum on a grid of ``factor`` map pixels per cell
        (the per-episode shadow sweep starts from it instead of pooling the full-resolution heights again)."""
        def make() -> np.ndarray:
            from aerial_loc_env.world import shadows

            dsm = np.ascontiguousarray(self.ground.dsm_m, dtype=np.float32)
            return shadows.max_pool(dsm, factor) if factor > 1 else dsm

        return _cached(("coarse_dsm", self.key, int(factor)), make)

    def flyable_region(self, clearance_m: float, name: str) -> FlyableRegion:
        """Where a vehicle whose footprint needs ``clearance_m`` of valid ground around it may fly."""
        from aerial_loc_env.world.maps.region import FlyableRegion

        def make() -> FlyableRegion:
            g = self.ground
            # a map read by window gives its no-data as a coarse grid of "any no-data" blocks (conservative)
            nodata = g.validity_blocks() if self.windowed else g.nodata
            return FlyableRegion(g.width_m, g.height_m, clearance_m, nodata=nodata, name=name)

        return _cached(("region", self.key, round(float(clearance_m), 3)), make)

    @property
    def windowed(self) -> bool:
        """Whether the maps are read by window (``world.maps.raster.RasterMap``): the env reads each episode's
        window at reset."""
        return hasattr(self.ground, "validity_blocks")


#: the per-process cache of worlds and their parts, keyed by content (``_key``)
_CACHE: dict[tuple, Any] = {}


def _key(*parts: Any) -> str:
    return json.dumps(parts, sort_keys=True, default=repr)


def _folder_stat(path: Path) -> list:
    """A bundle folder's identity: its files' names, sizes and modification times."""
    return sorted((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in path.iterdir() if p.is_file())


def _cached(key: tuple, make: Any) -> Any:
    if key not in _CACHE:
        _CACHE[key] = make()
    return _CACHE[key]


def build_world(spec: WorldSpec) -> World:
    """The ``World`` of ``spec``, built once per process per content (see the module doc)."""
    map_key = spec.map_key()
    ground_key = _key(map_key, config_to_dict(spec.epoch)) if not spec.epoch.is_identity else map_key
    database_key = _key(map_key, repr(spec.shadows), repr(spec.database))
    world_key = _key(ground_key, database_key)
    if ("world", world_key) not in _CACHE:
        surveyed = _cached(("surveyed", map_key), lambda: _load_surveyed(spec))
        ground = _cached(("ground", ground_key), lambda: _epoch(spec, surveyed))
        database = _cached(("database", database_key), lambda: _database(spec, surveyed))
        _CACHE[("world", world_key)] = World(spec, world_key, surveyed, ground, database)
    return _CACHE[("world", world_key)]


def _load_surveyed(spec: WorldSpec) -> Orthomap:
    """Epoch A: the city (from its on-disk cache), the map file, or a pair's image A (on the pair's grid)."""
    if spec.map.kind == "pair":
        return _pair(spec).surveyed
    if spec.map.kind == "city":
        from aerial_loc_env.world.city import default_city

        return default_city(spec.city)
    from aerial_loc_env.world.maps.io import open_map

    kwargs: dict[str, Any] = {}
    if spec.map.gsd_m is not None:
        kwargs["gsd_m"] = spec.map.gsd_m
    if spec.map.crs is not None:
        kwargs["crs"] = spec.map.crs
    return open_map(spec.map_path(), read=spec.map.read, **kwargs)


def _refuse_windowed(spec: WorldSpec, surveyed: Any, section: str, fields: str) -> None:
    """A map read by window has no whole image to change: an epoch or an acquisition model on it is refused."""
    if hasattr(surveyed, "validity_blocks"):
        raise ConfigError(f"{spec.where}: [{section}] ({fields}) changes the whole map, but map '{surveyed.name}' "
                          f"({surveyed.width_px} x {surveyed.height_px} px) is read by window; turn [{section}] off, "
                          "or load a map that fits in memory whole (map.read = 'whole')")


def _epoch(spec: WorldSpec, surveyed: Orthomap) -> Orthomap:
    """The ground the camera sees: ``surveyed`` itself, epoch B of it (the city's cached on disk), or a pair's
    image B."""
    if spec.map.kind == "pair":
        return _pair(spec).ground
    if spec.epoch.is_identity:
        return surveyed
    _refuse_windowed(spec, surveyed, "epoch", "epoch B of the ground")
    from aerial_loc_env.world.city import epochs

    if spec.map.kind == "city":
        return epochs.epoch_city(spec.city, spec.epoch)
    return epochs.change_epoch(surveyed, spec.epoch)


def _pair(spec: WorldSpec) -> Any:
    """A ``kind = "pair"`` map's two epochs on one grid (``world.maps.pairs.load_pair``), loaded once."""
    if not spec.epoch.is_identity:
        raise ConfigError(f"{spec.where}: map.kind = 'pair' flies the camera over image B, a real later epoch; "
                          "[epoch] simulates one from the map and cannot apply to it: leave [epoch] at its "
                          "defaults (or fly a map file, map.kind = 'file', with [epoch])")

    def load() -> Any:
        from aerial_loc_env.world.maps.pairs import DEFAULT_MAX_SHIFT_M, load_pair

        cfg = spec.map
        path_a, path_b = spec.pair_paths()
        return load_pair(path_a, path_b, gsd_m=cfg.gsd_m, gsd_b_m=cfg.gsd_b_m, crs=cfg.crs,
                         max_shift_m=cfg.max_shift_m or DEFAULT_MAX_SHIFT_M, correct_shift=bool(cfg.correct_shift),
                         where=spec.where)

    return _cached(("pair", spec.map_key()), load)


def _database(spec: WorldSpec, surveyed: Orthomap) -> Orthomap:
    """What the estimators get as the map: the surveyed scene itself (shadow-free), or with
    ``shadows.database_sun_deg`` a copy with that other sun's shadows baked in (the time-of-day mismatch), then,
    with an acquisition model that is not the identity, as that sensor acquired it (``maps/acquisition.py``);
    the city's is cached on disk."""
    from aerial_loc_env.world.maps import acquisition as acq

    if acq.database_is_identity(spec.shadows, spec.database):
        return surveyed
    _refuse_windowed(spec, surveyed, "database", "shadows.database_sun_deg or the acquisition model")
    if spec.map.kind == "city":
        return acq.database_city(spec.city, spec.shadows, spec.database)
    return acq.acquire_map(surveyed, spec.shadows, spec.database)
