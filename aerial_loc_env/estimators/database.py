"""The database as the estimators read it: the briefing's map, loaded whole (``Orthomap``) or read by window
(``world.maps.raster.RasterMap``, a city-scale COG).

On a map read by window an estimator reads the window around where it searches (``DatabaseWindow``: the pixels
[u0, u1) x [v0, v1) of the whole map) and reads a new one when its search nears that window's edge
(``WindowPolicy``). Positions stay in the whole map's world frame (metres from its south-west corner), and the
layers the estimators build from a window keep the whole map's pixel indices (``SparseLayer``: an array of the
whole map's or level's shape whose memory exists only where a window was written), so every coordinate, every
compiled lookup and every downsampled level value is the one the same estimator computes on the file loaded whole
(``levels.area_window`` makes a window of a level bit for bit): the estimates are the same, while the memory held
is that of the windows (a few footprints), not of the map. Two views are made per window and may differ from the
whole map's near a window's border: the edge model's feature map (Canny, probabilistic Hough lines: not pixelwise)
and the learned agents' rendered views (``WindowedRenderer``: OpenCV's warp rounds its float32 coordinates at the
window's magnitude, a level off on a few pixels of a view).

A search over the whole map (a uniform prior, MCL ``init = "uniform"``, template matching's global search) would
need the whole map: on a map read by window it is refused before the episode starts (``refuse_global_search``).
"""

from __future__ import annotations

import math
import mmap
import sys
import weakref
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from aerial_loc_env.errors import MapError
from aerial_loc_env.estimators.levels import area_window, level_pixels_within
from aerial_loc_env.world.maps.raster import RasterMap, check_memory, gb

#: a pixel box (u0, v0, u1, v1): columns [u0, u1), rows [v0, v1)
Box = tuple[int, int, int, int]

#: Linux's MAP_NORESERVE (the mapping reserves no swap: only the pages written count), absent from ``mmap``
_MAP_NORESERVE = 0x4000


def read_by_window(orthomap: Any) -> bool:
    """Whether ``orthomap`` is a map read by window (or a window of one) rather than one held whole."""
    return isinstance(orthomap, (RasterMap, DatabaseWindow))


def map_size(orthomap: Any) -> str:
    """'W x H px (w x h km at g m/px)', for messages."""
    return (f"{orthomap.width_px} x {orthomap.height_px} px ({orthomap.width_m / 1000:.1f} x "
            f"{orthomap.height_m / 1000:.1f} km at {orthomap.gsd_x_m:.3g} m/px)")


#: id(map layer) -> (weak reference to it, {key: (derived array(s), the other inputs they were made from)})
_DERIVED: dict[int, tuple[weakref.ref, dict[Hashable, tuple[Any, tuple]]]] = {}


def derived_once(layer: np.ndarray, key: Hashable, make: Callable[[], Any], inputs: tuple = ()) -> Any:
    """``make()`` computed once per map layer ``layer`` (the database's RGB held whole) and ``key``, then shared:
    what estimators derive from the map at reset (a gray level, luma words) is the same every episode and for every
    agent on that map, and an agent that resets when a flight's first frame arrives must not spend that frame's
    time converting the map again. ``inputs``: the other arrays ``make`` reads (e.g. the no-data layer), named by
    ``id`` in ``key`` and held with the result (their ids stay theirs while cached). The entries go with the layer
    (a weak reference); a layer that cannot be weakly referenced is not cached. Results must not be written to: mark
    them read-only."""
    lid = id(layer)
    entry = _DERIVED.get(lid)
    if entry is None or entry[0]() is not layer:
        try:
            ref = weakref.ref(layer, lambda _: _DERIVED.pop(lid, None))   # (gone before its id can be reused)
        except TypeError:
            return make()
        entry = _DERIVED[lid] = (ref, {})
    got = entry[1].get(key)
    if got is None:
        got = entry[1][key] = (make(), inputs)
    return got[0]


def refuse_global_search(orthomap: Any, agent: str, why: str) -> None:
    """Raise the ``MapError`` of a search over the whole of a map read by window (see the module docstring)."""
    raise MapError(
        f"{agent}: {why} searches the whole map, but map '{orthomap.name}' ({map_size(orthomap)}, "
        f"{gb(3 * orthomap.width_px * orthomap.height_px)} of RGB) is read by window: an estimator reads the windows "
        "around a gaussian prior only. Start from a position (episode.start = 'tracking'), use a tracking agent, or "
        "load a map that fits in memory whole (map.read = 'whole')")


