"""Loading orthomaps from image files (GeoTIFF, PNG/JPEG/TIFF + ESRI world file) and bundle directories.

Supported rasters: unsigned 8-bit or 16-bit, with 1 (grey), 3 (RGB) or 4 (RGBA) channels. Grey becomes RGB;
alpha 0 marks no-data. 16-bit data are mapped linearly to 0..255 from the actual value range of the valid
pixels (min -> 0, max -> 255); the range used is written into ``Orthomap.source`` so the conversion is on record
without a warning. Float, signed, 1-bit, palette, 2-channel and >4-channel rasters are rejected.

Georeference, first match wins: an explicit ``world_file``; GeoTIFF tags (ModelPixelScale + ModelTiepoint, or
ModelTransformation; PixelIsArea / PixelIsPoint; EPSG code from the GeoKey directory); a world file beside the
image (``.pgw``/``.jgw``/``.tfw``/``<ext>w``/``.wld``); else ``gsd_m`` with a nominal local tangent plane. World files
and GeoTIFFs without an EPSG code need ``crs``. The map must be north-up (no rotation terms).

No-data (``nodata="auto"``): the GDAL_NODATA tag if present; else alpha == 0 for RGBA; else the black pixels
(every channel <= ``nodata_black_max``) connected to the image border, so black wedges outside a mosaic become
no-data but a black roof inside it does not.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps.geo import (
    AffineGeoref,
    Georeference,
    LocalTangentGeoref,
    georef_for_crs,
    normalize_crs,
    regional_crs_covering,
)
from aerial_loc_env.world.maps.orthomap import Orthomap
from aerial_loc_env.world.maps.raster import (
    READ_MODES,
    WHOLE_LOAD_FACTOR,
    WINDOW_MIN_BYTES,
    RasterMap,
    _pages,
    check_memory,
    tiff_layout,
)

SUPPORTED = "unsigned 8-bit or 16-bit rasters with 1 (grey), 3 (RGB) or 4 (RGBA) channels"
_TIFF_SUFFIXES = (".tif", ".tiff")
_WORLD_SUFFIXES = {".png": (".pgw",), ".jpg": (".jgw",), ".jpeg": (".jgw",), ".tif": (".tfw",), ".tiff": (".tfw",)}
_GDAL_NODATA_TAG = 42113
# GeoTIFF GeoKey values
_MODEL_PROJECTED, _MODEL_GEOGRAPHIC = 1, 2
_RASTER_PIXEL_IS_POINT = 2
_USER_DEFINED = 32767


@dataclass(frozen=True)
class _Raster:
    data: np.ndarray                      # (H, W, C) C in {1, 3, 4}, uint8 or uint16
    geotiff: dict | None = None           # tifffile's geotiff_metadata
    gdal_nodata: float | None = None
    mask_nodata: np.ndarray | None = None  # (H, W) bool from the file's internal (GDAL) mask, True = no-data


# --- public entry point ---------------------------------------------------------------------------------

def load_orthomap(path: str | os.PathLike, *, gsd_m: float | tuple[float, float] | None = None,
                  crs: str | int | None = None, world_file: str | os.PathLike | None = None,
                  name: str | None = None, dsm: str | os.PathLike | np.ndarray | None = None,
                  classes: str | os.PathLike | np.ndarray | None = None,
                  nodata: str | float | None = "auto", nodata_black_max: int = 0,
                  origin_latlon_deg: tuple[float, float] = (0.0, 0.0), mmap: bool = True) -> Orthomap:
    """Load an orthomap from an image file or a bundle directory (see the module docstring).

    gsd_m: ground metres per pixel (one number or (x, y)); required when the file has no georeference, checked
        against the georeference (1 %) otherwise.
    crs: the CRS of a world file or of a GeoTIFF without an EPSG code ("EPSG:3395", 32633, ...).
    dsm / classes: (H, W) layers as arrays or single-band files; the DSM holds heights above ground in metres,
        its non-finite or GDAL_NODATA cells become no-data (height 0).
    nodata: "auto", "border_black" (black border-connected pixels only), None (no no-data layer) or a pixel
        value that marks no-data in every band.
    origin_latlon_deg: nominal origin of a map with no georeference (its lat/lon are then nominal).
    mmap: for bundles, memory-map the layers (read-only, shared between processes).
    """
    path = Path(path)
    if path.is_dir():
        if any(x is not None for x in (gsd_m, crs, world_file, dsm, classes, name)) or nodata != "auto":
            raise MapError(f"{path}: a bundle carries its own name, scale, georeference and layers; "
                           "load it without gsd_m/crs/world_file/dsm/classes/name/nodata")
        return Orthomap.load_bundle(path, mmap=mmap)
    if not path.is_file():
        raise MapError(f"{path}: no such map file or bundle directory")
    check_whole_load(path)
    raster = _read_raster(path)
    data = raster.data
    h, w, c = data.shape
    mask = _nodata_mask(path, raster, nodata, nodata_black_max)
    rgb, note = _to_rgb8(data, mask)
    if mask is not None and mask.all():
        raise MapError(f"{path}: every pixel is no-data (nodata={nodata!r}); nothing to fly over")

    georef, gx, gy, how = _scale(path, _georeference(path, raster.geotiff, crs, world_file), w, h, gsd_m,
                                 origin_latlon_deg)

    dsm_arr = None
    if dsm is not None:
        dsm_arr, dsm_bad = _load_dsm(path, dsm, (h, w))
        if dsm_bad.any():
            mask = dsm_bad if mask is None else (mask | dsm_bad)
    classes_arr = None if classes is None else _load_classes(path, classes, (h, w))
    source = f"{path} [{how}]" + (f" [{note}]" if note else "")
    try:
        return Orthomap(rgb, gx, gy, georef, dsm_m=dsm_arr, nodata=mask, classes=classes_arr,
                        name=name or path.stem, source=source)
    except MapError as exc:
        raise MapError(f"{path}: {exc}") from exc


def _scale(path: Path, found: tuple[Georeference | None, str], w: int, h: int, gsd_m, origin_latlon_deg
           ) -> tuple[Georeference, float, float, str]:
    """(georeference, ground metres per pixel x and y, how it was found): the file's, checked to be plausible and
    to agree with ``gsd_m``, or a nominal local tangent plane at ``gsd_m``."""
    georef, how = found
    if georef is None:
        if gsd_m is None:
            raise MapError(f"{path}: no georeference (no GeoTIFF tags, no world file beside it) and no gsd_m; "
                           "pass gsd_m=<ground metres per pixel>, or world_file=... with crs=...")
        gx, gy = _gsd_pair(path, gsd_m)
        georef = LocalTangentGeoref.centered(*origin_latlon_deg, w, h, gx, gy)
        return georef, gx, gy, f"no georeference, gsd {gx:g} x {gy:g} m, nominal origin {origin_latlon_deg}"
    gx_a, gy_a = check_plausible_pixel(path, georef, how, w, h)
    if gsd_m is not None:
        gx, gy = _gsd_pair(path, gsd_m)
        if abs(gx / gx_a - 1) > 0.01 or abs(gy / gy_a - 1) > 0.01:
            raise MapError(f"{path}: gsd_m={gsd_m} disagrees with the georeference ({gx_a:.6g} x {gy_a:.6g} "
                           "ground m/px at the centre); drop gsd_m or fix the georeference")
    return georef, gx_a, gy_a, how


# --- opened by window or loaded whole ----------------------------------------------------------------------

def open_map(path: str | os.PathLike, *, read: str = "auto", gsd_m: float | tuple[float, float] | None = None,
             crs: str | int | None = None, world_file: str | os.PathLike | None = None, name: str | None = None,
             nodata: str | float | None = "auto", origin_latlon_deg: tuple[float, float] = (0.0, 0.0),
             **whole_only: Any) -> Orthomap | RasterMap:
    """A map file opened by window (``RasterMap``) or loaded whole (``Orthomap``, as ``load_orthomap``).

    read: "window" opens a TIFF whose tiles or strips can be read by window (a COG, any tiled GeoTIFF, a striped
        8-bit one); "whole" loads the map (refused before decoding when it would not fit in memory); "auto" opens
        such a TIFF by window when its RGB layer takes at least ``raster.WINDOW_MIN_BYTES`` decoded, else loads
        it whole. Bundles are always loaded (memory-mapped). The other arguments are ``load_orthomap``'s
        (``dsm``, ``classes``, ``nodata_black_max`` and ``mmap`` only for maps loaded whole).
    """
    if read not in READ_MODES:
        raise MapError(f"{path}: read={read!r}; use one of {', '.join(READ_MODES)}")
    path = Path(path)
    layout = tiff_layout(path) if path.is_file() else None
    problem = None if layout is None else layout.window_problem()
    windowed = read == "window" or (read == "auto" and layout is not None and problem is None
                                    and layout.rgb_bytes >= WINDOW_MIN_BYTES)
    if not windowed:
        return load_orthomap(path, gsd_m=gsd_m, crs=crs, world_file=world_file, name=name, nodata=nodata,
                             origin_latlon_deg=origin_latlon_deg, **whole_only)
    if layout is None:
        raise MapError(f"{path}: read='window' needs a TIFF file (a COG or a tiled GeoTIFF); convert the map with "
                       f"`aerial-loc cog {path} OUT.tif`, or load it whole (read='whole')")
    if problem is not None:
        raise MapError(f"{path}: cannot be read by window: {problem}; convert it with `aerial-loc cog {path} "
                       "OUT.tif` (tiled, with overviews), or load it whole (read='whole')")
    if whole_only:
        raise MapError(f"{path}: {', '.join(sorted(whole_only))} apply to maps loaded whole; this one is read by "
                       "window (read='whole' loads it whole)")
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            geotiff = tif.geotiff_metadata or None
    except Exception as exc:   # tifffile raises many types on corrupt files
        raise MapError(f"{path}: unreadable TIFF: {exc}") from exc
    georef, gx, gy, how = _scale(path, _georeference(path, geotiff, crs, world_file), layout.width_px,
                                 layout.height_px, gsd_m, origin_latlon_deg)
    if isinstance(nodata, (int, float)) and not isinstance(nodata, bool) and not math.isfinite(nodata) or \
            not isinstance(nodata, (int, float, str, type(None))) or isinstance(nodata, bool):
        raise MapError(f"{path}: nodata={nodata!r}; use 'auto', None or a pixel value")
    if isinstance(nodata, str) and nodata not in ("auto", "border_black"):
        raise MapError(f"{path}: nodata={nodata!r}; use 'auto', 'border_black', None or a pixel value")
    return RasterMap(path, georef, gx, gy, name=name or path.stem, nodata=nodata,
                     source=f"{path} [{how}] [read by window]")


def check_whole_load(path: Path) -> None:
    """Refuse, before decoding, an image whose whole load would not fit in the memory available (see
    ``raster.check_memory``): the message names its size and the way out (a COG read by window)."""
    size = _decoded_size(path)
    if size is None:
        return
    w, h, nbytes = size
    layout = tiff_layout(path)
    if layout is not None and layout.window_problem() is None:
        fix = ("It can be read by window instead: open it with read='auto' or read='window' (gym.make(id, "
               "path=..., read='window')).")
    else:
        fix = (f"Convert it to a COG, which is read by window: `aerial-loc cog {path} {path.with_suffix('')}"
               ".cog.tif` (world.maps.write_cog), then fly over the COG.")
    check_memory(f"{path}: the image", w, h, int(WHOLE_LOAD_FACTOR * max(nbytes, 3 * w * h)), fix)


def _decoded_size(path: Path) -> tuple[int, int, int] | None:
    """(width, height, decoded bytes) from the file's header (TIFF, PNG, JPEG), or None when it says nothing."""
    layout = tiff_layout(path)
    if layout is not None:
        return layout.width_px, layout.height_px, \
            layout.width_px * layout.height_px * layout.channels * layout.dtype.itemsize
    with open(path, "rb") as fh:
        head = np.frombuffer(fh.read(65536), dtype=np.uint8)
    found = re.match(r" \((\d+) x (\d+) = ", _image_size(path, head))
    if not found:
        return None
    w, h = int(found.group(1)), int(found.group(2))
    bits = 1
    if bytes(head[:8]) == b"\x89PNG\r\n\x1a\n" and head.size >= 26:   # bit depth and colour type: channels
        bits = (2 if head[24] == 16 else 1) * {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(int(head[25]), 4)
    else:
        bits = 3
    return w, h, w * h * bits


# --- rasters ---------------------------------------------------------------------------------------------

def _read_raster(path: Path) -> _Raster:
    """Read the first image of a file as (H, W, C) in RGB(A) order, rejecting unsupported formats."""
    with open(path, "rb") as fh:
        head = fh.read(32)
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return _read_tiff(path)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 26 and head[24] == 1:
        raise MapError(f"{path}: 1-bit PNG images are not supported; supported: {SUPPORTED}")
    buf = np.fromfile(path, dtype=np.uint8)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    except cv2.error as exc:   # e.g. over OpenCV's pixel limit (OPENCV_IO_MAX_IMAGE_PIXELS, 2**30 by default)
        size = _image_size(path, buf)
        raise MapError(
            f"{path}: OpenCV refuses to decode this image{size}: {str(exc).strip().splitlines()[-1]}. "
            f"Images over OpenCV's limit of {_opencv_max_pixels()} pixels: convert it to a (tiled) GeoTIFF, "
            "which is read without that limit, or raise the limit with the environment variable "
            "OPENCV_IO_MAX_IMAGE_PIXELS") from None
    if img is None:
        raise MapError(f"{path}: not a readable image (PNG, JPEG or TIFF expected)")
    if img.ndim == 3 and img.shape[2] in (3, 4):   # OpenCV gives BGR(A)
        img = img[..., [2, 1, 0, 3][: img.shape[2]]]
    return _Raster(_check_raster(path, img))


def _opencv_max_pixels() -> int:
    return int(os.environ.get("OPENCV_IO_MAX_IMAGE_PIXELS", 2**30))


def _image_size(path: Path, buf: np.ndarray) -> str:
    """' (W x H = N pixels)' from a PNG/JPEG header, or '' when it cannot be read cheaply."""
    head = bytes(buf[:65536])
    w = h = None
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 24:
        w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    elif head[:2] == b"\xff\xd8":
        i = 2
        while i + 9 < len(head) and head[i] == 0xFF:
            marker, seg = head[i + 1], int.from_bytes(head[i + 2:i + 4], "big")
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                h, w = int.from_bytes(head[i + 5:i + 7], "big"), int.from_bytes(head[i + 7:i + 9], "big")
                break
            i += 2 + seg
    return "" if w is None else f" ({w} x {h} = {w * h} pixels)"


def _read_tiff(path: Path) -> _Raster:
    import tifffile

    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages.first
            if page.bitspersample == 1:
                raise MapError(f"{path}: 1-bit (bilevel) TIFF is not supported; supported: {SUPPORTED}")
            if page.photometric in (tifffile.PHOTOMETRIC.PALETTE, tifffile.PHOTOMETRIC.MINISWHITE,
                                    tifffile.PHOTOMETRIC.SEPARATED):
                raise MapError(f"{path}: TIFF photometric {page.photometric.name} is not supported; "
                               f"supported: {SUPPORTED} (RGB or min-is-black grey)")
            img = page.asarray()
            if page.planarconfig == tifffile.PLANARCONFIG.SEPARATE and img.ndim == 3:
                img = np.moveaxis(img, 0, -1)
            geo = tif.geotiff_metadata
            tag = page.tags.get(_GDAL_NODATA_TAG)
            mask_page = _pages(tif)["mask"]
            mask_nodata = None if mask_page is None else ~np.asarray(tif.pages[mask_page].asarray(), dtype=bool)
    except MapError:
        raise
    except Exception as exc:   # tifffile raises many types on corrupt files
        raise MapError(f"{path}: unreadable TIFF: {exc}") from exc
    gdal_nodata = None
    if tag is not None:
        try:
            gdal_nodata = float(str(tag.value).strip().strip("\x00"))
        except ValueError as exc:
            raise MapError(f"{path}: unparsable GDAL_NODATA tag {tag.value!r}") from exc
    if mask_nodata is not None and mask_nodata.ndim == 3:
        mask_nodata = mask_nodata[..., 0]
    return _Raster(_check_raster(path, img), geo or None, gdal_nodata, mask_nodata)


def _check_raster(path: Path, img: np.ndarray) -> np.ndarray:
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3:
        raise MapError(f"{path}: image has shape {img.shape} (multi-page or volumetric?); supported: {SUPPORTED}")
    c = img.shape[2]
    if img.dtype == np.bool_:
        raise MapError(f"{path}: 1-bit image; supported: {SUPPORTED}")
    if img.dtype not in (np.uint8, np.uint16) or c not in (1, 3, 4):
        raise MapError(f"{path}: found dtype {img.dtype} with {c} channel(s); supported: {SUPPORTED}")
    if img.shape[0] < 1 or img.shape[1] < 1:
        raise MapError(f"{path}: empty image, shape {img.shape}")
    return img


def _nodata_mask(path: Path, raster: _Raster, nodata: str | float | None, black_max: int) -> np.ndarray | None:
    data = raster.data
    colour = data[..., :3] if data.shape[2] == 4 else data
    if nodata is None:
        return None
    if isinstance(nodata, str):
        if nodata not in ("auto", "border_black"):
            raise MapError(f"{path}: nodata={nodata!r}; use 'auto', 'border_black', None or a pixel value")
        if nodata == "auto" and raster.mask_nodata is not None:
            mask = raster.mask_nodata
        elif nodata == "auto" and raster.gdal_nodata is not None:
            mask = (colour == raster.gdal_nodata).all(axis=-1)
        elif nodata == "auto" and data.shape[2] == 4:
            mask = data[..., 3] == 0
        else:
            mask = border_connected(colour.max(axis=-1) <= black_max)
    elif isinstance(nodata, (int, float)) and not isinstance(nodata, bool) and math.isfinite(nodata):
        mask = (colour == nodata).all(axis=-1)
    else:
        raise MapError(f"{path}: nodata={nodata!r}; use 'auto', 'border_black', None or a pixel value")
    return mask if mask.any() else None


def border_connected(mask: np.ndarray) -> np.ndarray:
    """The True pixels of ``mask`` 4-connected to the image border (vectorized, one connected-components pass)."""
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=4)
    if n <= 1:
        return np.zeros(mask.shape, dtype=bool)
    edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
    keep = np.zeros(n, dtype=bool)
    keep[edge] = True
    keep[0] = False
    return keep[labels]


