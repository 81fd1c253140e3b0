"""A georeference checked against its CRS's area of use (world/maps/geo.py AreaOfUse, world/maps/io.py
check_location): a wrong CRS guess for a world file's numbers is refused, not loaded at the wrong place."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import tifffile

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps.geo import AreaOfUse, projection_for, regional_crs_covering
from aerial_loc_env.world.maps.io import load_orthomap

pyproj = pytest.importorskip("pyproj", reason="the area-of-use checks of non-native CRSs need pyproj (extra 'geo')")

EUGENE = (44.05, -123.09)          # Eugene, Oregon


def _world_file_png(folder, x: float, y: float, pixel: float, name: str = "ortho.png"):
    png = folder / name
    cv2.imwrite(str(png), np.random.default_rng(0).integers(0, 255, (64, 64, 3), dtype=np.uint8))
    png.with_suffix(".pgw").write_text(f"{pixel}\n0\n0\n{-pixel}\n{x}\n{y}\n")
    return png


def _in(crs: str, lat: float, lon: float) -> tuple[float, float]:
    x, y = pyproj.Transformer.from_crs("EPSG:4326", crs, always_xy=True).transform(lon, lat)
    return float(x), float(y)


def test_a_state_plane_world_file_read_as_utm_is_refused_not_put_in_the_pacific(tmp_path):
    """The reported case: a 1 ft orthophoto of an Oregon city in EPSG:2994 (Oregon GIC Lambert, feet), its world
    file without a .prj. The hint no longer suggests a UTM zone; EPSG:32610 (whose area of use, 0-84 N, contains
    the resulting 7-13 N) is refused as open ocean; the right CRS loads it in Oregon at 0.3 m/px."""
    x, y = _in("EPSG:2994", *EUGENE)
    png = _world_file_png(tmp_path, x, y, 1.0)
    with pytest.raises(MapError, match=r"has no CRS .*projected coordinates, in metres or feet: UTM zones, national "
                                       r"grids and US State Plane zones \(in feet\)") as no_crs:
        load_orthomap(png)
    assert "326xx" not in str(no_crs.value) and "fit a UTM zone" not in str(no_crs.value)
    with pytest.raises(MapError, match=r"ortho\.png: world file ortho\.pgw, EPSG:32610: the georeference puts the "
                                       r"map's centre at \d+\.\d+ deg, -12\d\.\d+ deg, in open ocean: no national or "
                                       r"regional CRS .* a US State Plane zone in feet"):
        load_orthomap(png, crs="EPSG:32610")
    om = load_orthomap(png, crs="EPSG:2994")
    lat, lon = om.world_to_latlon(om.width_m / 2, om.height_m / 2)
    assert float(lat) == pytest.approx(EUGENE[0], abs=0.01) and float(lon) == pytest.approx(EUGENE[1], abs=0.01)
    assert om.gsd_x_m == pytest.approx(0.3048, rel=0.01)


@pytest.mark.parametrize("crs, x, y, said", [
    ("EPSG:32633", 1_300_000.0, 5_000_000.0, r"\d\.\d deg outside the area of use of EPSG:32633 \(UTM zone 33N: "
                                             r"12 deg E to 18 deg E, 0 deg N to 84 deg N\)"),
    ("EPSG:32733", 500_000.0, 10_600_000.0, r"5\.\d deg outside the area of use of EPSG:32733 \(UTM zone 33S: 12 deg "
                                            r"E to 18 deg E, 80 deg S to 0 deg N\)"),
])
def test_a_utm_georeference_outside_its_zone_or_hemisphere_is_refused(tmp_path, crs, x, y, said):
    png = _world_file_png(tmp_path, x, y, 0.5)
    (tmp_path / "ortho.prj").write_text(crs)           # named by the file: only the area of use is checked
    with pytest.raises(MapError, match=rf"ortho\.png: world file ortho\.pgw, {crs} from ortho\.prj: the "
                                       rf"georeference puts the map's centre at .*{said}\. The numbers were most "
                                       r"likely written in another CRS"):
        load_orthomap(png)


def test_a_pyproj_crs_is_checked_against_its_epsg_area_of_use(tmp_path):
    x, y = _in("EPSG:2994", 30.0, -100.0)               # Texas, in Oregon's Lambert grid
    png = _world_file_png(tmp_path, x, y, 1.0)
    with pytest.raises(MapError, match=r"outside the area of use of EPSG:2994 \(United States \(USA\) - Oregon"):
        load_orthomap(png, crs="EPSG:2994")


def test_a_place_just_beyond_its_zone_and_a_geotiff_over_water_still_load(tmp_path):
    # 2 deg east of UTM 33's band (a map kept in its neighbour's zone): inside the margin
    x, y = _in("EPSG:32633", 45.0, 20.0)
    assert load_orthomap(_world_file_png(tmp_path, x, y, 0.5), crs="EPSG:32633").width_px == 64
    # a GeoTIFF naming its own CRS is trusted over open water (only its area of use is checked)
    x, y = _in("EPSG:32610", 7.7, -123.0)
    tif = tmp_path / "sea.tif"
    tifffile.imwrite(tif, np.full((32, 32, 3), 90, np.uint8), photometric="rgb", extratags=[
        (33550, "d", 3, (0.5, 0.5, 0.0)), (33922, "d", 6, (0.0, 0.0, 0.0, x, y, 0.0)),
        (34735, "H", 16, (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32610))])
    om = load_orthomap(tif)
    assert float(om.world_to_latlon(8.0, 8.0)[0]) == pytest.approx(7.7, abs=0.01)


def test_area_of_use_boxes():
    utm = projection_for("EPSG:32610").area_of_use()
    assert (utm.west, utm.south, utm.east, utm.north) == (-126.0, 0.0, -120.0, 84.0)
    assert utm.distance_deg(45.0, -123.0) == 0.0 and utm.distance_deg(45.0, -117.0) == pytest.approx(3.0)
    assert utm.distance_deg(-2.0, -123.0) == pytest.approx(2.0)
    across = AreaOfUse(170.0, -50.0, -170.0, -30.0)     # crosses the antimeridian
    assert across.distance_deg(-40.0, 179.0) == 0.0 and across.distance_deg(-40.0, -175.0) == 0.0
    assert across.distance_deg(-40.0, 160.0) == pytest.approx(10.0)
    assert projection_for("EPSG:3395").area_of_use().distance_deg(70.0, 10.0) == 0.0
    assert regional_crs_covering(*EUGENE) and regional_crs_covering(7.7, -123.4) == []
