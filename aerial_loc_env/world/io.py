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
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import MapError
from .geo import AffineGeoref, Georeference, LocalTangentGeoref, georef_for_crs, normalize_crs
from .orthomap import Orthomap

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
    raster = _read_raster(path)
    data = raster.data
    h, w, c = data.shape
    mask = _nodata_mask(path, raster, nodata, nodata_black_max)
    rgb, note = _to_rgb8(data, mask)
    if mask is not None and mask.all():
        raise MapError(f"{path}: every pixel is no-data (nodata={nodata!r}); nothing to fly over")

    georef, how = _georeference(path, raster, crs, world_file)
    if georef is None:
        if gsd_m is None:
            raise MapError(f"{path}: no georeference (no GeoTIFF tags, no world file beside it) and no gsd_m; "
                           "pass gsd_m=<ground metres per pixel>, or world_file=... with crs=...")
        gx, gy = _gsd_pair(path, gsd_m)
        georef = LocalTangentGeoref.centered(*origin_latlon_deg, w, h, gx, gy)
        how = f"no georeference, gsd {gx:g} x {gy:g} m, nominal origin {origin_latlon_deg}"
    else:
        gx_a, gy_a = (float(x) for x in georef.ground_gsd_m((w - 1) / 2.0, (h - 1) / 2.0))
        if gsd_m is not None:
            gx, gy = _gsd_pair(path, gsd_m)
            if abs(gx / gx_a - 1) > 0.01 or abs(gy / gy_a - 1) > 0.01:
                raise MapError(f"{path}: gsd_m={gsd_m} disagrees with the georeference ({gx_a:.6g} x {gy_a:.6g} "
                               "ground m/px at the centre); drop gsd_m or fix the georeference")
        gx, gy = gx_a, gy_a

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
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    if img is None:
        raise MapError(f"{path}: not a readable image (PNG, JPEG or TIFF expected)")
    if img.ndim == 3 and img.shape[2] in (3, 4):   # OpenCV gives BGR(A)
        img = img[..., [2, 1, 0, 3][: img.shape[2]]]
    return _Raster(_check_raster(path, img))


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
    return _Raster(_check_raster(path, img), geo or None, gdal_nodata)


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
        if nodata == "auto" and raster.gdal_nodata is not None:
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

def _georeference(path: Path, raster: _Raster, crs: str | int | None,
                  world_file: str | os.PathLike | None) -> tuple[Georeference | None, str]:
    if world_file is not None:
        return _from_world_file(path, Path(world_file), crs)
    if raster.geotiff is not None:
        found = _from_geotiff(path, raster.geotiff, crs)
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
    if crs is None:
        raise MapError(f"{path}: world file {wf.name} has no CRS; pass crs=, e.g. crs='EPSG:3395'")
    a, d, b, e, c, f = vals
    return _north_up(path, (a, b, c, d, e, f), crs, f"world file {wf.name}, {normalize_crs(crs)}")


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
