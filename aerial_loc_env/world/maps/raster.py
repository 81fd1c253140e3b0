"""Maps opened, not loaded: a tiled (or striped) GeoTIFF, e.g. a COG, read by window.

``RasterMap`` has the geometry of the whole map (size, ground scale, georeference, the world frame of
``orthomap.py``) and reads pixels by window: ``read(u0, v0, w, h)`` decodes only the tiles (or strips) under the
window, ``window(...)`` gives that window as an in-memory ``Orthomap``. Its whole layers (``rgb``, ``nodata``) are
never materialized: reading them raises a ``MapError`` that names the map's size, so no caller swaps or is killed
by accident.

The tiles are decoded by tifffile, the decoder ``load_orthomap`` uses for TIFFs, so a window equals the same
window of the file loaded whole, bit for bit (GDAL's JPEG decoder differs from it by tens of levels on the real
tiles). No-data comes from what the file declares, with the loader's precedence: its internal mask (what
``write_cog`` writes), its GDAL_NODATA value, its alpha channel. Black border wedges, which only the whole
image shows, are found by ``write_cog`` (which loads the source as the loader does) and kept as the COG's mask.

Where a vehicle may fly (``FlyableRegion``) needs no-data over the whole map, but only coarsely:
``validity_blocks`` reduces the mask to "any no-data" per block of ``BLOCK_PX`` pixels, decoding each distinct
mask tile once (a COG's all-valid mask tiles are identical bytes), and keeps the grid in the cache folder, keyed
by the file's identity, when it had to decode the image itself (no mask, a nodata value or alpha).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import threading
import weakref
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps.orthomap import MapGeometry

#: files whose decoded RGB layer is at least this large are opened by window when ``read = "auto"``
WINDOW_MIN_BYTES = 256 << 20
#: a tile or strip larger than this (decoded) makes window reads decode too much: such files are read whole
SEGMENT_MAX_BYTES = 64 << 20
#: the validity grid's block side, map pixels
BLOCK_PX = 16
#: decoded tiles (or strips) a map read by window keeps, most recently used first: consecutive windows (the
#: env's, each estimator's, the next one along the flight) overlap, so most of a window's tiles were decoded for
#: the one before
TILE_CACHE_BYTES = 64 << 20
#: what loading a map whole costs per decoded RGB byte, at its peak (the decoded file, the RGB layer, the no-data
#: search, the renderer's RGBA copy): the loader and its renderer measure 3.7-4.2x on large maps
WHOLE_LOAD_FACTOR = 4.5
READ_MODES = ("auto", "window", "whole")


def available_memory_bytes() -> int:
    """Memory this process may still take: MemAvailable (Linux), capped by a cgroup limit if one is set."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
            avail = 1 << 62
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:
            limit = Path(limit_file).read_text().strip()
            usage = int(Path(usage_file).read_text().strip())
        except (OSError, ValueError):
            continue
        if limit.isdigit() and int(limit) < (1 << 60):
            avail = min(avail, max(0, int(limit) - usage))
        break
    return int(avail)


def gb(n_bytes: float) -> str:
    return f"{n_bytes / 1e9:.2f} GB" if n_bytes >= 1e8 else f"{n_bytes / 1e6:.1f} MB"


def check_memory(what: str, width_px: int, height_px: int, bytes_needed: int, fix: str) -> None:
    """Raise a MapError before decoding when ``bytes_needed`` exceeds the memory available (never swap or be
    killed): the message names the size and ``fix``."""
    avail = available_memory_bytes()
    if bytes_needed > avail:
        raise MapError(f"{what}: {width_px} x {height_px} px; reading it needs about {gb(bytes_needed)} of memory, "
                       f"more than the {gb(avail)} available. {fix}")


# --- the file's layout ------------------------------------------------------------------------------------

