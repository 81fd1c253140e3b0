"""WGS84 georeferences: round trips, distances against an independent geodesic, known projection values."""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable

import numpy as np
import pytest

from aerial_loc_env.errors import MapError, MissingExtraError
from aerial_loc_env.world.maps import geo
from aerial_loc_env.world.maps.geo import (
    WGS84_A_M,
    WGS84_B_M,
    WGS84_E2,
    WGS84_F,
    AffineGeoref,
    Georeference,
    LocalTangentGeoref,
    UTMProjection,
    WebMercatorGeoref,
    WorldMercatorGeoref,
    distance_m,
    east_north_m,
    georeference_from_dict,
    mercator_scale_factor,
    offset_latlon,
)


def all_georefs() -> list[Georeference]:
    """One georeference of each natively supported kind, with ~0.1 m pixels near real places."""
    return [
        LocalTangentGeoref.centered(39.17, -0.414, 4000, 3000, 0.1, 0.12),
        LocalTangentGeoref(-33.9, 151.2, 0.25, 0.25, 100.0, -50.0),
        WorldMercatorGeoref.north_up("EPSG:3395", -46189.54, 4719172.21, 0.1, 0.1),
        WebMercatorGeoref.north_up("EPSG:3857", 13467532.0, 1643000.0, 0.1, 0.1),
        AffineGeoref.north_up("EPSG:4326", 120.98, 14.60, 1e-6, 1e-6),
        AffineGeoref.north_up("EPSG:32633", 400000.0, 5500000.0, 0.1, 0.1),
        AffineGeoref.north_up("EPSG:32756", 330000.0, 6250000.0, 0.2, 0.2),
    ]


GEOREF_IDS = ["tangent_valencia", "tangent_sydney", "3395", "3857", "4326", "utm33n", "utm56s"]


def test_wgs84_constants_are_consistent():
    assert WGS84_B_M == pytest.approx(6356752.314245, abs=1e-6)     # defining a, 1/f -> b
    assert WGS84_E2 == pytest.approx(1 - (WGS84_B_M / WGS84_A_M) ** 2, rel=1e-12)
    assert 1 / WGS84_F == pytest.approx(298.257223563)


@pytest.mark.parametrize("g", all_georefs(), ids=GEOREF_IDS)
def test_pixel_latlon_round_trip(g: Georeference):
    rng = np.random.default_rng(1)
    u, v = rng.uniform(-10, 4000, 500), rng.uniform(-10, 3000, 500)
    lat, lon = g.pixel_to_latlon(u, v)
    u2, v2 = g.latlon_to_pixel(lat, lon)
    gx, gy = g.ground_gsd_m(u, v)
    assert np.max(np.abs(u2 - u) * gx) < 1e-4 and np.max(np.abs(v2 - v) * gy) < 1e-4   # sub-mm (0.1 mm)
    lat3, lon3 = g.pixel_to_latlon(u2, v2)
    assert np.max(np.abs(lat3 - lat)) < 1e-9 and np.max(np.abs(lon3 - lon)) < 1e-9


@pytest.mark.parametrize("g", all_georefs(), ids=GEOREF_IDS)
def test_north_up_orientation(g: Georeference):
    lat0, lon0 = g.pixel_to_latlon(100.0, 100.0)
    lat_r, lon_r = g.pixel_to_latlon(101.0, 100.0)   # one column right -> east
    lat_d, lon_d = g.pixel_to_latlon(100.0, 101.0)   # one row down -> south
    # UTM grid north is off true north by the meridian convergence (a few degrees at most)
    assert lon_r > lon0 and abs(lat_r - lat0) < 0.06 * abs(lon_r - lon0)
    assert lat_d < lat0


@pytest.mark.parametrize("g", all_georefs(), ids=GEOREF_IDS)
def test_to_dict_round_trip(g: Georeference):
    d = json.loads(json.dumps(g.to_dict()))
    g2 = georeference_from_dict(d)
    assert type(g2) is type(g) and g2 == g
    u, v = np.array([0.0, 123.4]), np.array([0.0, 56.7])
    np.testing.assert_array_equal(np.stack(g2.pixel_to_latlon(u, v)), np.stack(g.pixel_to_latlon(u, v)))


