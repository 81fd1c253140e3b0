"""Writing a map as a Cloud-Optimized GeoTIFF (COG): tiled, with overviews and the map's no-data as an internal
mask, so that it is opened, not loaded (``world.maps.raster``), and its pyramid levels come from the overviews.

``write_cog(source, out)`` takes anything the loader accepts (a file, a bundle, an ``Orthomap``) or a map opened
by window, and writes it band of tiles by band of tiles: a map larger than memory is converted without ever being
whole in memory. The pixels go through GDAL's COG driver (``rasterio``, the ``geo`` extra): a temporary tiled
GeoTIFF beside ``out`` is written first, then copied into the COG layout with the overviews, then moved onto
``out`` (an existing ``out`` is replaced only with ``overwrite=True``; on any failure nothing is left behind).
The temporary files take about 1.6 times the map's decoded RGB on the disk of ``out`` while it is written.
The no-data the loader found (the GDAL nodata value, alpha, a mask, black border wedges) becomes the COG's mask,
so the COG read by window has the same no-data as the source read whole.
"""

from __future__ import annotations

import os
import tempfile
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from aerial_loc_env.errors import ConfigError, MapError, require_extra
from aerial_loc_env.world.maps.geo import AffineGeoref, Georeference

#: tile side of the COGs written (pixels): a window read decodes whole tiles
COG_BLOCK_PX = 512
COMPRESSIONS = ("jpeg", "deflate", "lzw", "zstd", "none")
_GDAL_CACHE_MB = 256   # GDAL's block cache while writing (its default is 5 % of the machine's memory)


class TileSource(Protocol):
    """What ``write_cog`` reads: the map's size, georeference and name, and its pixels by window."""

    width_px: int
    height_px: int
    georef: Georeference
    name: str

    def read(self, u0_px: int, v0_px: int, width_px: int, height_px: int) -> tuple[np.ndarray, np.ndarray | None]:
        """(rgb (h, w, 3) uint8, nodata (h, w) bool or None) of the window."""


@dataclass(frozen=True)
class _ArraySource:
    """An in-memory ``Orthomap`` as a ``TileSource``."""

    orthomap: Any

    @property
    def width_px(self) -> int:
        return self.orthomap.width_px

    @property
    def height_px(self) -> int:
        return self.orthomap.height_px

    @property
    def georef(self) -> Georeference:
        return self.orthomap.georef

    @property
    def name(self) -> str:
        return self.orthomap.name

    def read(self, u0_px: int, v0_px: int, width_px: int, height_px: int) -> tuple[np.ndarray, np.ndarray | None]:
        sl = (slice(v0_px, v0_px + height_px), slice(u0_px, u0_px + width_px))
        nd = self.orthomap.nodata
        return np.asarray(self.orthomap.rgb[sl]), None if nd is None else np.asarray(nd[sl])


def gdal_georeference(georef: Georeference) -> tuple[Any, Any] | tuple[None, None]:
    """(rasterio CRS, GDAL affine transform of the outer corner) of a georeference, or (None, None) for a map
    with no CRS (a nominal local tangent plane: the COG then needs ``gsd_m`` when opened, as its source did)."""
    if not isinstance(georef, AffineGeoref):
        return None, None
    from affine import Affine
    from rasterio.crs import CRS

    a, b, c, d, e, f = georef.pixel_to_crs
    return CRS.from_user_input(georef.crs), Affine(a, b, c - 0.5 * (a + b), d, e, f - 0.5 * (d + e))