def _to_rgb8(data: np.ndarray, mask: np.ndarray | None) -> tuple[np.ndarray, str]:
    """(H, W, C) uint8/uint16 -> (H, W, 3) uint8, and a note on any value scaling."""
    colour = data[..., :3] if data.shape[2] == 4 else data
    note = ""
    if colour.dtype == np.uint16:
        valid = colour if mask is None else colour[~mask]
        lo, hi = (int(valid.min()), int(valid.max())) if valid.size else (0, 65535)
        scale = 255.0 / max(hi - lo, 1)
        colour = np.clip(np.rint((colour.astype(np.float32) - lo) * scale), 0, 255).astype(np.uint8)
        note = f"16-bit, scaled linearly from [{lo}, {hi}] to [0, 255]"
    if colour.shape[2] == 1:
        colour = np.repeat(colour, 3, axis=2)
    return np.ascontiguousarray(colour), note


# --- georeference ----------------------------------------------------------------------------------------

def _georeference(path: Path, geotiff: dict | None, crs: str | int | None,
                  world_file: str | os.PathLike | None) -> tuple[Georeference | None, str]:
    if world_file is not None:
        return _from_world_file(path, Path(world_file), crs)
    if geotiff is not None:
        found = _from_geotiff(path, geotiff, crs)
        if found is not None:
            return found
    for cand in _world_file_candidates(path):
        if cand.is_file():
            return _from_world_file(path, cand, crs)
    return None, ""