def box_union_contains(outer: Box | None, inner: Box) -> bool:
    return outer is not None and outer[0] <= inner[0] and outer[1] <= inner[1] and inner[2] <= outer[2] \
        and inner[3] <= outer[3]


def grow(box: Box, px: int, width: int, height: int) -> Box:
    """``box`` grown by ``px`` on every side and clipped to a ``width`` x ``height`` grid."""
    return max(0, box[0] - px), max(0, box[1] - px), min(width, box[2] + px), min(height, box[3] + px)


def world_box(frame: Any, x_min: float, y_min: float, x_max: float, y_max: float, radius_m: float) -> Box:
    """The map pixels (clipped to the map) within ``radius_m`` of the world box, plus two pixels of slack (the
    nearest pixel of a rounding, a bilinear neighbour)."""
    u_lo = math.floor((x_min - radius_m) / frame.gsd_x_m - 0.5) - 2
    u_hi = math.ceil((x_max + radius_m) / frame.gsd_x_m - 0.5) + 3
    v_lo = math.floor(frame.height_px - 0.5 - (y_max + radius_m) / frame.gsd_y_m) - 2
    v_hi = math.ceil(frame.height_px - 0.5 - (y_min - radius_m) / frame.gsd_y_m) + 3
    box = (max(0, u_lo), max(0, v_lo), min(frame.width_px, u_hi), min(frame.height_px, v_hi))
    if box[2] <= box[0] or box[3] <= box[1]:   # wholly off the map: the nearest pixels (models clip to the edge)
        u = min(max(u_lo, 0), frame.width_px - 1)
        v = min(max(v_lo, 0), frame.height_px - 1)
        box = (u, v, u + 1, v + 1)
    return box


# --- arrays of the whole map's shape, backed where written ------------------------------------------------

def lazy_zeros(shape: tuple[int, ...], dtype: Any) -> np.ndarray:
    """A zero array whose memory is committed page by page as it is written (reading unwritten pages costs
    none): an anonymous private mapping without transparent huge pages (one 2 MB page per written row would
    commit whole bands of a wide map), without swap reservation on Linux. Elsewhere ``np.zeros`` (the system's
    own lazily zeroed allocation)."""
    dtype = np.dtype(dtype)
    count = int(np.prod(shape, dtype=np.int64))
    nbytes = max(1, count * dtype.itemsize)
    if sys.platform.startswith("linux"):
        try:
            buf = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | _MAP_NORESERVE,
                            prot=mmap.PROT_READ | mmap.PROT_WRITE)
        except OSError as exc:
            raise MapError(f"cannot map {gb(nbytes)} of address space for a database layer of shape {shape}: "
                           f"{exc}") from exc
        if hasattr(buf, "madvise") and hasattr(mmap, "MADV_NOHUGEPAGE"):
            buf.madvise(mmap.MADV_NOHUGEPAGE)
        return np.frombuffer(buf, dtype=dtype, count=count).reshape(shape)
    return np.zeros(shape, dtype)


