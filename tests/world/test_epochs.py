"""Two epochs of the world (world/city/epochs.py): identity at rate 0, determinism, each change kind where it belongs.

Rates are checked on a synthetic map with known objects (400 separated box buildings, 200 cars on a road,
300 trees, 200 marking dashes): the fraction of objects a kind changes is binomial(n, rate), so it must lie
within 4 standard deviations sqrt(rate (1 - rate) / n) of the rate.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import MapError
from aerial_loc_env.world.city.epochs import EpochConfig, change_epoch, epoch_cache_path
from aerial_loc_env.world.maps.geo import LocalTangentGeoref
from aerial_loc_env.world.maps.landcover import LandCover as LC
from aerial_loc_env.world.maps.orthomap import Orthomap
from aerial_loc_env.world.shadows import Sun, cast_shadow_mask

GSD = 0.25
N = 1400          # map side, px (350 m)


def _cfg(**kw) -> EpochConfig:
    return build_config(EpochConfig, kw, where="test [epoch]")


def _synthetic() -> tuple[Orthomap, dict[str, list[tuple[slice, slice]]]]:
    """Lawn; a 20 x 20 grid of 6 m x 6 m buildings (8-20 m tall) in the north; a road band with 200 cars and
    200 marking dashes across the middle; 300 trees (r 3 m, 12 m tall) and a pond in the south."""
    rng = np.random.default_rng(7)
    tex = rng.integers(-12, 13, (N, N, 1))
    rgb = np.clip(np.array([96, 132, 66]) + tex, 0, 255).astype(np.uint8)
    cls = np.full((N, N), LC.LAWN, np.uint8)
    dsm = np.zeros((N, N), np.float32)
    objs: dict[str, list] = {"building": [], "car": [], "marking": [], "tree": []}
    for i in range(20):
        for j in range(20):
            r0, c0 = 20 + 30 * i, 40 + 65 * j
            sl = (slice(r0, r0 + 24), slice(c0, c0 + 24))
            rgb[sl] = np.clip(np.array([150, 148, 144]) + tex[sl], 0, 255)
            cls[sl], dsm[sl] = LC.BUILDING, 8.0 + (i + j) % 13
            objs["building"].append(sl)
    road = slice(640, 760)
    rgb[road] = np.clip(90 + tex[road], 0, 255)
    cls[road] = LC.ROAD
    for k in range(200):                      # 4 lanes of 50 cars, 4.5 m x 1.8 m, 6.5 m apart
        lane, n = divmod(k, 50)
        r0, c0 = 650 + 28 * lane, 20 + 27 * n
        sl = (slice(r0, r0 + 7), slice(c0, c0 + 18))
        rgb[sl] = (200, 40, 40) if k % 2 else (230, 230, 230)
        cls[sl], dsm[sl] = LC.CAR, 1.5
        objs["car"].append(sl)
    for k in range(200):                      # dashes between the lanes: 3 m x 0.5 m
        lane, n = divmod(k, 50)
        r0, c0 = 662 + 28 * lane, 22 + 27 * n
        if lane == 3:
            r0 = 746
        sl = (slice(r0, r0 + 2), slice(c0, c0 + 12))
        rgb[sl] = 200
        cls[sl] = LC.LANE_MARKING
        objs["marking"].append(sl)
    for k in range(300):
        i, j = divmod(k, 30)
        cy, cx = 800 + 30 * i, 30 + 40 * j
        yy, xx = np.ogrid[:N, :N]
        disc = (yy - cy) ** 2 + (xx - cx) ** 2 <= 12 ** 2
        rgb[disc] = (50, 90, 44)
        cls[disc], dsm[disc] = LC.TREE, 12.0
        objs["tree"].append((slice(cy - 12, cy + 13), slice(cx - 12, cx + 13)))
    rgb[1110:1390, 1250:1390] = (40, 80, 120)
    cls[1110:1390, 1250:1390] = LC.WATER
    georef = LocalTangentGeoref(37.5, 127.2, GSD, GSD, origin_u_px=-0.5, origin_v_px=N - 0.5)
    om = Orthomap(rgb=rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=georef, dsm_m=dsm, classes=cls, name="synthetic")
    return om, objs


@pytest.fixture(scope="module")
def synthetic():
    return _synthetic()


def _changed(a: Orthomap, b: Orthomap, sl) -> bool:
    return bool(np.any(np.asarray(a.rgb)[sl] != b.rgb[sl]))


def _binomial_ok(k: int, n: int, rate: float) -> None:
    sigma = math.sqrt(rate * (1 - rate) / n)
    assert abs(k / n - rate) <= 4 * sigma, f"{k}/{n} = {k / n:.3f}, rate {rate} +- 4 x {sigma:.3f}"


def test_all_rates_zero_is_the_same_map(synthetic):
    om, _ = synthetic
    assert _cfg().is_identity and _cfg(seed=12).is_identity
    assert change_epoch(om, _cfg(seed=12), seed=3) is om


def test_deterministic_from_the_seeds(synthetic):
    om, _ = synthetic
    cfg = _cfg(car_turnover=0.3, car_arrivals=0.3, leaf_off=0.4, roof_change=0.3, built=0.05, seed=4)
    b1, b2 = change_epoch(om, cfg, seed=1), change_epoch(om, cfg, seed=1)
    for name in ("rgb", "dsm_m", "classes"):
        assert np.array_equal(getattr(b1, name), getattr(b2, name))
    b3 = change_epoch(om, _cfg(**{**cfg.__dict__, "seed": 5}), seed=1)
    assert not np.array_equal(b1.rgb, b3.rgb)
    # one kind's draws do not depend on another kind's rate
    only = change_epoch(om, _cfg(roof_change=0.3, seed=4), seed=1)
    assert np.array_equal(only.rgb[:620], change_epoch(om, _cfg(roof_change=0.3, leaf_off=0.9, seed=4),
                                                       seed=1).rgb[:620])


def test_roof_change_rate_and_nothing_else(synthetic):
    om, objs = synthetic
    b = change_epoch(om, _cfg(roof_change=0.3), seed=0)
    k = sum(_changed(om, b, sl) for sl in objs["building"])
    _binomial_ok(k, len(objs["building"]), 0.3)
    assert np.array_equal(b.dsm_m, om.dsm_m) and np.array_equal(b.classes, om.classes)
    assert np.array_equal(b.rgb[620:], om.rgb[620:])


def test_demolished_buildings_leave_cleared_ground_and_lose_their_shadows(synthetic):
    om, objs = synthetic
    b = change_epoch(om, _cfg(demolished=0.25), seed=0)
    gone = [sl for sl in objs["building"] if np.all(b.dsm_m[sl] == 0.0)]
    _binomial_ok(len(gone), len(objs["building"]), 0.25)
    for sl in gone:
        assert np.all(b.classes[sl] == LC.BARE_SOIL)
    kept = [sl for sl in objs["building"] if sl not in gone]
    assert all(np.array_equal(b.dsm_m[sl], om.dsm_m[sl]) for sl in kept)
    # shadows fall north, at most 20 m / tan(70 deg) = 7.3 m (29 px) long: the row to the south (30 px on)
    # cannot reach past a demolished building's north edge, so what lay north of it was its own shadow
    sun = Sun(180.0, 70.0)
    sa = cast_shadow_mask(np.asarray(om.dsm_m), GSD, GSD, sun)
    sb = cast_shadow_mask(b.dsm_m, GSD, GSD, sun)
    for sl in gone:                          # the 6 m north of each demolished building was shadowed, now lit
        north = (slice(sl[0].start - 4, sl[0].start), sl[1])
        assert sa[north].mean() > 0.9 and sb[north].mean() < 0.1


def test_new_buildings_stand_on_open_ground_with_height(synthetic):
    om, _ = synthetic
    b = change_epoch(om, _cfg(built=0.1), seed=0)
    new = (b.classes == LC.BUILDING) & (np.asarray(om.classes) != LC.BUILDING)
    assert new.any()
    assert np.all(np.asarray(om.classes)[new] == LC.LAWN)
    assert np.all(b.dsm_m[new] >= 3.0)
    n, _ = cv2.connectedComponents(new.astype(np.uint8))
    assert 1 <= n - 1 <= 40 + 4 * math.sqrt(40)      # Poisson(0.1 x 400) at most
    sun = Sun(180.0, 40.0)
    assert cast_shadow_mask(b.dsm_m, GSD, GSD, sun).sum() > cast_shadow_mask(np.asarray(om.dsm_m), GSD, GSD,
                                                                             sun).sum()


def test_construction_sites_clear_open_ground(synthetic):
    om, _ = synthetic
    b = change_epoch(om, _cfg(construction_per_km2=60.0), seed=0)
    site = (b.classes == LC.BARE_SOIL) & (np.asarray(om.classes) != LC.BARE_SOIL)
    assert site.sum() * GSD ** 2 > 300.0
    assert np.all(np.isin(np.asarray(om.classes)[site], (LC.LAWN, LC.TREE)))


def test_cars_leave_at_the_turnover_rate_and_arrive_on_the_road(synthetic):
    om, objs = synthetic
    b = change_epoch(om, _cfg(car_turnover=0.4), seed=0)
    gone = [sl for sl in objs["car"] if not np.any(b.classes[sl] == LC.CAR)]
    _binomial_ok(len(gone), len(objs["car"]), 0.4)
    for sl in gone:
        assert np.all(b.classes[sl] == LC.ROAD) and np.all(b.dsm_m[sl] == 0.0)
        assert np.abs(b.rgb[sl].astype(int) - 90).mean() < 15          # the asphalt, not the car
    b = change_epoch(om, _cfg(car_arrivals=0.3), seed=0)
    new = (b.classes == LC.CAR) & (np.asarray(om.classes) != LC.CAR)
    assert new.any() and np.all(np.isin(np.asarray(om.classes)[new], (LC.ROAD, LC.LANE_MARKING)))
    assert np.allclose(b.dsm_m[new], 1.5)
    n, _ = cv2.connectedComponents(new.astype(np.uint8))
    assert n - 1 <= 60 + 4 * math.sqrt(60)


def test_leaf_off_trees_thin_their_crowns(synthetic):
    om, objs = synthetic
    b = change_epoch(om, _cfg(leaf_off=0.5), seed=0)
    bare = [sl for sl in objs["tree"] if _changed(om, b, sl)]
    _binomial_ok(len(bare), len(objs["tree"]), 0.5)
    dsm_a, dsm_b = np.asarray(om.dsm_m), b.dsm_m
    for sl in bare:
        tree = np.asarray(om.classes)[sl] == LC.TREE
        kept = np.mean(dsm_b[sl][tree] > 0)
        assert 0.02 < kept < 0.8                                   # a sparse crown of branches
        assert b.rgb[sl][tree].mean() > np.asarray(om.rgb)[sl][tree].mean() + 10    # no dark foliage
    assert np.array_equal(b.classes, om.classes)
    assert np.all(dsm_b <= dsm_a)


def test_season_grass_and_water_change_only_their_classes(synthetic):
    om, _ = synthetic
    cls = np.asarray(om.classes)
    b = change_epoch(om, _cfg(grass_dryness=0.8), seed=0)
    lawn = cls == LC.LAWN
    ra = np.asarray(om.rgb)[lawn].astype(float).mean(axis=0)
    rb = b.rgb[lawn].astype(float).mean(axis=0)
    assert rb[0] / rb[1] > ra[0] / ra[1] + 0.2           # redder: straw, not green
    assert np.array_equal(b.rgb[~lawn], np.asarray(om.rgb)[~lawn])
    w = change_epoch(om, _cfg(water_change=0.7), seed=0)
    water = cls == LC.WATER
    assert np.abs(w.rgb[water].astype(int) - np.asarray(om.rgb)[water]).mean() > 10
    assert np.array_equal(w.rgb[~water], np.asarray(om.rgb)[~water])


def test_marking_renewal_rate(synthetic):
    om, objs = synthetic
    b = change_epoch(om, _cfg(marking_renewal=0.5), seed=0)
    k = sum(_changed(om, b, sl) for sl in objs["marking"])
    _binomial_ok(k, len(objs["marking"]), 0.5)


def test_maps_without_layers_are_refused(synthetic):
    om, _ = synthetic
    import dataclasses

    with pytest.raises(MapError, match="classes"):
        change_epoch(dataclasses.replace(om, classes=None), _cfg(leaf_off=0.5))


def test_cache_key_holds_generator_and_epoch_config(monkeypatch):
    from aerial_loc_env.world.city import epochs, small_city_config

    city = small_city_config(0)
    p1 = epoch_cache_path(city, _cfg(leaf_off=0.5))
    assert p1 != epoch_cache_path(city, _cfg(leaf_off=0.6))
    assert p1 != epoch_cache_path(city, _cfg(leaf_off=0.5, seed=1))
    assert p1 != epoch_cache_path(small_city_config(1), _cfg(leaf_off=0.5))
    monkeypatch.setattr(epochs, "GENERATOR_VERSION", epochs.GENERATOR_VERSION + 1)
    assert p1 != epoch_cache_path(city, _cfg(leaf_off=0.5))
    from aerial_loc_env.world.city import generator as city_mod

    monkeypatch.setattr(epochs, "GENERATOR_VERSION", epochs.GENERATOR_VERSION - 1)
    monkeypatch.setattr(city_mod, "GENERATOR_VERSION", city_mod.GENERATOR_VERSION + 1)
    assert p1 != epoch_cache_path(city, _cfg(leaf_off=0.5))