def _world_file_candidates(path: Path) -> list[Path]:
    suf = path.suffix.lower()
    names = list(_WORLD_SUFFIXES.get(suf, ())) + [suf + "w", ".wld"]
    return [path.with_suffix(s) for s in names] + [path.with_suffix(s.upper()) for s in names]


def _from_world_file(path: Path, wf: Path, crs: str | int | None) -> tuple[Georeference, str]:
    """ESRI world file: A, D, B, E, C, F with (C, F) the centre of the top-left pixel (our pixel convention)."""
    if not wf.is_file():
        raise MapError(f"{path}: world file {wf} does not exist")
    try:
        vals = [float(x) for x in wf.read_text().split()]
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise MapError(f"{wf}: unreadable world file for {path.name} (6 numbers expected): {exc}") from exc
    if len(vals) != 6:
        raise MapError(f"{wf}: a world file has 6 numbers (A D B E C F), found {len(vals)}")
    a, d, b, e, c, f = vals
    found = crs_beside(path)
    if crs is None and found is None:
        raise MapError(f"{path}: world file {wf.name} has no CRS and no .prj / .aux.xml beside the image names "
                       f"one; {_crs_hint(a, e, c, f)}")
    if crs is not None and found is not None and not _same_crs(crs, found[0]):
        raise MapError(f"{path}: crs={crs!r} was given but {found[1].name} beside the image says "
                       f"{_short(found[0])}; drop crs (the file's CRS is used) or fix the file")
    use = crs if crs is not None else found[0]
    where = f"world file {wf.name}, {_short(normalize_crs(use))}" + (f" from {found[1].name}" if crs is None else "")
    return _north_up(path, (a, b, c, d, e, f), use, where)


