"""The map database: ``Orthomap`` (layers + ground scale + georeference) and its on-disk bundle format.

World frame (docs/ARCHITECTURE.md): metres, x east, y north, origin at the south-west outer corner of the image;
``x_m = (u + 0.5) * gsd_x_m``, ``y_m = (H - 0.5 - v) * gsd_y_m``. World <-> lat/lon goes through map pixels and
the georeference.

Bundle (``<name>.alm/``): ``meta.json`` + one ``.npy`` per layer. Bundles are written atomically (a temporary
directory beside the target, then ``os.replace``) and loaded memory-mapped and read-only, so vectorized env
workers share one copy of the layers; a memory-mapped Orthomap pickles as its bundle path. ``meta.json`` holds
each layer file's SHA-256, and loading checks it, so a layer changed on disk (even at the same size) is an
error, never a different map. Hashing every load would cost more than mapping, so ``.verified.json`` in the
bundle records each file's (size, mtime, ctime, inode) when its hash last matched; a file whose record still
holds is not read again (a write changes its mtime and ctime; a file changed within ``_RACY_NS`` of the record
is hashed anyway, as file timestamps are coarse). Bundles written before checksums load unchecked;
``add_bundle_checksums`` gives them theirs (the map cache does so for its entries).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aerial_loc_env.errors import MapError
from aerial_loc_env.paths import atomic_write_bytes, umask_mode
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


class MapGeometry:
    """A map's frames (docs/ARCHITECTURE.md): the world frame in metres from the map's south-west outer corner,
    pixels with centres at integers, lat/lon through the georeference. Shared by maps held in memory
    (``Orthomap``) and maps read by window (``raster.RasterMap``); a subclass provides ``width_px``,
    ``height_px``, ``gsd_x_m``, ``gsd_y_m``, ``georef`` and ``name``."""

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


@dataclass(frozen=True, eq=False)
class Orthomap(MapGeometry):
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

    def valid_mask(self) -> np.ndarray:
        """(H, W) bool, True where the map has data (a fresh array; all True without a no-data layer)."""
        if self.nodata is None:
            return np.ones((self.height_px, self.width_px), dtype=bool)
        return ~np.asarray(self.nodata)

    def nodata_fraction(self) -> float:
        return 0.0 if self.nodata is None else float(np.count_nonzero(self.nodata)) / self.nodata.size

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
                meta["layers"][n]["sha256"] = _file_sha256(tmp / f"{n}.npy")   # what is on disk, header included
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
        for n, info in meta["layers"].items():
            if not isinstance(info, dict) or not isinstance(info.get("file"), str) or \
                    not isinstance(info.get("dtype"), str) or not isinstance(info.get("shape"), list) or \
                    not isinstance(info.get("sha256", ""), str):
                raise MapError(f"{path / 'meta.json'}: layers[{n!r}] = {info!r} must be a table with 'file', "
                               "'dtype', 'shape' (and 'sha256'); the bundle is corrupt, rebuild it with save_bundle")
            if n not in _LAYERS:
                raise MapError(f"{path}: unknown layer {n!r} in meta.json; known: {', '.join(_LAYERS)}")
        _verify_layers(path, meta)
        arrays: dict[str, np.ndarray] = {}
        for n, info in meta["layers"].items():
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


#: the stamp of verified layer files inside a bundle (see the module docstring)
STAMP_FILE = ".verified.json"
#: a file changed less than this before its stamp was written is hashed again: timestamps are coarse (a jiffy on
#: Linux, 1-2 s on some file systems), so a change within the same tick leaves (size, mtime, ctime) unchanged
_RACY_NS = 3_000_000_000


def _file_sha256(path: Path) -> str:
    """The SHA-256 of a file's bytes, read in 4 MiB blocks (hashlib releases the GIL on each)."""
    digest, buf = hashlib.sha256(), bytearray(1 << 22)
    view = memoryview(buf)
    with open(path, "rb", buffering=0) as fh:
        while n := fh.readinto(buf):
            digest.update(view[:n])
    return digest.hexdigest()


def _stat_key(path: Path) -> list[int]:
    st = os.stat(path)
    return [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]


def _verify_layers(path: Path, meta: dict) -> None:
    """Check every layer file that ``meta`` gives a SHA-256 against it, unless the bundle's stamp shows the file
    unchanged since it last matched; raise MapError naming the first layer that differs. Records what matched
    in the stamp (best effort: a read-only bundle is hashed on every load)."""
    want = {n: info["sha256"] for n, info in meta["layers"].items() if "sha256" in info}
    if not want:
        return
    try:
        stamp = json.loads((path / STAMP_FILE).read_text())
        if not isinstance(stamp, dict) or stamp.get("bundle_id") != meta["bundle_id"] or \
                not isinstance(stamp.get("layers"), dict) or not isinstance(stamp.get("written_ns"), int):
            stamp = {}
    except (OSError, ValueError):
        stamp = {}
    trusted_before = stamp.get("written_ns", 0) - _RACY_NS
    record: dict[str, Any] = {}
    hashed = False
    for n, digest in want.items():
        f = path / meta["layers"][n]["file"]
        try:
            key = _stat_key(f)
        except OSError as exc:
            raise MapError(f"{f}: cannot read layer {n!r} of the bundle: {exc}") from exc
        entry = {"sha256": digest, "stat": key}
        if stamp.get("layers", {}).get(n) == entry and key[2] < trusted_before:
            record[n] = entry
            continue
        try:
            have = _file_sha256(f)
        except OSError as exc:
            raise MapError(f"{f}: cannot read layer {n!r} of the bundle: {exc}") from exc
        if have != digest:
            raise MapError(f"{f}: layer {n!r} does not match the SHA-256 in meta.json (the file changed after the "
                           "bundle was written); the bundle is corrupt, rebuild it")
        record[n], hashed = entry, True
    if hashed:
        try:
            atomic_write_bytes(path / STAMP_FILE, json.dumps({"bundle_id": meta["bundle_id"], "written_ns":
                                                              time.time_ns(), "layers": record}).encode())
        except OSError:
            pass


def add_bundle_checksums(path: str | os.PathLike) -> None:
    """Give a bundle written without layer checksums (by a version before them) the SHA-256 of each layer file as
    it is now, in its meta.json (replaced atomically), so that loading verifies it from then on. Best effort: a
    bundle that cannot be written keeps loading unchecked."""
    path = Path(path).absolute()
    meta = read_bundle_meta(path)
    missing = [n for n, info in meta["layers"].items() if isinstance(info, dict) and "sha256" not in info]
    if not missing:
        return
    for n in missing:
        meta["layers"][n]["sha256"] = _file_sha256(path / meta["layers"][n]["file"])
    try:
        atomic_write_bytes(path / "meta.json", json.dumps(meta, indent=2).encode())
    except OSError:
        pass


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