@pytest.mark.parametrize("g", all_georefs(), ids=GEOREF_IDS)
def test_shifted_is_a_crop(g: Georeference):
    s = g.shifted(37.0, -12.0)
    np.testing.assert_allclose(np.stack(s.pixel_to_latlon(5.0, 6.0)), np.stack(g.pixel_to_latlon(42.0, -6.0)),
                               rtol=0, atol=1e-11)


@pytest.mark.parametrize("g", all_georefs(), ids=GEOREF_IDS)
def test_ground_gsd_matches_geodesic(g: Georeference, vincenty_m: Callable[..., float]):
    """ground_gsd_m (closed form for the projections) agrees with the Vincenty length of a 100-pixel step."""
    u, v = 700.0, 400.0
    gx, gy = g.ground_gsd_m(u, v)
    lat_a, lon_a = g.pixel_to_latlon(u - 50, v)
    lat_b, lon_b = g.pixel_to_latlon(u + 50, v)
    assert float(gx) == pytest.approx(vincenty_m(lat_a, lon_a, lat_b, lon_b) / 100, rel=1e-6)
    lat_a, lon_a = g.pixel_to_latlon(u, v - 50)
    lat_b, lon_b = g.pixel_to_latlon(u, v + 50)
    assert float(gy) == pytest.approx(vincenty_m(lat_a, lon_a, lat_b, lon_b) / 100, rel=1e-6)


@pytest.mark.parametrize("lat0", [0.0, 14.6, 39.17, -62.0])
def test_local_tangent_distances_match_vincenty_over_km(lat0: float, vincenty_m: Callable[..., float]):
    g = LocalTangentGeoref(lat0, 25.0, 0.5, 0.5, 0.0, 0.0)
    rng = np.random.default_rng(abs(int(lat0 * 10)) + 100)
    u, v = rng.uniform(-2000, 2000, (40, 2)), rng.uniform(-2000, 2000, (40, 2))  # points within ~1.4 km
    lat, lon = g.pixel_to_latlon(u, v)
    plane = np.hypot((u[:, 1] - u[:, 0]) * 0.5, (v[:, 1] - v[:, 0]) * 0.5)
    geod = np.array([vincenty_m(lat[i, 0], lon[i, 0], lat[i, 1], lon[i, 1]) for i in range(len(u))])
    # Orthographic projection shortens a distance r from the origin by ~ r^2 / (2 R^2) ~ 3e-8 at 1.4 km.
    assert np.max(np.abs(plane / geod - 1)) < 1e-6


def test_local_tangent_origin_and_axes():
    g = LocalTangentGeoref(45.0, 7.0, 1.0, 2.0, 10.0, 20.0)
    lat, lon = g.pixel_to_latlon(10.0, 20.0)
    assert float(lat) == pytest.approx(45.0, abs=1e-12) and float(lon) == pytest.approx(7.0, abs=1e-12)
    # 100 px north (v - 100, 200 m): the meridional arc is M * dphi
    m, n = geo.radii_of_curvature_m(45.0)
    lat_n, lon_n = g.pixel_to_latlon(10.0, -80.0)
    assert math.radians(float(lat_n) - 45.0) * m == pytest.approx(200.0, rel=1e-6)
    assert float(lon_n) == pytest.approx(7.0, abs=1e-12)


def test_local_tangent_rejects_bad_fields():
    assert LocalTangentGeoref(np.float32(45.0), np.int64(7), 1.0, 1.0).origin_lat_deg == 45.0   # numpy scalars ok
    with pytest.raises(MapError, match="origin_lat_deg"):
        LocalTangentGeoref(95.0, 0.0, 1.0, 1.0)
    with pytest.raises(MapError, match="gsd_x_m"):
        LocalTangentGeoref(10.0, 0.0, 0.0, 1.0)
    with pytest.raises(MapError, match="finite"):
        LocalTangentGeoref(10.0, float("nan"), 1.0, 1.0)


