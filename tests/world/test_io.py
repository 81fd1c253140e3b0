"""load_orthomap: GeoTIFF tags, world files, conversions, no-data, bad inputs, and the two real tiles."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from shared_helpers import REPO_ROOT, crop_png

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps.geo import LocalTangentGeoref, WorldMercatorGeoref, mercator_scale_factor
from aerial_loc_env.world.maps.io import border_connected, load_orthomap

H, W = 40, 50
# ModelPixelScale / ModelTiepoint of a valencia-like EPSG:3395 tile
SX, SY, X0, Y0 = 0.1, 0.1, -46189.5, 4719172.2


def geokeys(epsg: int, *, point: bool = False, geographic: bool = False) -> tuple[int, ...]:
    """A minimal GeoKey directory: model type, raster type, projected/geographic EPSG code."""
    keys = [(1024, 0, 1, 2 if geographic else 1), (1025, 0, 1, 2 if point else 1),
            (2048 if geographic else 3072, 0, 1, epsg)]
    return tuple([1, 1, 0, len(keys)] + [x for k in keys for x in k])


def write_geotiff(path: Path, img: np.ndarray, *, epsg: int = 3395, point: bool = False,
                  transformation: bool = False, nodata: str | None = None, geographic: bool = False,
                  scale=(SX, SY), tie=(X0, Y0)) -> Path:
    keys = geokeys(epsg, point=point, geographic=geographic)
    tags = [(34735, "H", len(keys), keys, True)]
    if transformation:
        m = (scale[0], 0.0, 0.0, tie[0], 0.0, -scale[1], 0.0, tie[1], 0, 0, 0, 0, 0, 0, 0, 1)
        tags.append((34264, "d", 16, m, True))
    else:
        tags += [(33550, "d", 3, (scale[0], scale[1], 0.0), True),
                 (33922, "d", 6, (0.0, 0.0, 0.0, tie[0], tie[1], 0.0), True)]
    if nodata is not None:
        tags.append((42113, "s", 0, nodata, True))
    tifffile.imwrite(path, img, extratags=tags, photometric="rgb" if img.ndim == 3 and img.shape[2] >= 3
                     else "minisblack")
    return path


def texture(seed: int = 0, shape=(H, W, 3), lo: int = 30) -> np.ndarray:
    return np.random.default_rng(seed).integers(lo, 256, shape, dtype=np.uint8)


def write_png(path: Path, rgb: np.ndarray) -> Path:
    img = rgb[..., ::-1] if rgb.ndim == 3 and rgb.shape[2] in (3, 4) else rgb
    if rgb.ndim == 3 and rgb.shape[2] == 4:
        img = rgb[..., [2, 1, 0, 3]]
    assert cv2.imwrite(str(path), np.ascontiguousarray(img))
    return path


def test_geotiff_pixel_is_area(tmp_path):
    img = texture()
    om = load_orthomap(write_geotiff(tmp_path / "a.tif", img))
    assert isinstance(om.georef, WorldMercatorGeoref)
    assert np.array_equal(om.rgb, img) and om.nodata is None and om.name == "a"
    x, y = om.georef.pixel_to_xy(-0.5, -0.5)      # the tie point is the outer corner of pixel (0, 0)
    assert (float(x), float(y)) == pytest.approx((X0, Y0), abs=1e-9)
    lat_c, _ = om.georef.pixel_to_latlon((W - 1) / 2, (H - 1) / 2)
    k = float(mercator_scale_factor(lat_c))
    assert om.gsd_x_m == pytest.approx(SX / k, rel=1e-9) and om.gsd_y_m == pytest.approx(SY / k, rel=1e-9)
    assert "PixelIsArea" in om.source and "EPSG:3395" in om.source


def test_geotiff_pixel_is_point_and_model_transformation(tmp_path):
    img = texture()
    area = load_orthomap(write_geotiff(tmp_path / "area.tif", img))
    point = load_orthomap(write_geotiff(tmp_path / "point.tif", img, point=True))
    x, y = point.georef.pixel_to_xy(0.0, 0.0)     # PixelIsPoint: the tie point is the centre of pixel (0, 0)
    assert (float(x), float(y)) == pytest.approx((X0, Y0), abs=1e-9)
    xa, ya = area.georef.pixel_to_xy(0.0, 0.0)
    assert float(xa - x) == pytest.approx(SX / 2) and float(y - ya) == pytest.approx(SY / 2)
    trans = load_orthomap(write_geotiff(tmp_path / "m.tif", img, transformation=True))
    assert trans.georef == area.georef
    trans_pt = load_orthomap(write_geotiff(tmp_path / "mp.tif", img, transformation=True, point=True))
    assert trans_pt.georef == point.georef


def test_geotiff_geographic_and_crs_rules(tmp_path):
    img = texture()
    f = write_geotiff(tmp_path / "g.tif", img, epsg=4326, geographic=True, scale=(1e-6, 1e-6), tie=(-0.42, 39.17))
    om = load_orthomap(f)
    lat, lon = om.georef.pixel_to_latlon(-0.5, -0.5)
    assert (float(lat), float(lon)) == pytest.approx((39.17, -0.42), abs=1e-12)
    m_per_deg_lat = math.pi / 180 * 6335439.327 / (1 - 0.00669438 * math.sin(math.radians(39.17)) ** 2) ** 1.5
    assert om.gsd_y_m == pytest.approx(1e-6 * m_per_deg_lat, rel=1e-3)
    with pytest.raises(MapError, match=r"g\.tif: the GeoTIFF says EPSG:4326 but crs='EPSG:3395'"):
        load_orthomap(f, crs="EPSG:3395")
    nokey = write_geotiff(tmp_path / "nokey.tif", img, epsg=32767)
    with pytest.raises(MapError, match=r"nokey\.tif: the GeoTIFF has no EPSG code"):
        load_orthomap(nokey)
    assert load_orthomap(nokey, crs="EPSG:3395").georef == load_orthomap(write_geotiff(tmp_path / "x.tif", img)).georef


def test_world_file_png(tmp_path):
    rgb = texture(1)
    png = write_png(tmp_path / "m.png", rgb)
    # world file: A D B E C F with (C, F) the centre of the top-left pixel
    (tmp_path / "m.pgw").write_text(f"{SX}\n0\n0\n{-SY}\n{X0 + SX / 2}\n{Y0 - SY / 2}\n")
    with pytest.raises(MapError, match=r"m\.png: world file m\.pgw has no CRS.*pass crs="):
        load_orthomap(png)
    om = load_orthomap(png, crs="EPSG:3395")
    assert np.array_equal(om.rgb, rgb)
    ref = load_orthomap(write_geotiff(tmp_path / "ref.tif", rgb))
    assert om.georef == ref.georef                       # same place as the PixelIsArea GeoTIFF
    # an explicit world file wins over a sidecar; .wld also found
    (tmp_path / "other.txt").write_text(f"{SX}\n0\n0\n{-SY}\n{X0 + 100}\n{Y0}\n")
    om2 = load_orthomap(png, crs=3395, world_file=tmp_path / "other.txt")
    assert float(om2.georef.pixel_to_xy(0, 0)[0]) == pytest.approx(X0 + 100)
    (tmp_path / "m.pgw").unlink()
    (tmp_path / "m.wld").write_text("0.5 0 0 -0.5 -46000 4746000")     # Valencia (not Null Island: refused)
    assert load_orthomap(png, crs="EPSG:3857").georef.pixel_to_crs == (0.5, 0.0, -46000.0, 0.0, -0.5, 4746000.0)


def test_bad_world_files(tmp_path):
    png = write_png(tmp_path / "m.png", texture())
    (tmp_path / "m.pgw").write_text("0.1 0 0 -0.1 5")
    with pytest.raises(MapError, match=r"m\.pgw: a world file has 6 numbers"):
        load_orthomap(png, crs="EPSG:3395")
    (tmp_path / "m.pgw").write_text("0.1 0.02 0 -0.1 5 6")
    with pytest.raises(MapError, match=r"m\.png: .*rotated"):
        load_orthomap(png, crs="EPSG:3395")
    (tmp_path / "m.pgw").write_text("a b c d e f")
    with pytest.raises(MapError, match=r"m\.pgw"):
        load_orthomap(png, crs="EPSG:3395")
    with pytest.raises(MapError, match=r"does not exist"):
        load_orthomap(png, crs="EPSG:3395", world_file=tmp_path / "none.pgw")


def test_no_georeference_needs_gsd(tmp_path):
    png = write_png(tmp_path / "plain.png", texture())
    with pytest.raises(MapError, match=r"plain\.png: no georeference .* no gsd_m"):
        load_orthomap(png)
    om = load_orthomap(png, gsd_m=(0.2, 0.3), origin_latlon_deg=(14.6, 121.0))
    assert isinstance(om.georef, LocalTangentGeoref) and (om.gsd_x_m, om.gsd_y_m) == (0.2, 0.3)
    lat, lon = om.world_to_latlon(om.width_m / 2, om.height_m / 2)
    assert (float(lat), float(lon)) == pytest.approx((14.6, 121.0), abs=1e-12)
    with pytest.raises(MapError, match="gsd_m must be > 0"):
        load_orthomap(png, gsd_m=-1.0)
    tif = write_geotiff(tmp_path / "g.tif", texture())
    with pytest.raises(MapError, match=r"g\.tif: gsd_m=0\.2 disagrees"):
        load_orthomap(tif, gsd_m=0.2)
    assert load_orthomap(tif, gsd_m=0.0776).gsd_x_m == pytest.approx(0.0776, rel=0.01)


def test_grey_rgba_and_16_bit_conversions(tmp_path):
    grey = texture(2, (H, W))
    om = load_orthomap(write_png(tmp_path / "grey.png", grey), gsd_m=0.1)
    assert om.rgb.shape == (H, W, 3) and all(np.array_equal(om.rgb[..., i], grey) for i in range(3))
    rgba = np.concatenate([texture(3), np.full((H, W, 1), 255, np.uint8)], axis=2)
    rgba[10:20, 5:9, 3] = 0
    om = load_orthomap(write_png(tmp_path / "rgba.png", rgba), gsd_m=0.1)
    assert np.array_equal(om.rgb, rgba[..., :3])
    assert om.nodata is not None and om.nodata.sum() == 40 and om.nodata[10:20, 5:9].all()
    img16 = np.random.default_rng(4).integers(1000, 4001, (H, W, 3), dtype=np.uint16)
    img16[0, 0] = (1000, 1000, 1000)
    img16[1, 1] = (4000, 4000, 4000)
    om = load_orthomap(write_geotiff(tmp_path / "deep.tif", img16))
    expect = np.rint((img16.astype(np.float64) - 1000) * 255 / 3000).astype(np.uint8)
    assert np.abs(om.rgb.astype(int) - expect).max() <= 1
    assert om.rgb[0, 0].tolist() == [0, 0, 0] and om.rgb[1, 1].tolist() == [255, 255, 255]
    assert "scaled linearly from [1000, 4000]" in om.source


@pytest.mark.parametrize(("kind", "expect"), [
    ("float", r"found dtype float32 with 3 channel"),
    ("two", r"found dtype uint8 with 2 channel"),
    ("five", r"found dtype uint8 with 5 channel"),
    ("int16", r"found dtype int16"),
    ("bilevel", r"1-bit"),
])
def test_unsupported_rasters_are_rejected(tmp_path, kind, expect):
    f = tmp_path / f"bad_{kind}.tif"
    data = {"float": np.zeros((H, W, 3), np.float32), "two": np.zeros((H, W, 2), np.uint8),
            "five": np.zeros((H, W, 5), np.uint8), "int16": np.zeros((H, W), np.int16),
            "bilevel": np.zeros((H, W), bool)}[kind]
    tifffile.imwrite(f, data, photometric="minisblack", planarconfig="contig")
    with pytest.raises(MapError, match=rf"bad_{kind}\.tif: .*{expect}") as err:
        load_orthomap(f, gsd_m=0.1)
    assert "supported:" in str(err.value)


def test_missing_and_unreadable_files(tmp_path):
    with pytest.raises(MapError, match=r"nothere\.png: no such map file"):
        load_orthomap(tmp_path / "nothere.png", gsd_m=0.1)
    junk = tmp_path / "junk.jpg"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(MapError, match=r"junk\.jpg: not a readable image"):
        load_orthomap(junk, gsd_m=0.1)
    broken = tmp_path / "broken.tif"
    broken.write_bytes(b"II*\x00" + b"\xff" * 20)
    with pytest.raises(MapError, match=r"broken\.tif: unreadable TIFF"):
        load_orthomap(broken, gsd_m=0.1)


def test_border_connected_black_is_nodata_but_black_roof_is_not(tmp_path):
    img = texture(5)
    yy, xx = np.mgrid[:H, :W]
    wedge = xx + yy < 15                     # top-left black wedge, like the real tiles
    img[wedge] = 0
    img[20:26, 30:36] = 0                    # a black roof in the middle
    img[-1, -1] = (0, 0, 7)                  # nearly black corner pixel: data unless nodata_black_max >= 7
    om = load_orthomap(write_geotiff(tmp_path / "w.tif", img))
    assert np.array_equal(om.nodata, wedge)
    assert om.valid_mask()[20:26, 30:36].all()
    assert load_orthomap(tmp_path / "w.tif", nodata_black_max=7).nodata[-1, -1]
    assert load_orthomap(tmp_path / "w.tif", nodata=None).nodata is None
    np.testing.assert_array_equal(border_connected(np.zeros((3, 3), bool)), np.zeros((3, 3), bool))


def test_gdal_nodata_tag_and_explicit_value(tmp_path):
    img = texture(6)
    img[5:9, 20:30] = 7
    img[0:3, 0:3] = 0                              # black at the border is data when the tag says 7
    om = load_orthomap(write_geotiff(tmp_path / "n.tif", img, nodata="7"))
    assert om.nodata.sum() == 40 and om.nodata[5:9, 20:30].all()
    om = load_orthomap(write_geotiff(tmp_path / "v.tif", img), nodata=7)
    assert om.nodata.sum() == 40
    with pytest.raises(MapError, match="nodata='bogus'"):
        load_orthomap(tmp_path / "v.tif", nodata="bogus")
    img[:] = 0
    with pytest.raises(MapError, match=r"all\.tif: every pixel is no-data"):
        load_orthomap(write_geotiff(tmp_path / "all.tif", img))


def test_dsm_and_class_layers(tmp_path):
    tif = write_geotiff(tmp_path / "m.tif", texture())
    dsm = np.random.default_rng(7).uniform(0, 20, (H, W)).astype(np.float32)
    dsm[3, 4] = np.nan
    tifffile.imwrite(tmp_path / "dsm.tif", dsm)
    classes = np.random.default_rng(8).integers(0, 10, (H, W), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "cls.png"), classes)
    om = load_orthomap(tif, dsm=tmp_path / "dsm.tif", classes=tmp_path / "cls.png")
    assert om.dsm_m.dtype == np.float32 and om.dsm_m[3, 4] == 0.0 and om.nodata[3, 4] and om.nodata.sum() == 1
    good = np.isfinite(dsm)
    assert np.array_equal(om.dsm_m[good], dsm[good]) and np.array_equal(om.classes, classes)
    tifffile.imwrite(tmp_path / "small.tif", dsm[:10])
    with pytest.raises(MapError, match=r"m\.tif: the DSM \(.*small\.tif\) has shape \(10, 50\), the image has"):
        load_orthomap(tif, dsm=tmp_path / "small.tif")
    with pytest.raises(MapError, match=r"m\.tif: the class map .* dtype int64"):
        load_orthomap(tif, classes=classes.astype(np.int64))
    with pytest.raises(MapError, match=r"m\.tif: dsm file .*nope\.tif does not exist"):
        load_orthomap(tif, dsm=tmp_path / "nope.tif")


def test_bundle_directories_load(tmp_path):
    om = load_orthomap(write_geotiff(tmp_path / "m.tif", texture()))
    path = om.save_bundle(tmp_path / "m.alm")
    back = load_orthomap(path)
    assert back.georef == om.georef and np.array_equal(back.rgb, om.rgb) and isinstance(back.rgb, np.memmap)
    with pytest.raises(MapError, match="carries its own"):
        load_orthomap(path, gsd_m=0.1)


@pytest.mark.parametrize(("tile", "gsd_m", "lat", "lon", "nodata"), [
    ("manila_pasig_river.tif", 0.097, 14.596, 120.982, 0.18),
    ("valencia_orchard.tif", 0.078, 39.170, -0.414, 0.25),
])
def test_real_tiles(shared_data, tile, gsd_m, lat, lon, nodata):
    """README figures: ground scale to 2 digits, centre to 3 decimals of a degree, no-data to ~1 %."""
    om = load_orthomap(shared_data / tile)
    assert isinstance(om.georef, WorldMercatorGeoref) and (om.width_px, om.height_px) == (2048, 2048)
    sx, _, _, _, e, _ = om.georef.pixel_to_crs
    c_lat, c_lon = om.world_to_latlon(om.width_m / 2, om.height_m / 2)
    assert float(c_lat) == pytest.approx(lat, abs=6e-4) and float(c_lon) == pytest.approx(lon, abs=6e-4)
    # ground = projected x cos(lat) on the sphere; the ellipsoid differs by < e^2 sin^2(lat) / 2 ~ 0.14 %
    assert om.gsd_x_m == pytest.approx(sx * math.cos(math.radians(float(c_lat))), rel=2e-3)
    assert om.gsd_y_m == pytest.approx(-e * math.cos(math.radians(float(c_lat))), rel=2e-3)
    assert om.gsd_x_m == pytest.approx(gsd_m, abs=6e-4) and om.gsd_y_m == pytest.approx(gsd_m, abs=6e-4)
    assert om.nodata_fraction() == pytest.approx(nodata, abs=0.01)
    assert not om.nodata[1024, 1024] and om.nodata[0].all()        # data in the middle, none along the top
    assert om.contains_world(*om.pixel_to_world(1024, 1024))


def test_planar_grey_tiff_and_jpeg_world_file(tmp_path):
    img = texture(10)
    tifffile.imwrite(tmp_path / "planar.tif", np.moveaxis(img, -1, 0), photometric="rgb", planarconfig="separate")
    assert np.array_equal(load_orthomap(tmp_path / "planar.tif", gsd_m=0.1).rgb, img)
    grey = texture(11, (H, W))
    tifffile.imwrite(tmp_path / "grey.tif", grey, photometric="minisblack")
    assert np.array_equal(load_orthomap(tmp_path / "grey.tif", gsd_m=0.1).rgb[..., 1], grey)
    smooth = cv2.GaussianBlur(img, (0, 0), 3)
    assert cv2.imwrite(str(tmp_path / "photo.jpg"), smooth[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 98])
    (tmp_path / "photo.jgw").write_text(f"{SX}\n0\n0\n{-SY}\n{X0 + SX / 2}\n{Y0 - SY / 2}\n")
    om = load_orthomap(tmp_path / "photo.jpg", crs="EPSG:3395")
    assert np.abs(om.rgb.astype(int) - smooth).mean() < 3            # RGB order kept (JPEG is lossy)
    assert om.georef == load_orthomap(write_geotiff(tmp_path / "ref.tif", img)).georef


US_FT_M = 1200.0 / 3937.0          # one US survey foot in metres


def _tmerc_us_ft_wkt(lat0: float, lon0: float) -> str:
    """A transverse Mercator CRS in US survey feet, as ESRI-style WKT without an EPSG authority."""
    pyproj = pytest.importorskip("pyproj")
    crs = pyproj.CRS.from_proj4(f"+proj=tmerc +lat_0={lat0} +lon_0={lon0} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 "
                                "+units=us-ft +no_defs")
    return crs.to_wkt(pyproj.enums.WktVersion.WKT1_ESRI)


def test_image_over_opencvs_pixel_limit_is_a_map_error(tmp_path):
    png = tmp_path / "big.png"
    cv2.imwrite(str(png), np.full((40, 50, 3), 128, np.uint8))
    code = ("import sys\nfrom aerial_loc_env.world.maps.io import load_orthomap\nfrom aerial_loc_env.errors import "
            "MapError\ntry:\n    load_orthomap(sys.argv[1], gsd_m=1.0)\nexcept MapError as e:\n"
            "    print('MAPERROR', e)\n")
    env = {**os.environ, "OPENCV_IO_MAX_IMAGE_PIXELS": "1000", "PYTHONPATH": str(REPO_ROOT)}
    res = subprocess.run([sys.executable, "-c", code, str(png)], capture_output=True, text=True, env=env,
                         timeout=120)
    assert "Traceback" not in res.stderr, res.stderr[-2000:]
    assert "MAPERROR" in res.stdout and "big.png" in res.stdout and "2000" in res.stdout, res.stdout


@pytest.mark.parametrize("pixel, crs", [(1e9, "EPSG:32633"), (1e-7, "EPSG:32633"), (5.0, "EPSG:4326")])
def test_world_file_pixel_size_absurd_for_its_crs(tmp_path, pixel, crs):
    png = tmp_path / "m.png"
    cv2.imwrite(str(png), np.full((40, 50, 3), 128, np.uint8))
    north = 5_000_000.0 if crs != "EPSG:4326" else 45.0
    east = 500_000.0 if crs != "EPSG:4326" else 10.0
    (tmp_path / "m.pgw").write_text(f"{pixel}\n0\n0\n{-pixel}\n{east}\n{north}\n")
    with pytest.raises(MapError, match=r"m\.pgw.*pixel size"):
        load_orthomap(png, crs=crs)


def test_world_file_in_us_survey_feet_with_a_prj(manila, tmp_path):
    """A world file in US survey feet with its .prj: the map loads at the true ground scale (not 3.28x)."""
    png, lat, lon = crop_png(manila, tmp_path)
    gsd_m = float(manila.gsd_x_m)                    # ~0.097 m on the ground
    px_ft = gsd_m / US_FT_M
    (tmp_path / "crop.prj").write_text(_tmerc_us_ft_wkt(lat, lon))
    # the crop centre is the projection origin: top-left pixel centre at (-255.5, +255.5) pixels
    (tmp_path / "crop.pgw").write_text(f"{px_ft}\n0\n0\n{-px_ft}\n{-255.5 * px_ft}\n{255.5 * px_ft}\n")
    om = load_orthomap(png)
    assert om.gsd_x_m == pytest.approx(gsd_m, rel=1e-3) and om.gsd_y_m == pytest.approx(gsd_m, rel=1e-3)
    assert "crop.prj" in om.source
    c_lat, c_lon = om.world_to_latlon(om.width_m / 2, om.height_m / 2)
    assert math.hypot((float(np.ravel(c_lat)[0]) - lat) * 111_000.0,
                      (float(np.ravel(c_lon)[0]) - lon) * 111_000.0 * math.cos(math.radians(lat))) < 0.5
    # following the old fixed hint (crs='EPSG:3395') now fails, naming the .prj, instead of a 3.25x map
    with pytest.raises(MapError, match=r"crs='EPSG:3395'.*crop\.prj"):
        load_orthomap(png, crs="EPSG:3395")


def test_world_file_crs_from_an_aux_xml(manila, tmp_path):
    png, lat, lon = crop_png(manila, tmp_path)
    t = manila.georef.pixel_to_crs                 # World Mercator, as in the source GeoTIFF
    v0 = u0 = (manila.width_px - 512) // 2 + 200
    c, f = t[0] * u0 + t[2], t[4] * v0 + t[5]
    (tmp_path / "crop.pgw").write_text(f"{t[0]}\n0\n0\n{t[4]}\n{c}\n{f}\n")
    (tmp_path / "crop.png.aux.xml").write_text('<PAMDataset>\n  <SRS dataAxisToSRSAxisMapping="1,2">PROJCS["WGS 84 / '
                                              'World Mercator",AUTHORITY["EPSG","3395"]]</SRS>\n</PAMDataset>\n')
    om = load_orthomap(png)
    assert om.gsd_x_m == pytest.approx(manila.gsd_x_m, rel=1e-3)
    assert om.georef.crs == "EPSG:3395"


def test_world_file_without_crs_suggests_how_to_find_it(tmp_path):
    png = tmp_path / "m.png"
    cv2.imwrite(str(png), np.full((40, 50, 3), 128, np.uint8))
    (tmp_path / "m.pgw").write_text("0.5\n0\n0\n-0.5\n1000000.0\n200000.0\n")
    with pytest.raises(MapError) as err:
        load_orthomap(png)
    msg = str(err.value)
    assert ".prj" in msg and "gdalsrsinfo" in msg and "EPSG:3395" not in msg
