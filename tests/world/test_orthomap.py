"""Orthomap: validation, world frame, lat/lon through the georeference, bundles (atomic, mmap, pickle)."""

from __future__ import annotations

import hashlib
import json
import os
import pickle
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps import orthomap as om_mod
from aerial_loc_env.world.maps.geo import LocalTangentGeoref, WorldMercatorGeoref
from aerial_loc_env.world.maps.landcover import LandCover, colorize_classes
from aerial_loc_env.world.maps.orthomap import Orthomap, add_bundle_checksums

H, W = 60, 80


def make_map(gsd_x: float = 0.5, gsd_y: float = 0.25, *, layers: bool = True, seed: int = 0) -> Orthomap:
    rng = np.random.default_rng(seed)
    g = LocalTangentGeoref.centered(39.17, -0.414, W, H, gsd_x, gsd_y)
    nodata = np.zeros((H, W), bool)
    nodata[:5, :7] = True
    return Orthomap(
        rng.integers(0, 256, (H, W, 3), dtype=np.uint8), gsd_x, gsd_y, g,
        dsm_m=rng.uniform(0, 30, (H, W)).astype(np.float32) if layers else None,
        nodata=nodata if layers else None,
        classes=rng.integers(0, len(LandCover), (H, W), dtype=np.uint8) if layers else None,
        name="toy", source="unit test")


def test_sizes_and_world_frame_orientation():
    om = make_map()
    assert (om.width_px, om.height_px) == (W, H)
    assert om.width_m == pytest.approx(W * 0.5) and om.height_m == pytest.approx(H * 0.25)
    x, y = om.pixel_to_world(0, H - 1)              # bottom-left pixel centre
    assert (float(x), float(y)) == (0.25, 0.125)
    x, y = om.pixel_to_world(-0.5, H - 0.5)         # south-west outer corner = origin
    assert (float(x), float(y)) == (0.0, 0.0)
    _, y_top = om.pixel_to_world(0, 0)
    _, y_bottom = om.pixel_to_world(0, H - 1)
    assert y_top > y_bottom                          # north is up: row 0 has the largest y
    assert float(y_top) == pytest.approx(om.height_m - 0.125)


def test_pixel_world_round_trip_vectorized():
    om = make_map()
    rng = np.random.default_rng(3)
    u, v = rng.uniform(-1, W, (7, 5)), rng.uniform(-1, H, (7, 5))
    x, y = om.pixel_to_world(u, v)
    assert x.shape == (7, 5)
    u2, v2 = om.world_to_pixel(x, y)
    assert np.max(np.abs(u2 - u)) < 1e-12 and np.max(np.abs(v2 - v)) < 1e-12


def test_world_latlon_round_trip_and_axes(vincenty_m: Callable[..., float]):
    om = make_map()
    rng = np.random.default_rng(4)
    x, y = rng.uniform(0, om.width_m, 200), rng.uniform(0, om.height_m, 200)
    lat, lon = om.world_to_latlon(x, y)
    x2, y2 = om.latlon_to_world(lat, lon)
    assert np.max(np.hypot(x2 - x, y2 - y)) < 1e-6                      # sub-micrometre
    lat3, lon3 = om.world_to_latlon(x2, y2)
    assert np.max(np.abs(lat3 - lat)) < 1e-9 and np.max(np.abs(lon3 - lon)) < 1e-9
    lat0, lon0 = om.world_to_latlon(10.0, 5.0)
    lat_n, lon_n = om.world_to_latlon(10.0, 6.0)
    lat_e, lon_e = om.world_to_latlon(11.0, 5.0)
    # +y is north, +x is east (the plane's north drifts off the meridian by ~ x tan(lat) / R away from the origin)
    assert lat_n > lat0 and abs(float(lon_n - lon0)) < 1e-9
    assert lon_e > lon0 and abs(float(lat_e - lat0)) < 1e-9
    # world metres are ground metres (anisotropic pixels included)
    assert vincenty_m(float(lat0), float(lon0), float(lat_n), float(lon_n)) == pytest.approx(1.0, rel=1e-6)
    assert vincenty_m(float(lat0), float(lon0), float(lat_e), float(lon_e)) == pytest.approx(1.0, rel=1e-6)