# --- the CRS of a world file -------------------------------------------------------------------------------

_EPSG_AUTHORITY = re.compile(r'AUTHORITY\[\s*"EPSG"\s*,\s*"?(\d+)"?\s*\]\s*\]\s*$|^\s*EPSG:(\d+)\s*$',
                             re.IGNORECASE)


def crs_beside(path: Path) -> tuple[str, Path] | None:
    """The CRS named by a ``.prj`` (ESRI/WKT) or a GDAL ``.aux.xml`` (its <SRS>) beside the image, if any:
    ('EPSG:<code>' when the text names its EPSG code, else the WKT for pyproj) and the file it came from."""
    for cand in (path.with_suffix(".prj"), path.with_name(path.name + ".prj"), path.with_name(path.name + ".aux.xml")):
        if not cand.is_file():
            continue
        try:
            text = cand.read_text(encoding="utf-8", errors="replace").strip()
        except OSError as exc:
            raise MapError(f"{cand}: cannot read the CRS file beside {path.name}: {exc}") from exc
        if cand.name.endswith(".aux.xml"):
            import xml.etree.ElementTree as ET

            try:
                srs = ET.fromstring(text).find(".//SRS")
            except ET.ParseError as exc:
                raise MapError(f"{cand}: not a readable GDAL .aux.xml ({exc}); fix or delete it") from exc
            if srs is None or not (srs.text or "").strip():
                continue
            text = srs.text.strip()
        if not text:
            raise MapError(f"{cand}: empty CRS file beside {path.name}; fix or delete it")
        m = _EPSG_AUTHORITY.search(text)
        if m:
            return f"EPSG:{int(m.group(1) or m.group(2))}", cand
        return _wkt_to_crs(text, cand), cand
    return None


