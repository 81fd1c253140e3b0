"""The map-acquisition model (world/maps/acquisition.py): identity when off, lean geometry, georeference bias,
sensor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.world.maps.acquisition import AcquisitionConfig, acquire, acquire_layer, lean_buildings

GSD = 0.25


def _acq(**kw) -> AcquisitionConfig:
    return build_config(AcquisitionConfig, kw, where="test [database]")


def _textured(h: int = 240, w: int = 320, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (h // 8 + 1, w // 8 + 1, 3), dtype=np.uint8)
    import cv2

    img = cv2.resize(base, (w + 8, h + 8), interpolation=cv2.INTER_CUBIC)[:h, :w]
    return np.ascontiguousarray(img)


def _box_scene(h_m: float, size: int = 400, box: tuple[int, int, int, int] = (170, 230, 180, 220)):
    """Grey ground, a red roof (rows r0:r1, cols c0:c1) at height h_m."""
    r0, r1, c0, c1 = box
    rgb = np.full((size, size, 3), 100, np.uint8)
    rgb[r0:r1, c0:c1] = (220, 40, 40)
    dsm = np.zeros((size, size), np.float32)
    dsm[r0:r1, c0:c1] = h_m
    return rgb, dsm


def test_defaults_are_identity_and_return_the_input():
    img = _textured()
    cfg = _acq()
    assert cfg.is_identity
    assert acquire(img, None, GSD, GSD, cfg) is img
    assert acquire_layer(img[..., 0], GSD, GSD, cfg) is not None


def test_bad_values_are_named():
    with pytest.raises(ConfigError, match="jpeg_quality"):
        _acq(jpeg_quality=2)
    with pytest.raises(ConfigError, match="lean_deg"):
        _acq(lean_deg=80.0)
    with pytest.raises(ConfigError, match="gsd_m"):
        _acq(gsd_m=-1.0)
    with pytest.raises(MapError, match="lean_deg"):
        acquire(_textured(), None, GSD, GSD, _acq(lean_deg=10.0))


@pytest.mark.parametrize("east_m,north_m", [(3.0, 0.0), (0.0, -2.5), (1.75, 2.25)])
def test_georef_bias_shifts_the_content_by_the_stated_metres(east_m, north_m):
    import cv2

    img = _textured(256, 256, seed=1)
    out = acquire(img, None, GSD, GSD, _acq(georef_bias_m=(east_m, north_m)))
    a = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float64)
    b = cv2.cvtColor(out, cv2.COLOR_RGB2GRAY).astype(np.float64)
    win = cv2.createHanningWindow((256, 256), cv2.CV_64F)
    (du, dv), _ = cv2.phaseCorrelate(a, b, win)
    # content at world (x, y) appears where the georeference says (x + east, y + north): +east = +u, +north = -v
    assert du * GSD == pytest.approx(east_m, abs=0.05)
    assert -dv * GSD == pytest.approx(north_m, abs=0.05)


def test_georef_bias_carries_the_layers_along():
    classes = np.zeros((100, 100), np.uint8)
    classes[40:60, 40:60] = 4
    out = acquire_layer(classes, GSD, GSD, _acq(georef_bias_m=(2.0, 1.0)))      # 8 px east, 4 px north
    assert out.dtype == np.uint8
    assert np.array_equal(np.argwhere(out == 4).min(axis=0), [36, 48])
    nod = acquire_layer(classes == 4, GSD, GSD, _acq(georef_bias_m=(2.0, 1.0)))
    assert nod.dtype == bool and np.array_equal(nod, out == 4)


@pytest.mark.parametrize("h_m,lean_deg,azimuth_deg", [(10.0, 15.0, 90.0), (20.0, 10.0, 90.0),
                                                      (12.0, 20.0, 180.0), (8.0, 25.0, 45.0),
                                                      (30.0, 12.0, 300.0)])
def test_lean_displaces_a_box_roof_by_h_tan_angle(h_m, lean_deg, azimuth_deg):
    rgb, dsm = _box_scene(h_m)
    out, wall = lean_buildings(rgb, dsm, GSD, GSD, lean_deg, azimuth_deg)
    roof_in = np.argwhere(np.all(rgb == (220, 40, 40), axis=-1)).mean(axis=0)
    roof_out = np.argwhere(np.all(out == (220, 40, 40), axis=-1)).mean(axis=0)
    d_m = h_m * math.tan(math.radians(lean_deg))
    az = math.radians(azimuth_deg)
    expect = np.array([-d_m * math.cos(az), d_m * math.sin(az)]) / GSD       # (rows, cols): north is -row
    # the march moves in whole pixel steps along the lean (half a step off at most) and rounds each offset to a
    # pixel (half a pixel per axis): at most one pixel per axis
    assert roof_out - roof_in == pytest.approx(expect, abs=1.0)
    # the roof keeps its size and the facade facing the sensor shows, a band h tan(angle) deep
    assert np.count_nonzero(np.all(out == (220, 40, 40), axis=-1)) == pytest.approx(40 * 60, rel=0.06)
    assert wall.any()
    n_wall = np.count_nonzero(wall)
    box_side_px = abs(math.sin(az)) * 60 + abs(math.cos(az)) * 40     # the sides the sensor sees, projected
    assert n_wall == pytest.approx(d_m / GSD * box_side_px, rel=0.2)


def test_lean_zero_height_or_angle_is_identity():
    rgb, dsm = _box_scene(0.0)
    out, wall = lean_buildings(rgb, dsm, GSD, GSD, 20.0, 90.0)
    assert np.array_equal(out, rgb) and not wall.any()


def test_coarse_sensor_removes_fine_detail_and_keeps_the_grid():
    img = _textured(256, 256, seed=2)
    fine = np.random.default_rng(3).integers(0, 256, img.shape, dtype=np.uint8)
    img = ((img.astype(np.uint16) + fine) // 2).astype(np.uint8)
    out = acquire(img, None, GSD, GSD, _acq(gsd_m=1.0))
    assert out.shape == img.shape and out.dtype == np.uint8

    def hf(x):      # energy of the pixel-to-pixel differences
        return float(np.mean(np.diff(x.astype(np.float64), axis=1) ** 2))
    assert hf(out) < 0.25 * hf(img)
    # and the coarse image is still the same picture (colours of 4 m blocks agree)
    blocks = lambda x: x.reshape(16, 16, 16, 16, 3).mean(axis=(1, 3))      # noqa: E731
    assert np.abs(blocks(out) - blocks(img)).mean() < 6.0


def test_colour_response_haze_and_contrast():
    img = _textured(seed=4)
    hazy = acquire(img, None, GSD, GSD, _acq(haze=0.3, contrast=0.7))
    assert hazy.astype(np.float64).std() < 0.7 * 0.7 * img.astype(np.float64).std() + 1.0
    warm = acquire(img, None, GSD, GSD, _acq(gain_rgb=(1.1, 1.0, 0.85)))
    ratio = warm.reshape(-1, 3).mean(axis=0) / img.reshape(-1, 3).mean(axis=0)
    assert ratio[0] > 1.05 and ratio[2] < 0.9 and abs(ratio[1] - 1.0) < 0.01
    grey = acquire(img, None, GSD, GSD, _acq(saturation=0.0))
    assert np.abs(grey.astype(int) - grey[..., :1].astype(int)).max() <= 1


def test_jpeg_changes_the_image_and_is_deterministic():
    img = _textured(seed=5)
    a = acquire(img, None, GSD, GSD, _acq(jpeg_quality=40))
    b = acquire(img, None, GSD, GSD, _acq(jpeg_quality=40))
    assert np.array_equal(a, b)
    err = np.abs(a.astype(int) - img.astype(int)).mean()
    assert 0.3 < err < 10.0


# ------------------------------------------------------------------------------- the database cached on disk
_DB = {"gsd_m": 0.5, "blur_m": 0.35, "jpeg_quality": 70, "gain_rgb": [1.05, 1.0, 0.92], "haze": 0.08,
       "georef_bias_m": [1.2, -0.9], "lean_deg": 6.0, "lean_azimuth_deg": 200.0}


def _shadows(**kw):
    from aerial_loc_env.world.shadows import ShadowConfig

    return build_config(ShadowConfig, {"database_sun_deg": [145.0, 55.0], **kw}, where="test [shadows]")


def _all_layers(om) -> list[np.ndarray]:
    return [np.asarray(getattr(om, n)) for n in ("rgb", "dsm_m", "classes", "nodata") if getattr(om, n) is not None]


@pytest.fixture()
def cache_home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path


@pytest.fixture(scope="module")
def small_database():
    """The small city's database built without the cache (the reference for bit-for-bit comparisons)."""
    from aerial_loc_env.world.city import generate_city, small_city_config
    from aerial_loc_env.world.maps.acquisition import acquire_map

    return acquire_map(generate_city(small_city_config(0)), _shadows(), _acq(**_DB))