def test_validation_names_layer_and_shapes():
    om = make_map(layers=False)
    good = dict(rgb=om.rgb, gsd_x_m=0.5, gsd_y_m=0.5, georef=om.georef)
    with pytest.raises(MapError, match=r"'dsm_m' has shape \(10, 10\).*\(60, 80, 3\)"):
        Orthomap(**good, dsm_m=np.zeros((10, 10), np.float32))
    with pytest.raises(MapError, match=r"'nodata' must have dtype bool, got uint8"):
        Orthomap(**good, nodata=np.zeros((H, W), np.uint8))
    with pytest.raises(MapError, match=r"'classes' must have dtype uint8"):
        Orthomap(**good, classes=np.zeros((H, W), np.int32))
    with pytest.raises(MapError, match=r"'dsm_m' must have dtype float32, got float64"):
        Orthomap(**good, dsm_m=np.zeros((H, W)))
    with pytest.raises(MapError, match="NaN"):
        Orthomap(**good, dsm_m=np.full((H, W), np.nan, np.float32))
    with pytest.raises(MapError, match=r"'rgb' must be an \(H, W, 3\) uint8"):
        Orthomap(**{**good, "rgb": np.zeros((H, W), np.uint8)})
    with pytest.raises(MapError, match=r"'rgb' must have dtype uint8"):
        Orthomap(**{**good, "rgb": np.zeros((H, W, 3), np.float32)})
    with pytest.raises(MapError, match="gsd_y_m"):
        Orthomap(**{**good, "gsd_y_m": 0.0})
    with pytest.raises(MapError, match="georef"):
        Orthomap(**{**good, "georef": None})


def test_masks_contains_and_fits():
    om = make_map()
    valid = om.valid_mask()
    assert valid.dtype == bool and not valid[:5, :7].any() and valid[5:, :].all()
    assert om.nodata_fraction() == pytest.approx(35 / (H * W))
    assert make_map(layers=False).valid_mask().all()
    inside = om.contains_world(np.array([0.0, 1.0, 20.0, om.width_m]), np.array([0.0, 1.0, 7.0, 1.0]),
                               margin_m=1.0)
    assert inside.tolist() == [False, True, True, False]
    om.check_fits(om.width_m, om.height_m, "test")
    with pytest.raises(MapError, match=r"test: map 'toy' is 40.0 x 15.0 m, smaller than one camera footprint"):
        om.check_fits(30.0, 20.0, "test")


def test_crop_keeps_georeference_and_layers():
    om = make_map()
    c = om.crop(10, 20, 30, 15)
    assert (c.width_px, c.height_px) == (30, 15)
    np.testing.assert_array_equal(c.dsm_m, om.dsm_m[20:35, 10:40])
    np.testing.assert_allclose(np.stack(c.georef.pixel_to_latlon(0.0, 0.0)),
                               np.stack(om.georef.pixel_to_latlon(10.0, 20.0)), atol=1e-12)
    with pytest.raises(MapError, match="not inside"):
        om.crop(70, 0, 20, 10)