def _wkt_to_crs(text: str, source: Path) -> str:
    """A WKT without an EPSG authority: its EPSG code through pyproj when it identifies one, else the WKT."""
    from aerial_loc_env.errors import require_extra

    pyproj = require_extra("pyproj", "geo", f"Reading the CRS in {source.name}")
    try:
        obj = pyproj.CRS.from_user_input(text)
    except pyproj.exceptions.CRSError as exc:
        raise MapError(f"{source}: not a CRS pyproj can read ({exc}); fix it or pass crs='EPSG:<code>'") from exc
    code = obj.to_epsg(min_confidence=70)
    return f"EPSG:{code}" if code else obj.to_wkt()


def _same_crs(a: str | int, b: str) -> bool:
    a, b = normalize_crs(a), normalize_crs(b)
    if a == b:
        return True
    if a.startswith("EPSG:") and b.startswith("EPSG:"):
        return False
    try:
        import pyproj

        return pyproj.CRS.from_user_input(a).equals(pyproj.CRS.from_user_input(b), ignore_axis_order=True)
    except Exception:  # noqa: BLE001 (cannot compare: treat as different, the message names both)
        return False


def _short(crs: str) -> str:
    return crs if len(crs) <= 40 else crs[:37] + "..."


def _crs_hint(a: float, e: float, c: float, f: float) -> str:
    """How to find the CRS, with a guess from the numbers (never a fixed example that may be wrong)."""
    how = ("find the CRS the world file was written in: a .prj or .aux.xml from the same source, the original "
           "GeoTIFF's `gdalsrsinfo` / `gdalinfo`, or the data provider's description; then pass crs='EPSG:<code>' "
           "(or put the .prj beside the image).")
    if abs(c) <= 180 and abs(f) <= 90 and abs(a) < 0.01:
        return how + f" The numbers (x {c:.6g}, y {f:.6g}, pixel {a:.3g}) look like degrees: EPSG:4326?"
    return how + (f" The numbers (x {c:.6g}, y {f:.6g}, pixel {a:.3g}) are projected coordinates, in metres or "
                  "feet: UTM zones, national grids and US State Plane zones (in feet) all give numbers of this size, "
                  "so they cannot tell the CRS; a wrong guess puts the map elsewhere on Earth (loading refuses a "
                  "place outside the CRS's area of use, or in open ocean)")


