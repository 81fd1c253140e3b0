"""Procedural city: determinism, layers, heights per class, texture everywhere, no repetition, disk cache."""

from __future__ import annotations

import hashlib
import multiprocessing as mp
import os

import cv2
import numpy as np
import pytest

from aerial_loc_env.config import build_config, config_to_dict
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.world.city import (
    CityConfig,
    city_cache_path,
    default_city,
    generate_city,
    height_ranges_m,
    small_city_config,
)
from aerial_loc_env.world.maps.cache import CacheRebuiltWarning
from aerial_loc_env.world.maps.landcover import LandCover

# the camera footprint of the paper: 600 x 400 px at 0.25 m/px, i.e. 150 m x 100 m
FOOT_W_PX, FOOT_H_PX = 600, 400


@pytest.fixture(scope="module")
def city():
    return generate_city(small_city_config(0))


def _layers(om) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.asarray(om.rgb), np.asarray(om.dsm_m), np.asarray(om.classes)


def _digest(om) -> str:
    h = hashlib.sha256()
    for a in _layers(om):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


# ------------------------------------------------------------------------------------------------ determinism
def test_same_seed_gives_same_bytes(city):
    again = generate_city(small_city_config(0))
    for a, b in zip(_layers(city), _layers(again), strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert a.tobytes() == b.tobytes()


def test_different_seed_gives_a_different_city(city):
    other = generate_city(small_city_config(1))
    cls_a, cls_b = _layers(city)[2], _layers(other)[2]
    # two independent cities agree on a pixel's class about as often as chance (sum of squared class shares)
    pa = np.bincount(cls_a.ravel(), minlength=256) / cls_a.size
    pb = np.bincount(cls_b.ravel(), minlength=256) / cls_b.size
    chance = float(np.sum(pa * pb))
    agree = float(np.mean(cls_a == cls_b))
    assert agree < chance + 0.15
    assert np.mean(_layers(city)[0] != _layers(other)[0]) > 0.5


# ------------------------------------------------------------------------------------------------ layers
def test_layers_shapes_dtypes_and_codes(city):
    cfg = small_city_config(0)
    w_px, h_px = cfg.size_px
    assert (w_px, h_px) == (round(cfg.width_m / cfg.gsd_m), round(cfg.height_m / cfg.gsd_m))
    rgb, dsm, cls = _layers(city)
    assert rgb.shape == (h_px, w_px, 3) and rgb.dtype == np.uint8
    assert dsm.shape == (h_px, w_px) and dsm.dtype == np.float32 and np.isfinite(dsm).all()
    assert cls.shape == (h_px, w_px) and cls.dtype == np.uint8
    assert set(np.unique(cls).tolist()) <= {int(c) for c in LandCover} - {int(LandCover.NODATA)}
    assert city.gsd_x_m == city.gsd_y_m == cfg.gsd_m
    assert city.width_m == pytest.approx(cfg.width_m) and city.height_m == pytest.approx(cfg.height_m)


def test_georeference_origin_is_the_south_west_corner(city):
    cfg = small_city_config(0)
    lat, lon = city.world_to_latlon(np.array([0.0]), np.array([0.0]))
    assert float(lat[0]) == pytest.approx(cfg.origin_lat_deg, abs=1e-9)
    assert float(lon[0]) == pytest.approx(cfg.origin_lon_deg, abs=1e-9)
    # 400 m north of the origin is 400 / 111 km of latitude (meridian arc at 37.5 deg: ~110.99 km/deg)
    lat2, _ = city.world_to_latlon(np.array([0.0]), np.array([400.0]))
    assert (float(lat2[0]) - cfg.origin_lat_deg) * 110_990 == pytest.approx(400.0, rel=2e-3)


def test_other_origin_and_gsd():
    cfg = small_city_config(3, gsd_m=0.5, origin_lat_deg=-33.9, origin_lon_deg=18.4)
    om = generate_city(cfg)
    assert (om.width_px, om.height_px) == (800, 800)
    lat, lon = om.world_to_latlon(np.array([0.0]), np.array([0.0]))
    assert (float(lat[0]), float(lon[0])) == pytest.approx((-33.9, 18.4), abs=1e-9)


def test_small_city_is_still_a_city(city):
    cls = _layers(city)[2]
    share = np.bincount(cls.ravel(), minlength=256) / cls.size
    for code, least in ((LandCover.ROAD, 0.08), (LandCover.BUILDING, 0.05), (LandCover.SIDEWALK, 0.02),
                        (LandCover.TREE, 0.01), (LandCover.LANE_MARKING, 0.002), (LandCover.CAR, 0.002),
                        (LandCover.PARKING, 0.01), (LandCover.WATER, 0.02), (LandCover.ROOF_EQUIPMENT, 0.0005)):
        assert share[int(code)] >= least, f"{code.name} covers only {share[int(code)]:.4f}"


def test_no_river_option():
    om = generate_city(small_city_config(0, river=False))
    cls = np.asarray(om.classes)
    assert np.mean(cls == LandCover.WATER) < 0.02       # only park ponds remain


# ------------------------------------------------------------------------------------------------ heights
def test_heights_in_documented_ranges_per_class(city):
    _, dsm, cls = _layers(city)
    ranges = height_ranges_m(small_city_config(0))
    for code in np.unique(cls):
        h = dsm[cls == code]
        lo, hi = ranges.get(LandCover(int(code)), (0.0, 0.0))
        assert h.min() >= lo - 1e-4 and h.max() <= hi + 1e-4, \
            f"{LandCover(int(code)).name}: heights {h.min():.2f}..{h.max():.2f} outside [{lo}, {hi}]"


def test_building_heights_span_low_rise_to_towers(city):
    _, dsm, cls = _layers(city)
    h = dsm[cls == LandCover.BUILDING]
    assert np.percentile(h, 5) < 10.0          # houses, 1-3 floors
    assert h.max() > 30.0                      # towers or apartment slabs


def test_max_building_height_is_honoured():
    cfg = small_city_config(0, max_building_height_m=20.0)
    om = generate_city(cfg)
    dsm, cls = np.asarray(om.dsm_m), np.asarray(om.classes)
    assert dsm[(cls == LandCover.BUILDING) | (cls == LandCover.ROOF_EQUIPMENT)].max() <= 20.0 + 1e-4


# ------------------------------------------------------------------------------------------------ texture
def _grey(om) -> np.ndarray:
    return cv2.cvtColor(np.asarray(om.rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)


def _windows(h: int, w: int, step: int):
    for v in range(0, h - FOOT_H_PX + 1, step):
        for u in range(0, w - FOOT_W_PX + 1, step):
            yield v, u


def test_every_footprint_has_texture_and_structure(city):
    """Every 150 m x 100 m window: grey std, gradient energy and at least three land covers.

    Thresholds: a window of one material with only its noise texture has a grey std of a few levels and
    one class; structure (roads, roofs, trees) gives tens of levels. 12 levels and a mean gradient of
    1.5 levels/px sit well above texture-only and far below what the city shows (~25 and ~3).
    """
    g = _grey(city)
    cls = _layers(city)[2]
    gm = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(g, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
    n = 0
    for v, u in _windows(*g.shape, 200):
        win = g[v:v + FOOT_H_PX, u:u + FOOT_W_PX]
        assert win.std() > 12.0, f"window at ({u}, {v}) px is featureless: std {win.std():.1f}"
        assert gm[v:v + FOOT_H_PX, u:u + FOOT_W_PX].mean() > 1.5
        share = np.bincount(cls[v:v + FOOT_H_PX, u:u + FOOT_W_PX].ravel(), minlength=256) / win.size
        assert (share > 0.02).sum() >= 3, f"window at ({u}, {v}) px has fewer than 3 land covers"
        n += 1
    assert n >= 25


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    return float((a * b).sum() / np.sqrt((a * a).sum() * (b * b).sum()))


def test_map_does_not_repeat(city):
    """Distant footprints are uncorrelated: raw (structure) and high-passed (texture, would reveal tiling)."""
    g = _grey(city)
    hp = g - cv2.blur(g, (9, 9))
    wins = [(v, u) for v in range(0, g.shape[0] - FOOT_H_PX + 1, 400) for u in range(0, g.shape[1] - FOOT_W_PX + 1,
                                                                                    500)]
    assert len(wins) >= 9
    raw, fine = [], []
    for i, (v1, u1) in enumerate(wins):
        for v2, u2 in wins[i + 1:]:
            a, b = (slice(v1, v1 + FOOT_H_PX), slice(u1, u1 + FOOT_W_PX)), (slice(v2, v2 + FOOT_H_PX),
                                                                               slice(u2, u2 + FOOT_W_PX))
            raw.append(abs(_ncc(g[a], g[b])))
            fine.append(abs(_ncc(hp[a], hp[b])))
    # independent 240k-pixel textures correlate at ~1/sqrt(N_eff); structure (street grids) up to ~0.3
    assert max(raw) < 0.5
    assert max(fine) < 0.1
    # the metric does catch a tiled texture
    tile = hp[:200, :300]
    tiled = np.tile(tile, (2, 2))
    assert _ncc(tiled[:200, :300], tiled[200:, 300:]) > 0.99


# ------------------------------------------------------------------------------------------------ config
def test_config_validation():
    with pytest.raises(ConfigError, match="width_m"):
        build_config(CityConfig, {"width_m": 50.0})
    with pytest.raises(ConfigError, match="allowed keys"):
        build_config(CityConfig, {"density": 1.0})
    with pytest.raises(ConfigError, match="name"):
        build_config(CityConfig, {"name": "a/b"})
    with pytest.raises(ConfigError, match="CityConfig"):
        generate_city({"seed": 1})   # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="Mpx"):
        build_config(CityConfig, {"width_m": 8000.0, "height_m": 8000.0, "gsd_m": 0.1})
    cfg = small_city_config(5, river=False, tree_density=2.0)
    assert build_config(CityConfig, config_to_dict(cfg)) == cfg       # spec files round-trip
    default = CityConfig()
    assert default.width_m >= 1200 and default.height_m >= 1400 and default.gsd_m == 0.25
    assert default.size_px == (4800, 5600)


# ------------------------------------------------------------------------------------------------ cache
@pytest.fixture()
def cache_home(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path


def test_cache_second_call_maps_the_bundle(cache_home, city):
    cfg = small_city_config(0)
    path = city_cache_path(cfg)
    assert str(path).startswith(str(cache_home)) and not path.exists()
    first = default_city(cfg)
    assert path.is_dir()
    second = default_city(cfg)
    assert second.bundle_path == path
    for name in ("rgb", "dsm_m", "classes"):
        assert isinstance(getattr(first, name), np.memmap) and isinstance(getattr(second, name), np.memmap)
    for a, b, c in zip(_layers(first), _layers(second), _layers(city), strict=True):
        np.testing.assert_array_equal(b, c)
        np.testing.assert_array_equal(a, c)
    assert city_cache_path(small_city_config(1)) != path


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncate_rgb", "garbage_meta", "partial_dir", "wrong_shape"])
def test_damaged_cache_entry_is_regenerated(cache_home, city, damage):
    cfg = small_city_config(0)
    path = city_cache_path(cfg)
    if damage == "partial_dir":
        path.mkdir(parents=True)
        np.save(path / "rgb.npy", np.zeros((4, 4, 3), np.uint8))
    elif damage == "wrong_shape":
        generate_city(small_city_config(0, gsd_m=0.5)).save_bundle(path)
    else:
        default_city(cfg)
        if damage == "truncate_rgb":
            f = path / "rgb.npy"
            f.write_bytes(f.read_bytes()[: f.stat().st_size // 3])
        else:
            (path / "meta.json").write_text("{not json")
    with pytest.warns(CacheRebuiltWarning, match=f"cached map {path} is unusable"):
        om = default_city(cfg)
    assert _digest(om) == _digest(city)
    assert om.bundle_path == path
    leftovers = [p.name for p in path.parent.iterdir() if p != path]
    assert leftovers == []


def _race_worker(barrier, queue) -> None:
    barrier.wait()
    om = default_city(small_city_config(0))
    queue.put(_digest(om))


@pytest.mark.slow
def test_concurrent_first_calls_do_not_corrupt_the_cache(cache_home, city):
    ctx = mp.get_context("spawn")
    barrier, queue = ctx.Barrier(2), ctx.Queue()
    procs = [ctx.Process(target=_race_worker, args=(barrier, queue)) for _ in range(2)]
    for p in procs:
        p.start()
    digests = [queue.get(timeout=120) for _ in procs]
    for p in procs:
        p.join(timeout=60)
        assert p.exitcode == 0
    assert digests == [_digest(city)] * 2
    path = city_cache_path(small_city_config(0))
    assert sorted(os.listdir(path.parent)) == [path.name]
    assert _digest(default_city(small_city_config(0))) == _digest(city)
