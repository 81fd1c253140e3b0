"""The map database: ``Orthomap`` (layers + ground scale + georeference) and its on-disk bundle format.

World frame (docs/ARCHITECTURE.md): metres, x east, y north, origin at the south-west outer corner of the image;
``x_m = (u + 0.5) * gsd_x_m``, ``y_m = (H - 0.5 - v) * gsd_y_m``. World <-> lat/lon goes through map pixels and
the georeference.

Bundle (``<name>.alm/``): ``meta.json`` + one ``.npy`` per layer. Bundles are written atomically (a temporary
directory beside the target, then ``os.replace``) and loaded memory-mapped and read-only, so vectorized env
workers share one copy of the layers; a memory-mapped Orthomap pickles as its bundle path.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aerial_loc_env.errors import MapError
from aerial_loc_env.paths import umask_mode
from aerial_loc_env.world.maps.geo import Georeference, georeference_from_dict

BUNDLE_FORMAT = "aerial_loc_env.orthomap"
BUNDLE_VERSION = 1
#: Optional layers: name -> (dtype, trailing shape after (H, W)).
_LAYERS: dict[str, tuple[np.dtype, tuple[int, ...]]] = {
    "rgb": (np.dtype(np.uint8), (3,)),
    "dsm_m": (np.dtype(np.float32), ()),
    "nodata": (np.dtype(np.bool_), ()),
    "classes": (np.dtype(np.uint8), ()),
}


@dataclass(frozen=True, eq=False)
class Orthomap:
    """A georeferenced orthomap with optional DSM, no-data and land-cover layers (all (H, W) aligned)."""

    rgb: np.ndarray
    gsd_x_m: float
    gsd_y_m: float
    georef: Georeference
    dsm_m: np.ndarray | None = None
    nodata: np.ndarray | None = None
    classes: np.ndarray | None = None
    name: str = "map"
    source: str | None = None
    # memory-mapped maps: (bundle path, bundle_id, crop window (u0, v0, w, h) or None, name) for cheap pickling
    _bundle: tuple | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        where = f"Orthomap '{self.name}'"
        if not isinstance(self.rgb, np.ndarray) or self.rgb.ndim != 3 or self.rgb.shape[2] != 3:
            shape = getattr(self.rgb, "shape", type(self.rgb).__name__)
            raise MapError(f"{where}: layer 'rgb' must be an (H, W, 3) uint8 array, got shape {shape}")
        h, w = self.rgb.shape[:2]
        if h < 1 or w < 1:
            raise MapError(f"{where}: layer 'rgb' is empty, shape {self.rgb.shape}")
        for name, (dtype, trailing) in _LAYERS.items():
            arr = getattr(self, name)
            if arr is None:
                continue
            if not isinstance(arr, np.ndarray):
                raise MapError(f"{where}: layer '{name}' must be a numpy array, got {type(arr).__name__}")
            if arr.dtype != dtype:
                raise MapError(f"{where}: layer '{name}' must have dtype {dtype}, got {arr.dtype} "
                               f"(convert it with .astype(np.{dtype.name}))")
            if arr.shape != (h, w) + trailing:
                raise MapError(f"{where}: layer '{name}' has shape {arr.shape}, but the rgb layer has shape "
                               f"{self.rgb.shape}; expected {(h, w) + trailing}")
        if self.dsm_m is not None and not np.isfinite(self.dsm_m).all():
            raise MapError(f"{where}: layer 'dsm_m' has NaN/inf heights; fill them (and mark them in 'nodata')")
        for name in ("gsd_x_m", "gsd_y_m"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, (int, float, np.floating, np.integer)) \
                    or not math.isfinite(val) or val <= 0:
                raise MapError(f"{where}: '{name}' must be a finite number of metres > 0, got {val!r}")
            object.__setattr__(self, name, float(val))
        if not isinstance(self.georef, Georeference):
            raise MapError(f"{where}: 'georef' must be a Georeference, got {type(self.georef).__name__}")
        if not isinstance(self.name, str) or not self.name:
            raise MapError(f"Orthomap: 'name' must be a non-empty string, got {self.name!r}")

    def __repr__(self) -> str:
        layers = ", ".join(n for n in _LAYERS if getattr(self, n) is not None)
        return (f"Orthomap(name={self.name!r}, {self.width_px}x{self.height_px} px, gsd_x_m={self.gsd_x_m:.6g}, "
                f"gsd_y_m={self.gsd_y_m:.6g}, layers=[{layers}], georef={self.georef!r}, source={self.source!r})")

    # --- size -------------------------------------------------------------------------------------------------

    @property
    def width_px(self) -> int:
        return int(self.rgb.shape[1])

    @property
    def height_px(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width_m(self) -> float:
        return self.width_px * self.gsd_x_m

    @property
    def height_m(self) -> float:
        return self.height_px * self.gsd_y_m

    # --- frames -----------------------------------------------------------------------------------------------

    def pixel_to_world(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Map pixel (u, v) (centres at integers) -> world (x_m, y_m)."""
        u, v = np.broadcast_arrays(np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64))
        return (u + 0.5) * self.gsd_x_m, (self.height_px - 0.5 - v) * self.gsd_y_m

    def world_to_pixel(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
        """World (x_m, y_m) -> map pixel (u, v)."""
        x, y = np.broadcast_arrays(np.asarray(x_m, dtype=np.float64), np.asarray(y_m, dtype=np.float64))
        return x / self.gsd_x_m - 0.5, self.height_px - 0.5 - y / self.gsd_y_m

    def world_to_latlon(self, x_m, y_m) -> tuple[np.ndarray, np.ndarray]:
        """World metres -> WGS84 (lat_deg, lon_deg), through the georeference."""
        return self.georef.pixel_to_latlon(*self.world_to_pixel(x_m, y_m))

    def latlon_to_world(self, lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]:
        """WGS84 (lat_deg, lon_deg) -> world metres, through the georeference."""
        return self.pixel_to_world(*self.georef.latlon_to_pixel(lat_deg, lon_deg))

    def valid_mask(self) -> np.ndarray:
        """(H, W) bool, True where the map has data (a fresh array; all True without a no-data layer)."""
        if self.nodata is None:
            return np.ones((self.height_px, self.width_px), dtype=bool)
        return ~np.asarray(self.nodata)

    def nodata_fraction(self) -> float:
        return 0.0 if self.nodata is None else float(np.count_nonzero(self.nodata)) / self.nodata.size

    def contains_world(self, x_m, y_m, margin_m: float = 0.0) -> np.ndarray:
        """True where (x_m, y_m) lies inside the map extent shrunk by ``margin_m`` on every side."""
        x, y = np.asarray(x_m, dtype=np.float64), np.asarray(y_m, dtype=np.float64)
        return ((x >= margin_m) & (x <= self.width_m - margin_m)
                & (y >= margin_m) & (y <= self.height_m - margin_m))

    def check_fits(self, footprint_w_m: float, footprint_h_m: float, where: str) -> None:
        """Raise MapError if one camera footprint (its axis-aligned extent on the ground) exceeds the map.

        Pass the footprint's rotated bounding box (e.g. its diagonal on both axes) when the yaw is free.
        """
        if footprint_w_m > self.width_m or footprint_h_m > self.height_m:
            raise MapError(
                f"{where}: map '{self.name}' is {self.width_m:.1f} x {self.height_m:.1f} m, smaller than one "
                f"camera footprint of {footprint_w_m:.1f} x {footprint_h_m:.1f} m; use a larger map, a lower "
                f"altitude or a narrower field of view")

    def crop(self, u0_px: int, v0_px: int, width_px: int, height_px: int, *, name: str | None = None) -> Orthomap:
        """The sub-map of pixels [v0, v0 + height) x [u0, u0 + width), with its georeference (views, no copy)."""
        u0, v0, w, h = (int(x) for x in (u0_px, v0_px, width_px, height_px))
        if w < 1 or h < 1 or u0 < 0 or v0 < 0 or u0 + w > self.width_px or v0 + h > self.height_px:
            raise MapError(f"Orthomap '{self.name}'.crop: window u0={u0}, v0={v0}, {w} x {h} px is not inside "
                           f"the {self.width_px} x {self.height_px} px map")
        sl = (slice(v0, v0 + h), slice(u0, u0 + w))

        def cut(a: np.ndarray | None) -> np.ndarray | None:
            return None if a is None else a[sl]

        out = Orthomap(self.rgb[sl], self.gsd_x_m, self.gsd_y_m, self.georef.shifted(u0, v0),
                       cut(self.dsm_m), cut(self.nodata), cut(self.classes), name or f"{self.name}_crop",
                       self.source)
        if self._bundle is not None:   # a crop of a memory map still pickles as (bundle, window)
            path, bundle_id, win, _ = self._bundle
            pu, pv = (0, 0) if win is None else win[:2]
            object.__setattr__(out, "_bundle", (path, bundle_id, (pu + u0, pv + v0, w, h), out.name))
        return out

    # --- bundles ----------------------------------------------------------------------------------------------

    def save_bundle(self, path: str | os.PathLike, *, overwrite: bool = False,
                    provenance: dict[str, Any] | None = None) -> Path:
        """Write the bundle directory ``path`` (conventionally ``<name>.alm``) atomically; returns the path.

        An existing ``path`` is an error unless ``overwrite=True``. On any failure nothing is left behind.
        """
        path = Path(path).absolute()
        if path.exists() and not overwrite:
            raise MapError(f"{path}: already exists; pass overwrite=True to replace the bundle")
        if path.exists() and not (path / "meta.json").is_file():
            raise MapError(f"{path}: exists and is not an orthomap bundle; refusing to replace it")
        path.parent.mkdir(parents=True, exist_ok=True)
        layers = {name: getattr(self, name) for name in _LAYERS if getattr(self, name) is not None}
        meta = {
            "format": BUNDLE_FORMAT, "format_version": BUNDLE_VERSION, "bundle_id": uuid.uuid4().hex,
            "name": self.name, "source": self.source, "gsd_x_m": self.gsd_x_m, "gsd_y_m": self.gsd_y_m,
            "georef": self.georef.to_dict(),
            "layers": {n: {"file": f"{n}.npy", "dtype": a.dtype.name, "shape": list(a.shape)}
                       for n, a in layers.items()},
            "provenance": dict(provenance or {}),
        }
        tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
        tmp.chmod(umask_mode(0o777))   # the bundle folder as mkdir would make it (mkdtemp gives 0700)
        try:
            for n, a in layers.items():
                np.save(tmp / f"{n}.npy", np.ascontiguousarray(a), allow_pickle=False)
            (tmp / "meta.json").write_text(json.dumps(meta, indent=2))
            if path.exists():   # a directory cannot be os.replace'd onto a non-empty one: move the old aside
                old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old-", dir=path.parent))
                os.replace(path, old / "bundle")
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True)
            else:
                try:
                    os.replace(tmp, path)
                except OSError as exc:
                    if not path.exists():
                        raise
                    raise MapError(f"{path}: written meanwhile by another process; load it with "
                                   "Orthomap.load_bundle, or pass overwrite=True") from exc
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return path

    @classmethod
    def load_bundle(cls, path: str | os.PathLike, mmap: bool = True) -> Orthomap:
        """Load a bundle; with ``mmap`` the layers are read-only memory maps shared between processes."""
        path = Path(path).absolute()
        meta = read_bundle_meta(path)
        arrays: dict[str, np.ndarray] = {}
        for n, info in meta["layers"].items():
            if not isinstance(info, dict) or not isinstance(info.get("file"), str) or \
                    not isinstance(info.get("dtype"), str) or not isinstance(info.get("shape"), list):
                raise MapError(f"{path / 'meta.json'}: layers[{n!r}] = {info!r} must be a table with 'file', "
                               "'dtype' and 'shape'; the bundle is corrupt, rebuild it with save_bundle")
            if n not in _LAYERS:
                raise MapError(f"{path}: unknown layer {n!r} in meta.json; known: {', '.join(_LAYERS)}")
            f = path / info["file"]
            try:
                a = np.load(f, mmap_mode="r" if mmap else None, allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise MapError(f"{f}: cannot read layer {n!r} of the bundle: {exc}") from exc
            if a.dtype.name != info["dtype"] or list(a.shape) != list(info["shape"]):
                raise MapError(f"{f}: layer {n!r} is {a.dtype}{a.shape}, meta.json says "
                               f"{info['dtype']}{tuple(info['shape'])}; the bundle is corrupt, rebuild it")
            arrays[n] = a
        if "rgb" not in arrays:
            raise MapError(f"{path}: the bundle has no 'rgb' layer")
        try:
            om = cls(georef=georeference_from_dict(meta["georef"]), gsd_x_m=meta["gsd_x_m"],
                     gsd_y_m=meta["gsd_y_m"], name=meta["name"], source=meta.get("source"), **arrays)
        except MapError as exc:
            raise MapError(f"{path}: {exc}") from exc
        if mmap:
            object.__setattr__(om, "_bundle", (str(path), meta["bundle_id"], None, om.name))
        return om

    @property
    def bundle_path(self) -> Path | None:
        """The bundle this map is memory-mapped from, if any."""
        return None if self._bundle is None else Path(self._bundle[0])

    def __reduce_ex__(self, protocol):
        if self._bundle is not None:   # memory-mapped: pickle the path, re-map on unpickle
            return _unpickle_bundle, self._bundle
        return super().__reduce_ex__(protocol)


def read_bundle_meta(path: str | os.PathLike) -> dict:
    """Read and check a bundle's meta.json (format, version, required keys)."""
    path = Path(path)
    meta_file = path / "meta.json"
    if not meta_file.is_file():
        raise MapError(f"{path}: not an orthomap bundle (no meta.json); write one with Orthomap.save_bundle")
    try:
        meta = json.loads(meta_file.read_text())
    except (OSError, ValueError) as exc:
        raise MapError(f"{meta_file}: unreadable bundle metadata: {exc}") from exc
    if not isinstance(meta, dict) or meta.get("format") != BUNDLE_FORMAT:
        raise MapError(f"{meta_file}: not an {BUNDLE_FORMAT} bundle")
    if meta.get("format_version") != BUNDLE_VERSION:
        raise MapError(f"{meta_file}: bundle format version {meta.get('format_version')!r} is not supported "
                       f"(this version reads {BUNDLE_VERSION}); rebuild the bundle")
    missing = [k for k in ("bundle_id", "name", "gsd_x_m", "gsd_y_m", "georef", "layers") if k not in meta]
    if missing:
        raise MapError(f"{meta_file}: missing key(s) {', '.join(missing)}; the bundle is corrupt, rebuild it")
    if not isinstance(meta["layers"], dict):
        raise MapError(f"{meta_file}: 'layers' must map layer names to tables (file, dtype, shape), got "
                       f"{type(meta['layers']).__name__} {meta['layers']!r:.60}; the bundle is corrupt, rebuild it")
    return meta


def _unpickle_bundle(path: str, bundle_id: str, window: tuple[int, int, int, int] | None, name: str) -> Orthomap:
    om = Orthomap.load_bundle(path, mmap=True)
    if om._bundle is None or om._bundle[1] != bundle_id:
        raise MapError(f"{path}: the bundle was replaced after this map was pickled (bundle_id changed)")
    return om if window is None else om.crop(*window, name=name)