#: ground metres per pixel an aerial or satellite map can have: beyond this the georeference or its CRS is wrong
GSD_PLAUSIBLE_M = (1e-3, 1e3)


def check_plausible_pixel(path: Path, georef: Georeference, how: str, w: int, h: int) -> tuple[float, float]:
    """Ground metres per pixel at the map centre, after checking that the georeference makes sense: corners on
    the Earth, a pixel between 1 mm and 1 km (a pixel size in the wrong unit or CRS fails this)."""
    with np.errstate(all="ignore"):
        lat, lon = georef.pixel_to_latlon(np.array([0.0, w - 1.0, 0.0, w - 1.0]),
                                          np.array([0.0, 0.0, h - 1.0, h - 1.0]))
        gx, gy = (float(np.ravel(x)[0]) for x in georef.ground_gsd_m((w - 1) / 2.0, (h - 1) / 2.0))
    lo, hi = GSD_PLAUSIBLE_M
    on_earth = bool(np.all(np.isfinite(lat)) and np.all(np.isfinite(lon)) and np.all(np.abs(lat) <= 90.0))
    if on_earth and all(math.isfinite(g) and lo <= g <= hi for g in (gx, gy)):
        check_location(path, georef, how, w, h)
        return gx, gy
    t = getattr(georef, "pixel_to_crs", None)
    proj = getattr(georef, "projection", None)
    unit = getattr(proj, "unit", "CRS unit")
    size = f"{abs(t[0]):g} x {abs(t[4]):g} {unit}(s)" if t is not None else "the pixel size"
    where = "its corners fall outside the CRS's valid area" if not on_earth else \
        f"that is {gx:.3g} x {gy:.3g} m on the ground"
    raise MapError(f"{path}: {how}: pixel size {size} is implausible for an aerial map ({where}; allowed "
                   f"{lo:g} to {hi:g} m per pixel). The pixel size is in the CRS's unit ({unit}): check that the "
                   "CRS is the one the georeference was written in and that the world file belongs to this image")