@dataclass(frozen=True)
class TiffLayout:
    """What the TIFF header says (read without decoding a pixel)."""

    width_px: int
    height_px: int
    channels: int
    dtype: np.dtype
    tiled: bool
    segment_bytes: int          # the decoded size of one tile or strip
    contiguous: bool            # pixel-interleaved (one segment holds every channel)
    n_overviews: int
    has_mask: bool              # an internal (GDAL) mask of the full resolution

    @property
    def rgb_bytes(self) -> int:
        return self.width_px * self.height_px * 3

    def window_problem(self) -> str | None:
        """Why windows of this file cannot be read efficiently (None when they can)."""
        if not self.contiguous:
            return "its channels are stored in separate planes (PLANARCONFIG=SEPARATE)"
        if self.segment_bytes > SEGMENT_MAX_BYTES:
            kind = "tiles" if self.tiled else "strips"
            return (f"its {kind} are {gb(self.segment_bytes)} each when decoded, so a window decodes most of the "
                    "image")
        if self.dtype != np.uint8:
            return f"it is {self.dtype} (windows are read from 8-bit maps; 16-bit ones are scaled on the whole image)"
        return None


def tiff_layout(path: Path) -> TiffLayout | None:
    """The layout of a TIFF file's first image, or None when ``path`` is not a TIFF or is unreadable."""
    import tifffile

    try:
        with open(path, "rb") as fh:
            if fh.read(4) not in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
                return None
        with tifffile.TiffFile(path) as tif:
            page = tif.pages.first
            shape = page.shape
            channels = 1 if len(shape) == 2 else int(shape[-1] if page.planarconfig == 1 else shape[0])
            h, w = (shape[0], shape[1]) if page.planarconfig == 1 or len(shape) == 2 else (shape[1], shape[2])
            if page.is_tiled:
                seg_h, seg_w = page.tilelength, page.tilewidth
            else:
                seg_h, seg_w = min(int(page.rowsperstrip or h), h), w
            itemsize = np.dtype(page.dtype).itemsize if page.dtype is not None else 1
            seg_bytes = int(seg_h) * int(seg_w) * (channels if page.planarconfig == 1 else 1) * itemsize
            pages = _pages(tif)
            return TiffLayout(int(w), int(h), channels, np.dtype(page.dtype) if page.dtype else np.dtype(np.uint8),
                              bool(page.is_tiled), seg_bytes, page.planarconfig == 1 or len(shape) == 2,
                              len(pages["levels"]) - 1, pages["mask"] is not None)
    except Exception:  # noqa: BLE001 (the whole loader reports unreadable files with its own message)
        return None