def test_bundle_round_trip_mmap_and_pickle(tmp_path):
    om = make_map()
    path = om.save_bundle(tmp_path / "toy.alm", provenance={"by": "test"})
    meta = json.loads((path / "meta.json").read_text())
    assert meta["format_version"] == 1 and meta["provenance"] == {"by": "test"}
    assert sorted(meta["layers"]) == ["classes", "dsm_m", "nodata", "rgb"]
    back = Orthomap.load_bundle(path)
    for name in ("rgb", "dsm_m", "nodata", "classes"):
        a, b = getattr(om, name), getattr(back, name)
        assert isinstance(b, np.memmap) and not b.flags.writeable
        assert a.dtype == b.dtype and np.array_equal(a, b)
    with pytest.raises(ValueError):
        back.rgb[0, 0, 0] = 1
    assert back.georef == om.georef and (back.gsd_x_m, back.gsd_y_m) == (om.gsd_x_m, om.gsd_y_m)
    assert (back.name, back.source, back.bundle_path) == ("toy", "unit test", path)
    blob = pickle.dumps(back)
    assert len(blob) < 1000 < om.rgb.nbytes                # the path, not the layers
    again = pickle.loads(blob)
    assert np.array_equal(again.dsm_m, om.dsm_m) and isinstance(again.rgb, np.memmap)
    # a crop of a crop of a memory map also pickles as (bundle, window)
    crop = back.crop(5, 6, 40, 30).crop(2, 3, 20, 10, name="small")
    blob = pickle.dumps(crop)
    assert len(blob) < 1000
    again = pickle.loads(blob)
    assert again.name == "small" and np.array_equal(again.rgb, om.rgb[9:19, 7:27])
    assert again.georef == crop.georef
    # in-memory maps pickle their data
    mem = Orthomap.load_bundle(path, mmap=False)
    assert not isinstance(mem.rgb, np.memmap) and mem.bundle_path is None
    assert np.array_equal(pickle.loads(pickle.dumps(mem)).classes, om.classes)