def _forbid_building(monkeypatch):
    from aerial_loc_env.world.maps import acquisition

    def fail(*_a, **_k):
        raise AssertionError("the database was rebuilt: the cache missed")

    monkeypatch.setattr(acquisition, "acquire_map", fail)


def test_database_cache_second_construction_is_a_hit_and_bit_identical(cache_home, small_database, monkeypatch):
    from aerial_loc_env.world.city import small_city_config
    from aerial_loc_env.world.maps.acquisition import database_cache_path, database_city

    city, shadows, acq = small_city_config(0), _shadows(), _acq(**_DB)
    path = database_cache_path(city, shadows, acq)
    assert str(path).startswith(str(cache_home)) and not path.exists()
    first = database_city(city, shadows, acq)
    assert path.is_dir() and first.bundle_path == path
    _forbid_building(monkeypatch)
    second = database_city(city, shadows, acq)
    assert second.bundle_path == path and isinstance(second.rgb, np.memmap)
    for a, b, ref in zip(_all_layers(first), _all_layers(second), _all_layers(small_database), strict=True):
        assert a.dtype == ref.dtype and b.dtype == ref.dtype
        np.testing.assert_array_equal(a, ref)
        np.testing.assert_array_equal(b, ref)
    assert (second.gsd_x_m, second.gsd_y_m, second.name) == (small_database.gsd_x_m, small_database.gsd_y_m,
                                                             small_database.name)
    assert second.georef.to_dict() == small_database.georef.to_dict()