class SparseLayer:
    """A layer of the whole map's (or a level's) pixel grid whose values exist in the box last written
    (``box``, in this layer's pixels): ``array`` has the whole grid's shape, (H, W[, C]) or, ``planar``,
    (C, H, W). Pickles as its shape and the written box's values (not the whole grid)."""

    def __init__(self, height: int, width: int, channels: int | None, dtype: Any, *, planar: bool = False) -> None:
        self.height, self.width, self.channels, self.dtype, self.planar = height, width, channels, np.dtype(dtype), \
            planar
        shape = (height, width) if channels is None else ((channels, height, width) if planar
                                                           else (height, width, channels))
        self.array = lazy_zeros(shape, self.dtype)
        self.box: Box | None = None
        self.written = 0          # pixels written since the array was made (the memory it may hold)

    def write(self, box: Box, values: np.ndarray, *, mark: bool = True) -> None:
        """Store ``values`` (h, w[, C]) at ``box`` (``mark``: ``box`` becomes the box that holds values)."""
        u0, v0, u1, v1 = box
        if self.planar:
            self.array[:, v0:v1, u0:u1] = np.moveaxis(values.reshape(v1 - v0, u1 - u0, -1), 2, 0)
        else:
            self.array[v0:v1, u0:u1] = values
        self.written += (u1 - u0) * (v1 - v0)
        if mark:
            self.box = box

    def read(self, box: Box) -> np.ndarray:
        u0, v0, u1, v1 = box
        return np.moveaxis(self.array[:, v0:v1, u0:u1], 0, 2) if self.planar else self.array[v0:v1, u0:u1]

    def __getstate__(self) -> dict:
        state = {k: v for k, v in self.__dict__.items() if k != "array"}
        state["values"] = None if self.box is None else np.array(self.read(self.box))
        return state

    def __setstate__(self, state: dict) -> None:
        values, box = state.pop("values"), state["box"]
        self.__init__(state["height"], state["width"], state["channels"], state["dtype"], planar=state["planar"])
        if box is not None:
            self.write(box, values)


def box_area(box: Box) -> int:
    return max(0, box[2] - box[0]) * max(0, box[3] - box[1])


def box_minus(box: Box, other: Box) -> list[Box]:
    """``box`` less ``other``, as at most four boxes (the bands above and below, then left and right)."""
    u0, v0, u1, v1 = box
    a0, b0, a1, b1 = max(u0, other[0]), max(v0, other[1]), min(u1, other[2]), min(v1, other[3])
    if a0 >= a1 or b0 >= b1:
        return [box]
    parts = [(u0, v0, u1, b0), (u0, b1, u1, v1), (u0, b0, a0, b1), (a1, b0, u1, b1)]
    return [p for p in parts if box_area(p) > 0]


#: a layer carried from window to window is made again from scratch once it was written this many times its box
#: (the pages the earlier windows wrote are then given back)
REUSE_WRITTEN = 4


# --- a window of the database -------------------------------------------------------------------------------