def test_bundle_overwrite_rules(tmp_path):
    om = make_map()
    path = om.save_bundle(tmp_path / "toy.alm")
    loaded = Orthomap.load_bundle(path)
    blob = pickle.dumps(loaded)
    with pytest.raises(MapError, match="overwrite=True"):
        make_map(seed=1).save_bundle(path)
    make_map(seed=1).save_bundle(path, overwrite=True)
    assert np.array_equal(Orthomap.load_bundle(path).rgb, make_map(seed=1).rgb)
    assert np.array_equal(loaded.rgb, om.rgb)          # the old memory map still reads the old layers
    with pytest.raises(MapError, match="replaced after this map was pickled"):
        pickle.loads(blob)
    (tmp_path / "plain").mkdir()
    with pytest.raises(MapError, match="not an orthomap bundle"):
        om.save_bundle(tmp_path / "plain", overwrite=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plain", "toy.alm"]   # no temp leftovers


def test_interrupted_save_leaves_nothing(tmp_path, monkeypatch):
    om = make_map()
    good = make_map(seed=2).save_bundle(tmp_path / "keep.alm")
    calls = []

    def failing_save(file, arr, **kw):
        calls.append(file)
        if len(calls) == 2:
            raise KeyboardInterrupt("simulated crash while writing the second layer")
        return real_save(file, arr, **kw)

    real_save = np.save
    monkeypatch.setattr(np, "save", failing_save)
    with pytest.raises(KeyboardInterrupt):
        om.save_bundle(tmp_path / "new.alm")
    calls.clear()
    with pytest.raises(KeyboardInterrupt):
        om.save_bundle(good, overwrite=True)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.alm"]
    assert np.array_equal(Orthomap.load_bundle(good).rgb, make_map(seed=2).rgb)   # old bundle intact


def test_corrupt_bundles_are_clear_errors(tmp_path):
    path = make_map().save_bundle(tmp_path / "toy.alm")
    meta = json.loads((path / "meta.json").read_text())
    (path / "meta.json").write_text(json.dumps({**meta, "format_version": 99}))
    with pytest.raises(MapError, match="version 99"):
        Orthomap.load_bundle(path)
    (path / "meta.json").write_text(json.dumps(meta))
    (path / "dsm_m.npy").unlink()
    with pytest.raises(MapError, match="dsm_m"):
        Orthomap.load_bundle(path)
    with pytest.raises(MapError, match="no meta.json"):
        Orthomap.load_bundle(tmp_path)


def test_mercator_map_world_to_latlon(vincenty_m: Callable[..., float]):
    g = WorldMercatorGeoref.north_up("EPSG:3395", -46189.54, 4719172.21, 0.1, 0.1)
    gx, gy = (float(a) for a in g.ground_gsd_m(49.5, 29.5))
    om = Orthomap(np.zeros((H, W, 3), np.uint8), gx, gy, g)
    lat, lon = om.world_to_latlon(0.5 * om.width_m, 0.5 * om.height_m)
    lat_c, lon_c = g.pixel_to_latlon((W - 1) / 2, (H - 1) / 2)
    assert float(lat) == pytest.approx(float(lat_c), abs=1e-12) and float(lon) == pytest.approx(float(lon_c))
    # one world metre east is one ground metre (to the Mercator scale change over the map, ~1e-6)
    la2, lo2 = om.world_to_latlon(0.5 * om.width_m + 1.0, 0.5 * om.height_m)
    assert vincenty_m(float(lat), float(lon), float(la2), float(lo2)) == pytest.approx(1.0, rel=1e-5)


def test_landcover_palette():
    cls = np.array([[LandCover.NODATA, LandCover.WATER], [LandCover.TREE, 250]], dtype=np.uint8)
    img = colorize_classes(cls)
    assert img.shape == (2, 2, 3) and img.dtype == np.uint8
    assert img[0, 0].tolist() == [0, 0, 0] and img[0, 1].tolist() != img[1, 0].tolist()
    assert len({tuple(c) for c in img.reshape(-1, 3).tolist()}) == 4


def test_concurrent_writer_race_is_a_clear_error(tmp_path, monkeypatch):
    """Two processes caching the same bundle: the loser gets a MapError, the winner's bundle stays whole."""
    real_replace = om_mod.os.replace
    state = {"raced": False}

    def racing_replace(src, dst):
        if not state["raced"]:
            state["raced"] = True
            make_map(seed=9).save_bundle(dst)      # the other process finishes first
        return real_replace(src, dst)

    monkeypatch.setattr(om_mod.os, "replace", racing_replace)
    with pytest.raises(MapError, match="written meanwhile by another process"):
        make_map().save_bundle(tmp_path / "race.alm")
    monkeypatch.undo()
    assert np.array_equal(Orthomap.load_bundle(tmp_path / "race.alm").rgb, make_map(seed=9).rgb)
    assert [p.name for p in tmp_path.iterdir()] == ["race.alm"]


@pytest.mark.parametrize("layers", [[1, 2], {"rgb": "x.npy"}, {"rgb": {"file": "rgb.npy"}}, "rgb"])
def test_bundle_with_malformed_layers_is_a_map_error(tmp_path, layers):
    om = Orthomap(np.zeros((20, 30, 3), np.uint8), 1.0, 1.0,
                  __import__("aerial_loc_env.world.maps.geo", fromlist=["x"]).LocalTangentGeoref.centered(
                      0.0, 0.0, 30, 20, 1.0, 1.0), name="m")
    path = om.save_bundle(tmp_path / "m.alm")
    meta = json.loads((Path(path) / "meta.json").read_text())
    meta["layers"] = layers
    (Path(path) / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(MapError, match=r"meta\.json.*layers"):
        Orthomap.load_bundle(path)


# ------------------------------------------------------------------------------------------------ layer checksums
def _change_same_size(file: Path, *, new_file: bool = False) -> None:
    """Change 32 bytes in the middle of a layer file, keeping its size: in place, or as a new file renamed over."""
    data = bytearray(file.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 32] = bytes(255 - b for b in data[mid:mid + 32])
    if new_file:
        file.with_name("swap").write_bytes(data)
        os.replace(file.with_name("swap"), file)
    else:
        with open(file, "r+b") as fh:
            fh.write(data)


@pytest.mark.parametrize("layer", ["rgb", "dsm_m", "nodata", "classes"])
def test_a_layer_changed_at_the_same_size_is_a_map_error(tmp_path, layer):
    path = make_map().save_bundle(tmp_path / "toy.alm")
    meta = json.loads((path / "meta.json").read_text())
    assert meta["layers"][layer]["sha256"] == hashlib.sha256((path / f"{layer}.npy").read_bytes()).hexdigest()
    Orthomap.load_bundle(path)
    _change_same_size(path / f"{layer}.npy")
    with pytest.raises(MapError, match=rf"{layer}\.npy: layer '{layer}' does not match the SHA-256 in meta\.json "
                                       r"\(the file changed after the bundle was written\); the bundle is corrupt"):
        Orthomap.load_bundle(path)


def test_verified_layers_are_read_again_only_when_they_change(tmp_path, monkeypatch):
    """The stamp spares the hashing of unchanged files; a replaced, touched or unstamped file is hashed."""
    monkeypatch.setattr(om_mod, "_RACY_NS", -10**15)     # as if file times were exact: trust every stamp entry
    hashed: list[str] = []
    real = om_mod._file_sha256
    monkeypatch.setattr(om_mod, "_file_sha256", lambda f: hashed.append(Path(f).name) or real(f))
    path = make_map().save_bundle(tmp_path / "toy.alm")
    hashed.clear()
    Orthomap.load_bundle(path)                       # the first load checks everything and stamps it
    assert sorted(hashed) == ["classes.npy", "dsm_m.npy", "nodata.npy", "rgb.npy"]
    hashed.clear()
    for _ in range(3):
        assert np.array_equal(Orthomap.load_bundle(path).rgb, make_map().rgb)
    assert hashed == []
    st = (path / "dsm_m.npy").stat()
    os.utime(path / "dsm_m.npy", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))      # touched, same bytes
    Orthomap.load_bundle(path)
    assert hashed == ["dsm_m.npy"]
    hashed.clear()
    _change_same_size(path / "rgb.npy", new_file=True)
    with pytest.raises(MapError, match="layer 'rgb' does not match"):
        Orthomap.load_bundle(path)
    assert hashed == ["rgb.npy"]


def test_a_change_within_a_timestamp_tick_of_the_check_is_still_caught(tmp_path):
    """A file changed so soon after its check that its (size, mtime, ctime, inode) read the same: the stamp is
    not trusted for files that recent, so the content is hashed."""
    path = make_map().save_bundle(tmp_path / "toy.alm")
    Orthomap.load_bundle(path)
    stamp = json.loads((path / om_mod.STAMP_FILE).read_text())
    _change_same_size(path / "classes.npy")
    st = (path / "classes.npy").stat()               # what a coarse clock would have left unchanged
    stamp["layers"]["classes"]["stat"] = [st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev]
    (path / om_mod.STAMP_FILE).write_text(json.dumps(stamp))
    with pytest.raises(MapError, match="layer 'classes' does not match"):
        Orthomap.load_bundle(path)


def test_a_bundle_written_before_checksums_loads_and_can_gain_them(tmp_path):
    path = make_map().save_bundle(tmp_path / "toy.alm")
    meta = json.loads((path / "meta.json").read_text())
    for info in meta["layers"].values():
        del info["sha256"]
    (path / "meta.json").write_text(json.dumps(meta))
    _change_same_size(path / "rgb.npy")                 # unchecked: nothing to compare with
    changed = np.asarray(Orthomap.load_bundle(path).rgb).copy()
    add_bundle_checksums(path)
    gained = json.loads((path / "meta.json").read_text())
    assert gained["bundle_id"] == meta["bundle_id"]
    assert gained["layers"]["rgb"]["sha256"] == hashlib.sha256((path / "rgb.npy").read_bytes()).hexdigest()
    assert np.array_equal(Orthomap.load_bundle(path).rgb, changed)
    _change_same_size(path / "rgb.npy")
    with pytest.raises(MapError, match="layer 'rgb' does not match"):
        Orthomap.load_bundle(path)


def test_a_read_only_bundle_is_checked_on_every_load(tmp_path, monkeypatch):
    path = make_map().save_bundle(tmp_path / "toy.alm")

    def cannot_write(*_a, **_k):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(om_mod, "atomic_write_bytes", cannot_write)
    for _ in range(2):
        assert np.array_equal(Orthomap.load_bundle(path).classes, make_map().classes)
    assert not (path / om_mod.STAMP_FILE).exists()
    _change_same_size(path / "nodata.npy")
    with pytest.raises(MapError, match="layer 'nodata' does not match"):
        Orthomap.load_bundle(path)