@pytest.mark.parametrize("field_name,value", [("jpeg_quality", 71), ("lean_deg", 6.5), ("georef_bias_m", [1.2, -1.0]),
                                              ("haze", 0.0), ("gain_rgb", [1.0, 1.0, 0.92])])
def test_database_cache_misses_on_a_changed_database_field(cache_home, field_name, value):
    from aerial_loc_env.world.city import small_city_config
    from aerial_loc_env.world.maps.acquisition import database_cache_path

    city, shadows = small_city_config(0), _shadows()
    assert database_cache_path(city, shadows, _acq(**{**_DB, field_name: value})) != \
        database_cache_path(city, shadows, _acq(**_DB))


def test_database_cache_key_holds_city_sun_and_generator_versions(cache_home, monkeypatch):
    from aerial_loc_env.world import shadows as shadow_mod
    from aerial_loc_env.world.city import generator as city_mod
    from aerial_loc_env.world.city import small_city_config
    from aerial_loc_env.world.maps import acquisition

    city, shadows, acq = small_city_config(0), _shadows(), _acq(**_DB)
    p = acquisition.database_cache_path(city, shadows, acq)
    assert p == acquisition.database_cache_path(small_city_config(0), _shadows(), _acq(**_DB))   # stable
    assert p != acquisition.database_cache_path(small_city_config(1), shadows, acq)
    assert p != acquisition.database_cache_path(city, _shadows(database_sun_deg=[150.0, 65.0]), acq)
    assert p != acquisition.database_cache_path(city, _shadows(database_strength=0.5), acq)
    for module in (acquisition, city_mod, shadow_mod):
        monkeypatch.setattr(module, "GENERATOR_VERSION", module.GENERATOR_VERSION + 1)
        assert acquisition.database_cache_path(city, shadows, acq) != p, module.__name__
        monkeypatch.undo()
    # without its own sun the database does not depend on the [shadows] section (nor on the shadow generator)
    no_sun = _shadows(database_sun_deg=None)
    assert acquisition.database_cache_path(city, no_sun, acq) == \
        acquisition.database_cache_path(city, _shadows(database_sun_deg=None, shadow_ratio=0.3), acq)


def test_database_cache_changed_field_builds_a_second_entry(cache_home, small_database):
    from aerial_loc_env.world.city import default_city, small_city_config
    from aerial_loc_env.world.maps.acquisition import acquire_map, database_city

    city, shadows = small_city_config(0), _shadows()
    a = database_city(city, shadows, _acq(**_DB))
    b = database_city(city, shadows, _acq(**{**_DB, "jpeg_quality": 40}))
    assert a.bundle_path != b.bundle_path and a.bundle_path.is_dir() and b.bundle_path.is_dir()
    np.testing.assert_array_equal(a.rgb, small_database.rgb)
    np.testing.assert_array_equal(b.rgb, acquire_map(default_city(city), shadows,
                                                     _acq(**{**_DB, "jpeg_quality": 40})).rgb)
    assert not np.array_equal(a.rgb, b.rgb)


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncate_rgb", "garbage_meta", "foreign"])
def test_database_cache_corrupt_or_foreign_entry_is_rebuilt_with_a_warning(cache_home, small_database, damage):
    from aerial_loc_env.world.city import default_city, small_city_config
    from aerial_loc_env.world.maps.acquisition import acquire_map, database_cache_path, database_city
    from aerial_loc_env.world.maps.cache import CacheRebuiltWarning

    city, shadows, acq = small_city_config(0), _shadows(), _acq(**_DB)
    path = database_cache_path(city, shadows, acq)
    if damage == "foreign":       # a right-sized bundle of another spec under this name
        other = acquire_map(default_city(city), shadows, _acq(**{**_DB, "jpeg_quality": 40}))
        other.save_bundle(path, provenance={"generator": "someone else"})
    else:
        database_city(city, shadows, acq)
        if damage == "truncate_rgb":
            f = path / "rgb.npy"
            f.write_bytes(f.read_bytes()[: f.stat().st_size // 3])
        else:
            (path / "meta.json").write_text("{not json")
    with pytest.warns(CacheRebuiltWarning, match="rebuilding") as record:
        om = database_city(city, shadows, acq)
    assert str(path) in str(record[0].message)
    for a, ref in zip(_all_layers(om), _all_layers(small_database), strict=True):
        np.testing.assert_array_equal(a, ref)
    assert om.bundle_path == path
    assert [p.name for p in path.parent.iterdir() if p.name.startswith(".")] == []     # nothing left aside