def _pages(tif: Any) -> dict:
    """The indices of the image pages (full resolution then each overview, halving) and of the full-resolution
    mask page, from a TIFF's top-level pages."""
    first = tif.pages.first
    w0, h0 = first.imagewidth, first.imagelength
    levels, masks = [0], {}
    for i in range(1, len(tif.pages)):
        p = tif.pages[i]
        if not hasattr(p, "subfiletype"):
            continue
        if p.subfiletype & 4:          # a mask (GDAL's internal mask, or an overview's)
            masks[(p.imagewidth, p.imagelength)] = i
        elif p.subfiletype & 1:        # a reduced-resolution image
            f = 1 << len(levels)
            if (p.imagewidth, p.imagelength) == (-(-w0 // f), -(-h0 // f)):
                levels.append(i)
    sizes = [(-(-w0 // (1 << k)), -(-h0 // (1 << k))) for k in range(len(levels))]
    return {"levels": levels, "mask": masks.get((w0, h0)), "level_masks": [masks.get(s) for s in sizes]}


# --- reading windows ----------------------------------------------------------------------------------------

class TileCache:
    """Decoded segments (tiles or strips) by key, least recently used dropped beyond ``max_bytes``; thread-safe."""

    def __init__(self, max_bytes: int = TILE_CACHE_BYTES) -> None:
        self.max_bytes, self.nbytes = int(max_bytes), 0
        self._items: OrderedDict[Any, np.ndarray] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: Any) -> np.ndarray | None:
        with self._lock:
            seg = self._items.get(key)
            if seg is not None:
                self._items.move_to_end(key)
            return seg

    def put(self, key: Any, seg: np.ndarray) -> None:
        if seg.nbytes > self.max_bytes:
            return
        seg.flags.writeable = False
        with self._lock:
            if key in self._items:
                return
            self._items[key] = seg
            self.nbytes += seg.nbytes
            while self.nbytes > self.max_bytes:
                _, old = self._items.popitem(last=False)
                self.nbytes -= old.nbytes


class TileReader:
    """Windows of one page of a TIFF, decoded tile by tile (or strip by strip) with tifffile; decoded segments are
    kept in ``cache`` (a ``TileCache``) under ``key`` + their index."""

    def __init__(self, tif: Any, index: int, cache: TileCache | None = None, key: Any = None) -> None:
        page = tif.pages[index]
        self._tif, self._page, self._lock = tif, page, threading.Lock()
        self._cache, self._key = cache, key
        self.width_px, self.height_px = int(page.imagewidth), int(page.imagelength)
        if page.is_tiled:
            self.seg_h, self.seg_w = int(page.tilelength), int(page.tilewidth)
        else:
            self.seg_h, self.seg_w = min(int(page.rowsperstrip or self.height_px), self.height_px), self.width_px
        self.cols = -(-self.width_px // self.seg_w)
        self.samples = int(page.samplesperpixel)
        self.dtype = np.dtype(bool) if page.bitspersample == 1 else np.dtype(page.dtype)

    def raw(self, index: int) -> bytes:
        with self._lock:
            fh = self._tif.filehandle
            fh.seek(self._page.dataoffsets[index])
            return fh.read(self._page.databytecounts[index])

    def decode(self, data: bytes, index: int) -> np.ndarray:
        """The segment ``index`` as (seg_h, seg_w, samples) (edge segments padded)."""
        page = self._page
        seg, _, _ = page.decode(data if data else None, index, jpegtables=page.jpegtables,
                                jpegheader=page.jpegheader)
        if seg is None:                  # a sparse (missing) segment: GDAL's zeros
            return np.zeros((self.seg_h, self.seg_w, self.samples), self.dtype)
        seg = np.asarray(seg)
        return seg.reshape(seg.shape[-3], seg.shape[-2], seg.shape[-1])

    def read(self, u0: int, v0: int, w: int, h: int) -> np.ndarray:
        """Pixels [v0, v0 + h) x [u0, u0 + w) as (h, w, samples)."""
        out = np.empty((h, w, self.samples), self.dtype)
        r0, r1 = v0 // self.seg_h, (v0 + h - 1) // self.seg_h
        c0, c1 = u0 // self.seg_w, (u0 + w - 1) // self.seg_w
        for r in range(r0, r1 + 1):
            for c in range(c0, c1 + 1):
                idx = r * self.cols + c
                seg = self.segment(idx)
                y0, x0 = r * self.seg_h, c * self.seg_w
                ya, yb = max(v0, y0), min(v0 + h, y0 + self.seg_h)
                xa, xb = max(u0, x0), min(u0 + w, x0 + self.seg_w)
                out[ya - v0:yb - v0, xa - u0:xb - u0] = seg[ya - y0:yb - y0, xa - x0:xb - x0]
        return out

    def segment(self, index: int) -> np.ndarray:
        """The decoded segment ``index`` (from the cache when it is there)."""
        if self._cache is None:
            return self.decode(self.raw(index), index)
        key = (self._key, index)
        seg = self._cache.get(key)
        if seg is None:
            seg = self.decode(self.raw(index), index)
            self._cache.put(key, seg)
        return seg

    def segment_grid(self) -> tuple[int, int]:
        return -(-self.height_px // self.seg_h), self.cols


class RasterMap(MapGeometry):
    """A map file opened, not loaded (see the module docstring). Made by ``world.maps.io.open_map``.

    Geometry and frames are the ``Orthomap`` ones (``MapFrame``); ``dsm_m`` and ``classes`` are None (a windowed
    map carries colour and no-data only); ``rgb`` and ``nodata`` raise a ``MapError`` naming the size: read
    windows with ``read`` / ``window`` instead. Pickles as its path and options (each process opens the file).
    """

    dsm_m = None
    classes = None

    def __init__(self, path: str | os.PathLike, georef: Any, gsd_x_m: float, gsd_y_m: float, *, name: str,
                 source: str, nodata: str | float | None = "auto") -> None:
        self.path = Path(path).absolute()
        self.georef, self.gsd_x_m, self.gsd_y_m = georef, float(gsd_x_m), float(gsd_y_m)
        self.name, self.source = name, source
        self._nodata_rule = nodata
        self._pid: int | None = None
        self._tif: Any = None
        self._closer: weakref.finalize | None = None
        self._readers: dict[Any, TileReader] = {}
        self._tiles = TileCache()
        tif = self._file()
        page = tif.pages.first
        self._width, self._height = int(page.imagewidth), int(page.imagelength)
        self._samples = int(page.samplesperpixel)
        tag = page.tags.get(42113)   # GDAL_NODATA
        self._gdal_nodata = None if tag is None else float(str(tag.value).strip().strip("\x00"))
        stat = self.path.stat()
        self._identity = (str(self.path), stat.st_size, stat.st_mtime_ns)
        self._pages = _pages(tif)
        self._nodata_source = self._pick_nodata_source()
        self._validity: np.ndarray | None = None

    # --- the file ------------------------------------------------------------------------------------------
    def _file(self) -> Any:
        import tifffile

        if self._tif is None or self._pid != os.getpid():   # a forked worker opens its own handle
            try:
                tif = tifffile.TiffFile(self.path)
            except Exception as exc:   # tifffile raises many types on corrupt files
                raise MapError(f"{self.path}: unreadable TIFF: {exc}") from exc
            # the handle is closed with the map (or by ``close``), never left to the garbage collector's warning
            self._tif, self._closer = tif, weakref.finalize(self, tif.close)
            self._pid, self._readers, self._tiles = os.getpid(), {}, TileCache()
        return self._tif

    def close(self) -> None:
        """Close the map's file handle now (a later read opens it again); the map also closes it when collected."""
        if self._closer is not None:
            self._closer()
        self._tif = self._closer = None

    def _reader(self, key: str, level: int = 0) -> TileReader:
        tif = self._file()
        if (key, level) not in self._readers:
            index = self._pages["levels"][level] if key == "image" else self._pages["level_masks"][level]
            self._readers[(key, level)] = TileReader(tif, index, self._tiles, (key, level))
        return self._readers[(key, level)]

    def _pick_nodata_source(self) -> str | None:
        rule = self._nodata_rule
        if rule is None:
            return None
        if isinstance(rule, str):
            if rule == "border_black":
                raise MapError(f"{self.path}: nodata='border_black' needs the whole image (black pixels connected to "
                               "its border); convert it to a COG with `aerial-loc cog`, which finds them and writes "
                               "them as the COG's mask, or load it whole (map.read = 'whole')")
            if self._pages["mask"] is not None:
                return "mask"
            if self._gdal_nodata is not None:
                return "value"
            if self._samples == 4:
                return "alpha"
            return None
        return "value"

    def __getstate__(self) -> dict:
        return {"path": str(self.path), "georef": self.georef, "gsd": (self.gsd_x_m, self.gsd_y_m),
                "name": self.name, "source": self.source, "nodata": self._nodata_rule, "identity": self._identity}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["path"], state["georef"], *state["gsd"], name=state["name"], source=state["source"],
                      nodata=state["nodata"])
        if self._identity != tuple(state["identity"]):
            raise MapError(f"{state['path']}: the map file changed after this map was pickled (size or modification "
                           "time differ); make the env again")

    def __repr__(self) -> str:
        return (f"RasterMap(name={self.name!r}, {self.width_px}x{self.height_px} px read by window, "
                f"gsd_x_m={self.gsd_x_m:.6g}, gsd_y_m={self.gsd_y_m:.6g}, georef={self.georef!r}, "
                f"source={self.source!r})")

    # --- size (the frames come from MapGeometry) ------------------------------------------------------------------
    @property
    def width_px(self) -> int:
        return self._width

    @property
    def height_px(self) -> int:
        return self._height

    @property
    def n_overviews(self) -> int:
        return len(self._pages["levels"]) - 1

    @property
    def bundle_path(self) -> None:
        return None

    # --- the whole layers: refused ---------------------------------------------------------------------------
    def _whole(self, layer: str) -> MapError:
        size = gb(3 * self.width_px * self.height_px)
        return MapError(
            f"map '{self.name}' ({self.path.name}, {self.width_px} x {self.height_px} px, {size} of RGB decoded) "
            f"is read by window: its whole '{layer}' layer is not loaded. Read "
            "windows (RasterMap.read / RasterMap.window); to load a map that fits in memory whole, set map.read = "
            "'whole' (gym.make(id, path=..., read='whole')) or use world.maps.load_orthomap")

    @property
    def rgb(self) -> np.ndarray:
        raise self._whole("rgb")

    @property
    def nodata(self) -> np.ndarray:
        raise self._whole("nodata")

    def valid_mask(self) -> np.ndarray:
        raise self._whole("nodata")

    # --- windows ----------------------------------------------------------------------------------------------
    def _check_window(self, u0: int, v0: int, w: int, h: int, level: int) -> None:
        if not 0 <= level <= self.n_overviews:
            raise MapError(f"RasterMap '{self.name}': level {level} does not exist; the file has overview levels "
                           f"0..{self.n_overviews}")
        lw, lh = -(-self.width_px // (1 << level)), -(-self.height_px // (1 << level))
        if w < 1 or h < 1 or u0 < 0 or v0 < 0 or u0 + w > lw or v0 + h > lh:
            raise MapError(f"RasterMap '{self.name}': window u0={u0}, v0={v0}, {w} x {h} px is not inside the "
                           f"{lw} x {lh} px map (level {level})")

    def read(self, u0_px: int, v0_px: int, width_px: int, height_px: int, *,
             level: int = 0) -> tuple[np.ndarray, np.ndarray | None]:
        """The window [v0, v0 + h) x [u0, u0 + w) at ``level`` (0: full resolution, k: the file's k-th overview):
        (rgb (h, w, 3) uint8, nodata (h, w) bool, or None where the map declares no no-data)."""
        u0, v0, w, h = (int(x) for x in (u0_px, v0_px, width_px, height_px))
        self._check_window(u0, v0, w, h, level)
        data = self._reader("image", level).read(u0, v0, w, h)
        c = data.shape[2]
        colour = data[..., :3] if c == 4 else data
        src = self._nodata_source
        nodata = None
        if src == "mask" and self._pages["level_masks"][level] is not None:
            nodata = ~self._reader("mask", level).read(u0, v0, w, h)[..., 0].astype(bool)
        elif src == "value" or src == "mask":   # an overview without its mask: the value rule, if any
            value = self._gdal_nodata if isinstance(self._nodata_rule, str) else self._nodata_rule
            if value is not None:
                nodata = (colour == value).all(axis=-1)
        elif src == "alpha":
            nodata = data[..., 3] == 0
        rgb = np.repeat(colour, 3, axis=2) if colour.shape[2] == 1 else np.ascontiguousarray(colour)
        return rgb, nodata

    def window(self, u0_px: int, v0_px: int, width_px: int, height_px: int, *, name: str | None = None) -> Any:
        """The window as an in-memory ``Orthomap`` (its own frame, origin at the window's south-west corner; the
        georeference shifted), as ``Orthomap.crop`` of the map loaded whole would give."""
        from aerial_loc_env.world.maps.orthomap import Orthomap

        rgb, nodata = self.read(u0_px, v0_px, width_px, height_px)
        return Orthomap(rgb, self.gsd_x_m, self.gsd_y_m, self.georef.shifted(int(u0_px), int(v0_px)),
                        nodata=nodata, name=name or f"{self.name}_window", source=self.source)

    # --- the validity grid ------------------------------------------------------------------------------------
    def validity_blocks(self) -> np.ndarray | None:
        """(ceil(H / BLOCK_PX), ceil(W / BLOCK_PX)) bool, True where a block holds any no-data pixel; None when the
        map declares no no-data. See the module docstring for how it is made and cached."""
        if self._nodata_source is None:
            return None
        if self._validity is None:   # kept: the env's flyable region and every estimator's reset ask for it
            self._validity = self._blocks_from_mask() if self._nodata_source == "mask" else \
                _cached_grid(self._identity, repr(self._nodata_rule), self._blocks_from_image)
            self._validity.flags.writeable = False
        return self._validity

    def _blocks_from_mask(self) -> np.ndarray:
        reader = self._reader("mask", 0)
        if reader.seg_h % BLOCK_PX or reader.seg_w % BLOCK_PX:
            return self._blocks_by_bands(lambda u0, v0, w, h: ~reader.read(u0, v0, w, h)[..., 0].astype(bool))
        rows, cols = reader.segment_grid()
        th, tw = reader.seg_h // BLOCK_PX, reader.seg_w // BLOCK_PX
        grid = np.zeros((rows * th, cols * tw), bool)
        seen: dict[bytes, np.ndarray] = {}
        for r in range(rows):
            in_h = min(reader.seg_h, self.height_px - r * reader.seg_h)
            for c in range(cols):
                idx = r * cols + c
                data = reader.raw(idx)
                in_w = min(reader.seg_w, self.width_px - c * reader.seg_w)
                key = (hashlib.blake2b(data, digest_size=16).digest(), in_h, in_w)
                if key not in seen:
                    valid = reader.decode(data, idx)[..., 0].astype(bool)
                    valid[in_h:] = True          # an edge tile's padding lies outside the map
                    valid[:, in_w:] = True
                    seen[key] = ~valid.reshape(th, BLOCK_PX, tw, BLOCK_PX).all(axis=(1, 3))
                grid[r * th:(r + 1) * th, c * tw:(c + 1) * tw] = seen[key]
        return grid[:-(-self.height_px // BLOCK_PX), :-(-self.width_px // BLOCK_PX)]

    def _blocks_from_image(self) -> np.ndarray:
        return self._blocks_by_bands(lambda u0, v0, w, h: self.read(u0, v0, w, h)[1])

    def _blocks_by_bands(self, nodata_of) -> np.ndarray:
        """The grid from full-width bands of no-data (None: none in the band), one band in memory at a time."""
        w, h = self.width_px, self.height_px
        nb_h, nb_w = -(-h // BLOCK_PX), -(-w // BLOCK_PX)
        grid = np.zeros((nb_h, nb_w), bool)
        band = max(BLOCK_PX, (32 << 20) // max(1, 4 * w) // BLOCK_PX * BLOCK_PX)
        for v0 in range(0, h, band):
            hh = min(band, h - v0)
            nd = nodata_of(0, v0, w, hh)
            if nd is None or not nd.any():
                continue
            padded = np.zeros((-(-hh // BLOCK_PX) * BLOCK_PX, nb_w * BLOCK_PX), bool)
            padded[:hh, :w] = nd
            i0 = v0 // BLOCK_PX
            grid[i0:i0 + padded.shape[0] // BLOCK_PX] = padded.reshape(-1, BLOCK_PX, nb_w, BLOCK_PX).any(axis=(1, 3))
        return grid


def _cached_grid(identity: tuple, rule: str, make) -> np.ndarray:
    """A validity grid kept in the cache folder under the file's identity (path, size, modification time)."""
    from aerial_loc_env.paths import atomic_write_bytes, cache_dir

    key = hashlib.sha256(json.dumps([list(identity), rule, BLOCK_PX]).encode()).hexdigest()[:24]
    path = cache_dir("maps", "validity") / f"{Path(identity[0]).name}-{key}.npy"
    if path.is_file():
        try:
            grid = np.load(path, allow_pickle=False)
            if grid.dtype == np.bool_ and grid.ndim == 2:
                return grid
        except (OSError, ValueError):
            pass   # a damaged entry: made again below
    grid = make()
    try:
        import io as _io

        buf = _io.BytesIO()
        np.save(buf, grid, allow_pickle=False)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(path, buf.getvalue())
    except OSError:
        pass   # a cache that cannot be written costs time on the next open, never the run
    return grid


def window_for_box(frame: Any, box_m: tuple[float, float, float, float], pad_m: float,
                   align_px: int = BLOCK_PX) -> tuple[int, int, int, int]:
    """The pixel window (u0, v0, w, h) of ``frame`` (a map's geometry) covering the world box (x0, y0, x1, y1)
    grown by ``pad_m`` on every side, aligned outwards to ``align_px`` and clipped to the map."""
    x0, y0, x1, y1 = box_m
    u_lo = math.floor((x0 - pad_m) / frame.gsd_x_m) // align_px * align_px
    u_hi = -(-math.ceil((x1 + pad_m) / frame.gsd_x_m) // align_px) * align_px
    v_lo = math.floor(frame.height_px - (y1 + pad_m) / frame.gsd_y_m) // align_px * align_px
    v_hi = -(-math.ceil(frame.height_px - (y0 - pad_m) / frame.gsd_y_m) // align_px) * align_px
    u0, v0 = max(0, u_lo), max(0, v_lo)
    u1, v1 = min(frame.width_px, u_hi), min(frame.height_px, v_hi)
    if u1 <= u0 or v1 <= v0:
        raise MapError(f"map '{getattr(frame, 'name', 'map')}': the box {box_m} m lies outside the map")
    return u0, v0, u1 - u0, v1 - v0