class DatabaseWindow:
    """The pixels ``box`` = (u0, v0, u1, v1) of ``frame`` (a map read by window), as an estimator's reset takes its
    database: the whole map's geometry and frames (``width_px``, ``gsd_x_m``, ``world_to_pixel``, ...: the same
    numbers as the map loaded whole), with the window's pixels as ``rgb`` (h, w, 3) and ``nodata`` (h, w) (None
    when the map declares none). Code that indexes pixels subtracts ``origin_px``; the layers below keep the
    whole map's pixel indices."""

    dsm_m = None
    classes = None

    def __init__(self, frame: RasterMap, box: Box, *, where: str = "estimator",
                 previous: DatabaseWindow | None = None) -> None:
        u0, v0, u1, v1 = box
        w, h = u1 - u0, v1 - v0
        check_memory(f"{where}: the database window of map '{frame.name}'", w, h, 8 * w * h,
                     "Lower the altitude (a smaller footprint) or the prior's spread (episode.prior_std_m)")
        self.frame, self.box = frame, (int(u0), int(v0), int(u1), int(v1))
        same_map = previous is not None and previous.frame is frame
        self.has_nodata = previous.has_nodata if same_map else frame_has_nodata(frame)
        self._pixels: tuple[np.ndarray, np.ndarray | None] | None = None     # read on first use
        # the layers made of the window before (same map): kept, and only their part outside it made again
        self._layers: dict[Any, SparseLayer] = {}
        if same_map:
            self._layers, previous._layers = previous._layers, {}

    def _carried(self, key: Any, shape: tuple[int, int, int | None], dtype: Any, planar: bool, box: Box,
                 make: Callable[[Box], np.ndarray]) -> SparseLayer:
        """The layer ``key`` with values over ``box``: the previous window's, completed over what it lacks, or a new
        one (``make(part)``: the values over a part of ``box``)."""
        height, width, channels = shape
        layer = self._layers.get(key) if key is not None else None
        if layer is None or layer.box is None or (layer.height, layer.width, layer.channels, layer.dtype,
                                                  layer.planar) != (height, width, channels, np.dtype(dtype), planar) \
                or layer.written > REUSE_WRITTEN * box_area(box):
            layer = SparseLayer(height, width, channels, dtype, planar=planar)
            layer.write(box, make(box))
        else:
            for part in box_minus(box, layer.box):
                layer.write(part, make(part), mark=False)
            layer.box = box
        if key is not None:
            self._layers[key] = layer
        return layer

    @property
    def rgb(self) -> np.ndarray:
        """The window's colour (h, w, 3) uint8."""
        return self.read(self.box)[0]

    @property
    def nodata(self) -> np.ndarray | None:
        """The window's no-data flags (h, w) bool, or None when the map declares no no-data."""
        return self.read(self.box)[1]

    def read(self, part: Box) -> tuple[np.ndarray, np.ndarray | None]:
        """(rgb, nodata) of the map pixels ``part`` (inside the window): cut from the window's pixels once they
        were read, else read alone (the map keeps the tiles it decoded)."""
        if self._pixels is None:
            if part != self.box:
                return self._read_frame(part)
            self._pixels = self._read_frame(self.box)
        u0, v0, u1, v1 = part
        wu0, wv0 = self.origin_px
        rgb, nodata = self._pixels
        rows, cols = slice(v0 - wv0, v1 - wv0), slice(u0 - wu0, u1 - wu0)
        return rgb[rows, cols], (None if nodata is None else nodata[rows, cols])

    def _read_frame(self, part: Box) -> tuple[np.ndarray, np.ndarray | None]:
        u0, v0, u1, v1 = part
        rgb, nodata = self.frame.read(u0, v0, u1 - u0, v1 - v0)
        if not self.has_nodata:
            return rgb, None
        return rgb, nodata if nodata is not None else np.zeros(rgb.shape[:2], bool)

    @property
    def origin_px(self) -> tuple[int, int]:
        return self.box[0], self.box[1]

    def __getattr__(self, name: str) -> Any:
        # geometry, georeference, names and frames: the whole map's
        if name in ("width_px", "height_px", "width_m", "height_m", "gsd_x_m", "gsd_y_m", "georef", "name",
                    "source", "pixel_to_world", "world_to_pixel", "world_to_latlon", "latlon_to_world",
                    "contains_world", "check_fits", "bundle_path"):
            return getattr(self.frame, name)
        raise AttributeError(name)

    def __repr__(self) -> str:
        return f"DatabaseWindow({self.frame.name!r}, box={self.box})"

    # the layers of the whole map's pixel grid, filled over the window
    def pixel_bytes(self, channels: int) -> tuple[np.ndarray, np.ndarray | None]:
        """What the intensity-pair kernel reads, flat over the whole map: the RGB bytes (``channels`` = 3) or the
        luma bytes (1, ``cv2.COLOR_RGB2GRAY``), and the no-data flags (None when the map declares none)."""
        H, W = self.height_px, self.width_px

        def colour(part: Box) -> np.ndarray:
            rgb = self.read(part)[0]
            return rgb if channels == 3 else cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY)

        db = self._carried(("bytes", channels), (H, W, 3 if channels == 3 else None), np.uint8, False, self.box,
                           colour)
        nodata = None
        if self.has_nodata:
            nd = self._carried(("nodata",), (H, W, None), bool, False, self.box, lambda p: self.read(p)[1])
            nodata = nd.array.reshape(-1)
        return db.array.reshape(-1), nodata

    def level(self, layer: np.ndarray, size: tuple[int, int], dtype: Any, *, planar: bool = False,
              nan_on_nodata: bool = False, key: Any = None) -> SparseLayer:
        """``cv2.resize(layer of the whole map, size, INTER_AREA)`` over the level pixels this window's pixels
        make (``levels.area_window``), ``layer`` being this window's (h, w[, C]); ``size`` = the map's size gives
        the layer itself. ``nan_on_nodata``: NaN (every channel) where a level pixel averages any no-data pixel.
        ``key``: carry the level from window to window under that name (see ``_carried``)."""
        layer = np.asarray(layer)
        u0, v0 = self.origin_px
        return self._level(lambda src: layer[src[1] - v0:src[3] - v0, src[0] - u0:src[2] - u0], layer.shape[2:],
                           size, dtype, planar, nan_on_nodata, key)

    def level_of(self, pixelwise: Callable[[np.ndarray], np.ndarray], size: tuple[int, int], dtype: Any, *,
                 planar: bool = False, nan_on_nodata: bool = False, key: Any = None) -> SparseLayer:
        """``level`` of ``pixelwise(rgb)`` (a function of each pixel's colour alone, e.g. its luma), made only
        where the level lacks values: from the map pixels under them, not from the whole window."""
        probe = np.asarray(pixelwise(np.zeros((1, 1, 3), np.uint8)))
        return self._level(lambda src: pixelwise(self.read(src)[0]), probe.shape[2:], size, dtype, planar,
                           nan_on_nodata, key)

    def _level(self, source: Callable[[Box], np.ndarray], trailing: tuple[int, ...], size: tuple[int, int],
               dtype: Any, planar: bool, nan_on_nodata: bool, key: Any) -> SparseLayer:
        src = (self.width_px, self.height_px)
        channels = (1 if planar else None) if not trailing else trailing[0]
        box = self.level_box(size)
        if box is None:
            return SparseLayer(size[1], size[0], channels, dtype, planar=planar)
        flags = self.level_flags(size) if nan_on_nodata and self.has_nodata else None

        def make(part: Box) -> np.ndarray:
            values = np.asarray(source(part) if tuple(size) == src else _area(source, src, size, part, dtype))
            values = values.astype(dtype, copy=True)
            if flags is not None:
                values[flags(part)] = np.nan
            return values

        return self._carried(key, (size[1], size[0], channels), dtype, planar, box, make)

    def level_flags(self, size: tuple[int, int]) -> Callable[[Box], np.ndarray]:
        """Level pixels of ``size`` that average any no-data pixel (``cv2.resize(nodata as float32, size,
        INTER_AREA) > 0`` of the whole map), as a function of a box of this window's level pixels."""
        src = (self.width_px, self.height_px)

        def bad(part: Box) -> np.ndarray:
            return self.read(part)[1].astype(np.float32)

        def flags(part: Box) -> np.ndarray:
            return (bad(part) if tuple(size) == src else _area(bad, src, size, part, np.float32)) > 0

        return flags

    def level_nodata(self, size: tuple[int, int], *, key: Any = None) -> SparseLayer | None:
        """``level_flags`` as a bool layer of the whole level's grid (None when the map declares no no-data)."""
        box = self.level_box(size)
        if not self.has_nodata or box is None:
            return None
        return self._carried(key, (size[1], size[0], None), bool, False, box, self.level_flags(size))

    def level_box(self, size: tuple[int, int]) -> Box | None:
        """The level pixels of ``size`` (w, h) whose source pixels all lie in this window (None: none do)."""
        src = (self.width_px, self.height_px)
        return self.box if tuple(size) == src else level_pixels_within(src, tuple(size), self.box)