def test_world_mercator_known_values():
    p = geo.WorldMercatorProjection()
    x, y = p.forward(45.0, 0.0)
    assert float(y) == pytest.approx(5591295.9186, abs=1e-3)   # EPSG:3395 northing of 45 deg N (PROJ)
    # The classical closed form: y = a ln[tan(pi/4 + phi/2) ((1 - e sin phi) / (1 + e sin phi))^(e/2)]
    e = math.sqrt(WGS84_E2)
    for lat in (-70.0, -10.0, 14.596, 39.17, 60.0, 84.0):
        phi = math.radians(lat)
        y_ref = WGS84_A_M * math.log(math.tan(math.pi / 4 + phi / 2)
                                     * ((1 - e * math.sin(phi)) / (1 + e * math.sin(phi))) ** (e / 2))
        x, y = p.forward(lat, -0.414)
        assert float(y) == pytest.approx(y_ref, abs=1e-6)
        assert float(x) == pytest.approx(WGS84_A_M * math.radians(-0.414), abs=1e-9)
        lat2, _ = p.inverse(x, y)
        assert float(lat2) == pytest.approx(lat, abs=1e-12)


def test_web_mercator_known_values():
    p = geo.WebMercatorProjection()
    x, y = p.forward(45.0, 90.0)
    assert float(y) == pytest.approx(WGS84_A_M * math.log(math.tan(math.radians(67.5))), abs=1e-6)
    assert float(x) == pytest.approx(WGS84_A_M * math.pi / 2, abs=1e-6)
    # max latitude of the web map square: y = pi a
    lat, _ = p.inverse(0.0, math.pi * WGS84_A_M)
    assert float(lat) == pytest.approx(85.0511287798, abs=1e-9)


def test_mercator_scale_factor_and_ground_gsd():
    lat = np.array([0.0, 14.596, 39.17, 60.0])
    k = mercator_scale_factor(lat)
    np.testing.assert_allclose(k, 1 / np.cos(np.radians(lat)), rtol=5e-3)      # sphere ~ ellipsoid
    assert k[0] == 1.0
    g = WorldMercatorGeoref.north_up("EPSG:3395", -46189.54, 4719172.21, 0.1, 0.1)
    la, _ = g.pixel_to_latlon(10.0, 10.0)
    gx, gy = g.ground_gsd_m(10.0, 10.0)
    assert float(gx) == pytest.approx(0.1 / float(mercator_scale_factor(la)), rel=1e-12)
    # the closed form agrees with the generic finite-difference version of the base class
    gx_n, gy_n = Georeference.ground_gsd_m(g, 10.0, 10.0)
    assert float(gx_n) == pytest.approx(float(gx), rel=1e-7) and float(gy_n) == pytest.approx(float(gy), rel=1e-7)
    # Web Mercator is not conformal on the ellipsoid: x and y ground scales differ by N/M
    w = WebMercatorGeoref.north_up("EPSG:3857", -46189.54, 4743000.0, 0.1, 0.1)
    wx, wy = w.ground_gsd_m(0.0, 0.0)
    la, _ = w.pixel_to_latlon(0.0, 0.0)
    m, n = geo.radii_of_curvature_m(la)
    assert float(wx / wy) == pytest.approx(float(n / m), rel=1e-12)


def test_utm_central_meridian_and_scale():
    p = UTMProjection(31, south=False)
    x, y = p.forward(0.0, 3.0)
    assert float(x) == pytest.approx(500000.0, abs=1e-6) and float(y) == pytest.approx(0.0, abs=1e-6)
    # on the central meridian the point scale is k0 = 0.9996
    g = AffineGeoref.north_up("EPSG:32631", 499950.0, 5000050.0, 1.0, 1.0)
    gx, gy = g.ground_gsd_m(50.0, 50.0)
    assert float(gx) == pytest.approx(1 / 0.9996, rel=1e-7) and float(gy) == pytest.approx(1 / 0.9996, rel=1e-7)
    # southern zones have a false northing of 10 000 km
    _, ys = UTMProjection(31, south=True).forward(-1e-9, 3.0)
    assert float(ys) == pytest.approx(10_000_000.0, abs=1e-3)