def write_cog(source: str | os.PathLike | Any, out: str | os.PathLike, *, overwrite: bool = False,
              compress: str = "jpeg", quality: int = 90, gsd_m: float | None = None, crs: str | None = None,
              band_rows: int | None = None, progress: Callable[[int, int], None] | None = None) -> Path:
    """Write ``source`` as a COG at ``out`` (see the module docstring); returns ``out``.

    source: a map file or bundle (``gsd_m``/``crs`` as for ``load_orthomap``), an ``Orthomap``, a map opened by
        window (``RasterMap``) or any ``TileSource``.
    compress: "jpeg" (lossy, ``quality`` 1..100, the size of aerial imagery), "deflate", "lzw", "zstd" or "none".
    band_rows: rows read from the source at a time (default: a band of COG tiles, or 64 MB of the source).
    progress: called with (rows written, total rows) after each band.
    """
    rasterio = require_extra("rasterio", "geo", "Writing a COG (aerial_loc_env.world.maps.write_cog)")
    from rasterio.shutil import copy as gdal_copy

    out = Path(out).expanduser().absolute()
    compress = str(compress).lower()
    if compress not in COMPRESSIONS:
        raise ConfigError(f"write_cog: compress={compress!r}; use one of {', '.join(COMPRESSIONS)}")
    if isinstance(quality, bool) or not isinstance(quality, int) or not 1 <= quality <= 100:
        raise ConfigError(f"write_cog: quality={quality!r}; JPEG quality is an integer in [1, 100]")
    if out.exists() and not overwrite:
        raise MapError(f"{out}: already exists; choose another path or pass overwrite=True (--overwrite)")
    if out.is_dir():
        raise MapError(f"{out}: is a folder; give the COG file to write")
    src = _as_source(source, gsd_m, crs)
    if isinstance(source, (str, os.PathLike)) and Path(source).expanduser().absolute() == out:
        raise MapError(f"{out}: the COG would overwrite its own source; choose another path")
    w, h = int(src.width_px), int(src.height_px)
    rows = band_rows or max(COG_BLOCK_PX, (64 << 20) // max(1, 4 * w) // COG_BLOCK_PX * COG_BLOCK_PX)
    crs_obj, transform = gdal_georeference(src.georef)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmpdir = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        plain = tmpdir / "tiles.tif"
        profile = {"driver": "GTiff", "width": w, "height": h, "count": 3, "dtype": "uint8", "tiled": True,
                   "blockxsize": COG_BLOCK_PX, "blockysize": COG_BLOCK_PX, "compress": "none",
                   "photometric": "rgb", "BIGTIFF": "IF_SAFER"}
        if crs_obj is not None:
            profile.update(crs=crs_obj, transform=transform)
        has_mask = False
        if crs_obj is None:   # a map with no CRS is written without one, as documented: no warning about it
            warnings.filterwarnings("ignore", category=rasterio.errors.NotGeoreferencedWarning)
        with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True, GDAL_CACHEMAX=_GDAL_CACHE_MB), \
                rasterio.open(plain, "w", **profile) as dst:
            for v0 in range(0, h, rows):
                hh = min(rows, h - v0)
                rgb, nodata = src.read(0, v0, w, hh)
                _check_band(src, rgb, nodata, (hh, w))
                window = rasterio.windows.Window(0, v0, w, hh)
                dst.write(np.moveaxis(rgb, -1, 0), window=window)
                if nodata is not None and nodata.any() or has_mask:
                    if not has_mask and v0 > 0:   # the rows before had no no-data: mark them valid
                        dst.write_mask(np.full((v0, w), 255, np.uint8), window=rasterio.windows.Window(0, 0, w, v0))
                    has_mask = True
                    valid = np.full((hh, w), 255, np.uint8) if nodata is None else np.where(nodata, 0, 255)
                    dst.write_mask(valid.astype(np.uint8), window=window)
                if progress is not None:
                    progress(v0 + hh, h)
            dst.update_tags(AERIAL_LOC_SOURCE=str(getattr(src, "source", None) or src.name)[:1000])
        options = {"COMPRESS": compress.upper(), "BLOCKSIZE": COG_BLOCK_PX, "OVERVIEW_RESAMPLING": "AVERAGE",
                   "BIGTIFF": "IF_SAFER", "NUM_THREADS": "ALL_CPUS"}
        if compress == "jpeg":
            options["QUALITY"] = quality
        staged = tmpdir / "cog.tif"
        with rasterio.Env(GDAL_TIFF_INTERNAL_MASK=True, GDAL_CACHEMAX=_GDAL_CACHE_MB):
            gdal_copy(plain, staged, driver="COG", **options)
        plain.unlink()
        if out.exists() and not overwrite:   # written meanwhile by another process
            raise MapError(f"{out}: appeared while the COG was written; choose another path or pass overwrite=True")
        os.replace(staged, out)
    except rasterio.errors.RasterioError as exc:
        raise MapError(f"{out}: GDAL could not write the COG: {exc}") from exc
    finally:
        import shutil

        shutil.rmtree(tmpdir, ignore_errors=True)
    return out