#: how far outside its CRS's area of use a map may lie, degrees: a UTM zone is commonly used up to half a zone
#: beyond its band (a map straddling two zones keeps one), national grids somewhat beyond their borders
AREA_OF_USE_MARGIN_DEG = 3.0
_FIND_CRS = ("find the CRS the georeference was written in: a .prj or .aux.xml from the same source, the original "
             "GeoTIFF's `gdalsrsinfo` / `gdalinfo`, or the data provider's description")


def check_location(path: Path, georef: Georeference, how: str, w: int, h: int) -> None:
    """Refuse a georeference that puts the map where its CRS is not used: outside the CRS's area of use (EPSG's,
    through pyproj; for UTM the zone's band and hemisphere) by more than ``AREA_OF_USE_MARGIN_DEG``, or, for a
    world file whose CRS the caller chose (no .prj beside it), in open ocean (no national or regional CRS of the
    EPSG database covers the point: ``geo.regional_crs_covering``). Both are what a wrong CRS guess for the
    same numbers gives (a US State Plane zone in feet read as a UTM zone lands in the Pacific)."""
    proj = getattr(georef, "projection", None)
    if proj is None:          # a nominal local tangent plane: nothing to check
        return
    lat, lon = (float(np.ravel(x)[0]) for x in georef.pixel_to_latlon((w - 1) / 2.0, (h - 1) / 2.0))
    crs = getattr(georef, "crs", "the CRS")
    where = f"{path}: {how}: the georeference puts the map's centre at {lat:.4f} deg, {lon:.4f} deg"
    area = proj.area_of_use()
    if area is not None:
        off = area.distance_deg(lat, lon)
        if off > AREA_OF_USE_MARGIN_DEG:
            raise MapError(f"{where}, {off:.1f} deg outside the area of use of {crs} ({area.describe()}). The "
                           f"numbers were most likely written in another CRS; {_FIND_CRS}; then pass "
                           "crs='EPSG:<code>' or put the .prj beside the image")
    chosen = how.startswith("world file") and " from " not in how
    if not chosen:
        return
    regional = regional_crs_covering(lat, lon)
    if regional is not None and not regional:
        raise MapError(f"{where}, in open ocean: no national or regional CRS of the EPSG database covers that point, "
                       f"so the world file's numbers were most likely written in another CRS than {crs} (a national "
                       "grid, or a US State Plane zone in feet, gives numbers of the same size as a UTM zone's); "
                       f"{_FIND_CRS}. A CRS named by the file itself (a .prj beside the image, GeoTIFF tags) is "
                       "trusted: a map of open water loads that way")