def test_utm_against_pyproj():
    pyproj = pytest.importorskip("pyproj")
    rng = np.random.default_rng(7)
    lat, lon = rng.uniform(-79, 83, 2000), rng.uniform(-3, 3, 2000) + 15.0
    for code in (32633, 32733):
        t = pyproj.Transformer.from_crs("EPSG:4326", f"EPSG:{code}", always_xy=True)
        xr, yr = t.transform(lon, lat)
        x, y = geo.projection_for(code).forward(lat, lon)
        assert np.max(np.abs(x - xr)) < 1e-5 and np.max(np.abs(y - yr)) < 1e-5   # 10 um


def test_affine_corner_and_centre_conventions():
    g = AffineGeoref.north_up("EPSG:3395", 1000.0, 2000.0, 0.5, 0.25)
    x, y = g.pixel_to_xy(-0.5, -0.5)               # outer corner of pixel (0, 0)
    assert (float(x), float(y)) == (1000.0, 2000.0)
    x, y = g.pixel_to_xy(0.0, 0.0)                 # its centre
    assert (float(x), float(y)) == (1000.25, 1999.875)
    assert g.pixel_to_crs == (0.5, 0.0, 1000.25, 0.0, -0.25, 1999.875)   # the world-file numbers
    assert type(georeference_from_dict(g.to_dict())) is AffineGeoref   # built generic, stays generic
    assert g.is_north_up() and not AffineGeoref((0.5, 0.01, 0, 0, -0.5, 0), "EPSG:3395").is_north_up()


def test_bad_affine_and_dicts():
    with pytest.raises(MapError, match="singular"):
        AffineGeoref((0.0, 0.0, 1.0, 0.0, 0.0, 1.0), "EPSG:3395")
    with pytest.raises(MapError, match="6 finite"):
        AffineGeoref((1.0, 0.0, 1.0), "EPSG:3395")
    with pytest.raises(MapError, match="EPSG:3395"):
        WorldMercatorGeoref((1.0, 0.0, 0.0, 0.0, -1.0, 0.0), "EPSG:3857")
    with pytest.raises(MapError, match="unknown type"):
        georeference_from_dict({"type": "nope"})
    with pytest.raises(MapError, match="bad fields"):
        georeference_from_dict({"type": "local_tangent", "origin_lat_deg": 1.0})
    with pytest.raises(MapError, match="latitude"):
        geo.WorldMercatorProjection().forward(90.0, 0.0)


def test_other_crs_through_pyproj():
    pytest.importorskip("pyproj")
    # ETRS89-LAEA Europe: false origin (4321000, 3210000) at 52 N 10 E, no datum shift from WGS84 in PROJ
    g = AffineGeoref.north_up("EPSG:3035", 4321000.0, 3210000.0, 0.1, 0.1)
    u, v = np.array([-0.5, 500.0]), np.array([-0.5, 800.0])
    lat, lon = g.pixel_to_latlon(u, v)
    assert float(lat[0]) == pytest.approx(52.0, abs=1e-9) and float(lon[0]) == pytest.approx(10.0, abs=1e-9)
    u2, v2 = g.latlon_to_pixel(lat, lon)
    # PROJ's LAEA inverse uses a truncated authalic-latitude series: ~0.3 mm, so 1 mm here
    np.testing.assert_allclose(np.stack([u2, v2]), np.stack([u, v]), atol=1e-2)
    gx, gy = g.ground_gsd_m(0.0, 0.0)     # equal-area, at its centre: scale 1 both ways
    assert float(gx) == pytest.approx(0.1, rel=1e-6) and float(gy) == pytest.approx(0.1, rel=1e-6)


def test_missing_pyproj_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "pyproj", None)     # makes `import pyproj` raise ImportError
    with pytest.raises(MissingExtraError, match=r"aerial-loc-env\[geo\]"):
        AffineGeoref.north_up("EPSG:2056", 2600000.0, 1200000.0, 0.1, 0.1)


def test_fixed_crs_classes_from_gdal():
    gt = (-46189.54, 0.1, 0.0, 4719172.21, 0.0, -0.1)
    g = WorldMercatorGeoref.from_gdal(gt)
    assert isinstance(g, WorldMercatorGeoref) and g.crs == "EPSG:3395"
    assert g.pixel_to_crs == AffineGeoref.from_gdal(gt, 3395).pixel_to_crs
    assert WebMercatorGeoref.from_gdal(gt).crs == "EPSG:3857"
    with pytest.raises(MapError, match="WebMercatorGeoref: crs must be EPSG:3857"):
        WebMercatorGeoref.from_gdal(gt, "EPSG:3395")