def _as_source(source: Any, gsd_m: float | None, crs: str | None) -> TileSource:
    from aerial_loc_env.world.maps.orthomap import Orthomap

    if isinstance(source, (str, os.PathLike)):
        from aerial_loc_env.world.maps.io import open_map

        kwargs: dict[str, Any] = {}
        if gsd_m is not None:
            kwargs["gsd_m"] = gsd_m
        if crs is not None:
            kwargs["crs"] = crs
        source = open_map(source, **kwargs)
    elif gsd_m is not None or crs is not None:
        raise ConfigError("write_cog: gsd_m and crs are for a source given as a file; a map carries its own")
    if isinstance(source, Orthomap):
        return _ArraySource(source)
    if not all(hasattr(source, a) for a in ("width_px", "height_px", "georef", "read")):
        raise ConfigError(f"write_cog: source must be a map file, an Orthomap or a TileSource, got "
                          f"{type(source).__name__}")
    return source


def _check_band(src: TileSource, rgb: np.ndarray, nodata: np.ndarray | None, shape: tuple[int, int]) -> None:
    if rgb.shape != shape + (3,) or rgb.dtype != np.uint8:
        raise MapError(f"write_cog: source '{src.name}' gave a window of {rgb.dtype} {rgb.shape}; expected uint8 "
                       f"{shape + (3,)}")
    if nodata is not None and (nodata.shape != shape or nodata.dtype != np.bool_):
        raise MapError(f"write_cog: source '{src.name}' gave a no-data window of {nodata.dtype} {nodata.shape}; "
                       f"expected bool {shape}")


def main(argv: list[str] | None = None) -> int:
    """``aerial-loc cog IN OUT``: write IN (any map file the loader accepts, or a bundle) as a COG at OUT."""
    import argparse
    import sys
    import time

    ap = argparse.ArgumentParser(prog="aerial-loc cog", description=(
        "Write a map as a Cloud-Optimized GeoTIFF (tiled, with overviews and its no-data as a mask), which "
        "gym.make(..., path=OUT) opens by window: city-scale maps at the memory of one episode's window."))
    ap.add_argument("input", help="map file (GeoTIFF, PNG/JPEG/TIFF with a world file) or bundle folder")
    ap.add_argument("output", help="the COG to write (.tif)")
    ap.add_argument("--overwrite", action="store_true", help="replace OUTPUT if it exists")
    ap.add_argument("--compress", default="jpeg", choices=COMPRESSIONS, help="tile compression (default jpeg)")
    ap.add_argument("--quality", type=int, default=90, help="JPEG quality 1..100 (default 90)")
    ap.add_argument("--gsd-m", type=float, default=None, help="ground metres per pixel, for inputs without a "
                    "georeference")
    ap.add_argument("--crs", default=None, help="the CRS of a world file or of a GeoTIFF without an EPSG code")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()

    def progress(done: int, total: int) -> None:
        print(f"\r  {done}/{total} rows", end="", file=sys.stderr, flush=True)

    out = write_cog(args.input, args.output, overwrite=args.overwrite, compress=args.compress,
                    quality=args.quality, gsd_m=args.gsd_m, crs=args.crs, progress=progress)
    print(file=sys.stderr)
    from aerial_loc_env.world.maps.raster import tiff_layout

    layout = tiff_layout(out)
    assert layout is not None
    print(f"wrote {out}: {layout.width_px} x {layout.height_px} px, {layout.n_overviews} overview(s), "
          f"{'with' if layout.has_mask else 'no'} no-data mask, {out.stat().st_size / 1e6:.1f} MB, in "
          f"{time.perf_counter() - t0:.1f} s")
    return 0