def _area(source: Callable[[Box], np.ndarray], src: tuple[int, int], size: tuple[int, int], part: Box,
          dtype: Any) -> np.ndarray:
    """``levels.area_window`` of the level pixels ``part``, the source pixels under them from ``source(box)``."""
    return area_window(lambda u, v, w, h: source((u, v, u + w, v + h)), src, size, part, dtype)


def frame_has_nodata(frame: RasterMap) -> bool:
    """Whether a map read by window has any no-data pixel (its validity grid: exact at that question)."""
    blocks = frame.validity_blocks()
    return blocks is not None and bool(blocks.any())


__all__ = ["Box", "DatabaseWindow", "SparseLayer", "WindowPolicy", "WindowedRenderer", "database_renderer",
           "derived_once", "lazy_zeros", "read_by_window", "refuse_global_search"]


# --- when to read a new window ------------------------------------------------------------------------------

@dataclass
class WindowPolicy:
    """Which window an estimator reads, and when it reads the next one.

    The need is what the estimator reads now: the map pixels within ``radius_m`` (a footprint radius, or a
    search window's half-size) of every position it scores, or a box it gives. The window read is the need grown
    by ``guard`` + ``ahead`` (``guard_radii`` and ``ahead_radii`` footprint radii, ``footprint_m``); the next one
    is read when the need leaves the current window shrunk by ``guard`` (room for the models' own reads around a
    point: level pixels and filters, a few samples of the patch grid). ``ahead`` is how far the vehicle flies
    before that happens: memory against how often a window is read."""

    frame: Any
    footprint_m: Callable[[float], float]
    radius_m: Callable[[float], float] | None = None
    ahead_radii: float = 1.0
    guard_radii: float = 0.5
    align_px: int = 1            # windows start and end on multiples of this (inside the map)
    window: Box | None = None
    reads: int = 0

    def _px(self, metres: float) -> int:
        return int(math.ceil(metres / min(self.frame.gsd_x_m, self.frame.gsd_y_m)))

    def update(self, xy_m: np.ndarray, altitude_m: float) -> Box | None:
        """The new window when the current one no longer covers the positions ``xy_m`` (N, 2) at ``altitude_m``,
        else None."""
        xy = np.asarray(xy_m, dtype=np.float64)
        x, y = xy[..., 0], xy[..., 1]          # (per column: a reduction along axis 0 of (N, 2) is far slower)
        radius = (self.radius_m or self.footprint_m)(altitude_m)
        need = world_box(self.frame, float(x.min()), float(y.min()), float(x.max()), float(y.max()), radius)
        return self.update_box(need, altitude_m)

    def update_box(self, need: Box, altitude_m: float) -> Box | None:
        """The new window when the current one no longer covers the map pixels ``need``, else None."""
        w, h = self.frame.width_px, self.frame.height_px
        guard = 8 + self._px(self.guard_radii * self.footprint_m(altitude_m))
        if self.window is not None:
            u0, v0, u1, v1 = self.window
            inner = (u0 + guard if u0 > 0 else 0, v0 + guard if v0 > 0 else 0,
                     u1 - guard if u1 < w else w, v1 - guard if v1 < h else h)
            if box_union_contains(inner, need):
                return None
        ahead = self._px(self.ahead_radii * self.footprint_m(altitude_m))
        u0, v0, u1, v1 = grow(need, guard + ahead, w, h)
        a = self.align_px
        self.window = (u0 // a * a, v0 // a * a, min(w, -(-u1 // a) * a), min(h, -(-v1 // a) * a))
        self.reads += 1
        return self.window


class WindowedRenderer:
    """``CameraRenderer.database_patch`` over a map read by window (the learned agents' view of the database):
    a renderer of the window around the pose (``CameraRenderer(frame=, origin_px=)``, poses in the whole map's
    world), made again for a new window when a pose nears the edge. Windows are aligned to 16 pixels and keep a
    footprint radius of margin, so the pyramid levels the renderer makes of them equal the whole map's there (as
    the env's own window)."""

    def __init__(self, frame: RasterMap, camera: Any, **renderer: Any) -> None:
        from aerial_loc_env.sensors.flight import footprint_radius_m

        self.frame, self.camera, self.options = frame, camera, renderer
        self.policy = WindowPolicy(frame, lambda alt: footprint_radius_m(*camera.footprint_m(alt)), guard_radii=1.0,
                                   align_px=16)
        self._renderer: Any = None

    def database_patch(self, pose: Any, size: tuple[int, int] | None = None, *, strict: bool = False) -> np.ndarray:
        from aerial_loc_env.sensors.render import CameraRenderer

        box = self.policy.update(np.array([[pose[0], pose[1]]]), float(pose[3]))
        if box is not None:
            u0, v0, u1, v1 = box
            w, h = u1 - u0, v1 - v0
            check_memory(f"the database window of map '{self.frame.name}'", w, h, 12 * w * h,
                         "Lower the altitude (a smaller footprint)")
            window = self.frame.window(u0, v0, w, h, name=f"{self.frame.name}-agent-window")
            self._renderer = CameraRenderer(window, self.camera, frame=self.frame, origin_px=(u0, v0), **self.options)
        return self._renderer.database_patch(pose, size, strict=strict)


def database_renderer(orthomap: Any, camera: Any, **options: Any) -> Any:
    """A renderer of the database's views: ``CameraRenderer`` of a map held whole, ``WindowedRenderer`` of one read
    by window."""
    if isinstance(orthomap, RasterMap):
        return WindowedRenderer(orthomap, camera, **options)
    from aerial_loc_env.sensors.render import CameraRenderer

    return CameraRenderer(orthomap, camera, **options)