@pytest.mark.parametrize("lat0", [0.0, -35.36, 47.4, 70.0])
def test_offsets_and_distances_match_vincenty(lat0: float, vincenty_m: Callable[..., float]):
    """offset_latlon puts a point the given ground metres east and north (its distance and bearing from the start
    are the geodesic's), east_north_m gives them back, distance_m is the geodesic distance, up to 5 km."""
    rng = np.random.default_rng(int(abs(lat0) * 100) + 7)
    east, north = rng.uniform(-3500, 3500, 30), rng.uniform(-3500, 3500, 30)
    lat, lon = offset_latlon(lat0, 149.16, east, north)
    geod = np.array([vincenty_m(lat0, 149.16, a, b) for a, b in zip(lat, lon, strict=True)])
    # the plane shortens a ground distance r by about r^3 / (24 R^2): 1e-7 relative at 5 km
    assert np.max(np.abs(np.hypot(east, north) / geod - 1)) < 2e-7
    assert np.max(np.abs(distance_m(lat0, 149.16, lat, lon) / geod - 1)) < 2e-7
    e2, n2 = east_north_m(lat0, 149.16, lat, lon)
    assert np.max(np.abs(e2 - east)) < 1e-6 and np.max(np.abs(n2 - north)) < 1e-6
    # the plane's north axis is the meridian's tangent: due north stays on the start's meridian
    lat_n, lon_n = offset_latlon(lat0, 149.16, 0.0, 1000.0)
    assert float(lon_n) == pytest.approx(149.16, abs=1e-12) and float(lat_n) > lat0


def test_offsets_are_the_local_tangent_georeference():
    """One convention: a synthetic map's LocalTangentGeoref and these functions agree to the last bit at its
    origin's metres (pixel size 1 m, origin pixel 0)."""
    g = LocalTangentGeoref(-35.363261, 149.165230, 1.0, 1.0)
    east, north = np.array([0.0, 80.0, -150.0, 2500.0]), np.array([0.0, 0.0, 40.0, -1800.0])
    lat, lon = offset_latlon(-35.363261, 149.165230, east, north)
    lat_g, lon_g = g.pixel_to_latlon(east, -north)
    assert np.array_equal(lat, lat_g) and np.array_equal(lon, lon_g)
    assert (float(lat[0]), float(lon[0])) == pytest.approx((-35.363261, 149.165230), abs=1e-12)
    u, v = g.latlon_to_pixel(lat, lon)
    e2, n2 = east_north_m(-35.363261, 149.165230, lat, lon)
    assert np.allclose(e2, u, rtol=0, atol=1e-9) and np.allclose(n2, -v, rtol=0, atol=1e-9)


def test_east_north_takes_one_origin_per_point(vincenty_m: Callable[..., float]):
    """Vectorized over origins too (an EKF sample against the truth at its own time): each pair on its own."""
    lat0, lon0 = np.array([-35.0, 10.0, 60.0]), np.array([149.0, 0.0, -20.0])
    lat, lon = offset_latlon(-35.0, 149.0, 30.0, 40.0)
    lat1, lon1 = offset_latlon(10.0, 0.0, -5.0, 0.0)
    lat2, lon2 = offset_latlon(60.0, -20.0, 0.0, 700.0)
    d = distance_m(lat0, lon0, np.array([lat, lat1, lat2]), np.array([lon, lon1, lon2]))
    assert d == pytest.approx([50.0, 5.0, 700.0], abs=1e-6)
    assert float(d[2]) == pytest.approx(vincenty_m(60.0, -20.0, float(lat2), float(lon2)), abs=1e-4)


def test_offsets_refuse_the_poles():
    with pytest.raises(MapError, match="latitude"):
        east_north_m(90.0, 0.0, 89.0, 0.0)
    with pytest.raises(MapError, match="origin_lat_deg"):
        offset_latlon(89.5, 0.0, 10.0, 10.0)