def _from_geotiff(path: Path, geo: dict, crs: str | int | None) -> tuple[Georeference, str] | None:
    scale, ties, matrix = geo.get("ModelPixelScale"), geo.get("ModelTiepoint"), geo.get("ModelTransformation")
    if matrix is None and (scale is None or ties is None):
        return None
    point = int(geo.get("GTRasterTypeGeoKey", 1)) == _RASTER_PIXEL_IS_POINT
    half = 0.0 if point else 0.5     # raster coordinate of a pixel centre = (u + half, v + half)
    if matrix is not None:
        m = np.asarray(matrix, dtype=np.float64).reshape(4, 4)
        a, b, f0 = m[0, 0], m[0, 1], m[0, 3]
        d, e, g0 = m[1, 0], m[1, 1], m[1, 3]
        t = (a, b, f0 + half * (a + b), d, e, g0 + half * (d + e))
    else:
        ties = np.asarray(ties, dtype=np.float64).ravel()
        if ties.size != 6:
            raise MapError(f"{path}: {ties.size // 6} GeoTIFF tie points (control points) are not supported, "
                           "only one tie point with ModelPixelScale; warp the image to a grid first")
        sx, sy = float(scale[0]), float(scale[1])
        i, j, x, y = ties[0], ties[1], ties[3], ties[4]
        t = (sx, 0.0, x + (half - i) * sx, 0.0, -sy, y - (half - j) * sy)
    model = int(geo.get("GTModelTypeGeoKey", 0))
    key = "GeographicTypeGeoKey" if model == _MODEL_GEOGRAPHIC else "ProjectedCSTypeGeoKey"
    code = geo.get(key)
    file_crs = f"EPSG:{int(code)}" if code is not None and int(code) != _USER_DEFINED else None
    if file_crs and crs is not None and normalize_crs(crs) != file_crs:
        raise MapError(f"{path}: the GeoTIFF says {file_crs} but crs={crs!r} was given; drop crs or fix the file")
    use = file_crs or crs
    if use is None:
        raise MapError(f"{path}: the GeoTIFF has no EPSG code ({key} missing or user-defined); "
                       "pass crs=, e.g. crs='EPSG:32633'")
    kind = "PixelIsPoint" if point else "PixelIsArea"
    return _north_up(path, t, use, f"GeoTIFF {normalize_crs(use)}, {kind}")


def _north_up(path: Path, t: tuple, crs: str | int, how: str) -> tuple[AffineGeoref, str]:
    try:
        g = georef_for_crs(t, crs)
    except MapError as exc:
        raise MapError(f"{path}: {exc}") from exc
    if not g.is_north_up():
        raise MapError(f"{path}: the georeference {t} is rotated, sheared or flipped; only north-up maps are "
                       "supported (resample it, e.g. with gdalwarp)")
    return g, how


def _gsd_pair(path: Path, gsd_m) -> tuple[float, float]:
    vals = (gsd_m, gsd_m) if np.isscalar(gsd_m) else tuple(gsd_m)
    try:
        gx, gy = (float(x) for x in vals)
    except (TypeError, ValueError) as exc:
        raise MapError(f"{path}: gsd_m must be a number or (x, y) of metres per pixel, got {gsd_m!r}") from exc
    if not (math.isfinite(gx) and math.isfinite(gy) and gx > 0 and gy > 0):
        raise MapError(f"{path}: gsd_m must be > 0 metres per pixel, got {gsd_m!r}")
    return gx, gy


# --- extra layers -----------------------------------------------------------------------------------------

def _read_band(path: Path, src: str | os.PathLike | np.ndarray, what: str) -> tuple[np.ndarray, str, float | None]:
    """A single-band layer from an array or a file: (array, its description, GDAL_NODATA or None)."""
    if isinstance(src, np.ndarray):
        return src, f"the {what} array", None
    f = Path(src)
    if not f.is_file():
        raise MapError(f"{path}: {what} file {f} does not exist")
    nod = None
    if f.suffix.lower() in _TIFF_SUFFIXES:
        import tifffile

        try:
            with tifffile.TiffFile(f) as tif:
                arr = tif.pages.first.asarray()
                tag = tif.pages.first.tags.get(_GDAL_NODATA_TAG)
                nod = float(str(tag.value).strip("\x00 ")) if tag is not None else None
        except Exception as exc:
            raise MapError(f"{f}: unreadable {what} TIFF: {exc}") from exc
    else:
        arr = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        if arr is None:
            raise MapError(f"{f}: unreadable {what} image")
    return arr, str(f), nod


def _load_dsm(path: Path, src, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    arr, desc, nod = _read_band(path, src, "dsm")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.shape != shape:
        raise MapError(f"{path}: the DSM ({desc}) has shape {arr.shape}, the image has {shape}; they must match")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise MapError(f"{path}: the DSM ({desc}) has dtype {arr.dtype}; a real-valued band is needed")
    dsm = arr.astype(np.float32)
    bad = ~np.isfinite(dsm)
    if nod is not None:
        bad |= dsm == np.float32(nod)
    dsm[bad] = 0.0
    return dsm, bad


def _load_classes(path: Path, src, shape: tuple[int, int]) -> np.ndarray:
    arr, desc, _ = _read_band(path, src, "classes")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[..., 0]
    if arr.shape != shape:
        raise MapError(f"{path}: the class map ({desc}) has shape {arr.shape}, the image has {shape}; "
                       "they must match")
    if arr.dtype != np.uint8:
        raise MapError(f"{path}: the class map ({desc}) has dtype {arr.dtype}; uint8 land-cover codes are needed")
    return np.ascontiguousarray(arr)
