"""Maps read by window (world/maps/raster.py), written as COGs (world/maps/cog.py), refused before decoding when
they would not fit in memory (world/maps/io.py), and flown over by window (the env reads each episode's window)."""

from __future__ import annotations

import hashlib
import pickle
from pathlib import Path

import cv2
import numpy as np
import pytest

from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.world.maps import raster
from aerial_loc_env.world.maps.cog import write_cog
from aerial_loc_env.world.maps.geo import AffineGeoref
from aerial_loc_env.world.maps.io import load_orthomap, open_map
from aerial_loc_env.world.maps.orthomap import Orthomap
from aerial_loc_env.world.maps.raster import BLOCK_PX, RasterMap

W, H = 1300, 1100   # 3 x 3 tiles of 512 px, the last ones partial


def _texture(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    small = rng.integers(20, 235, (h // 8 + 2, w // 8 + 2, 3), dtype=np.uint8)
    big = cv2.resize(small, (w + 16, h + 16), interpolation=cv2.INTER_CUBIC)[:h, :w]
    return np.ascontiguousarray(big)


def _map(nodata: bool = True, seed: int = 0) -> Orthomap:
    rgb = _texture(H, W, seed)
    nd = None
    if nodata:
        yy, xx = np.mgrid[:H, :W]
        nd = (xx + yy) < 300          # a wedge in the north-west corner
        nd |= (np.abs(xx - 900) < 20) & (np.abs(yy - 700) < 9)   # a hole inside
        rgb[nd] = 0
    g = AffineGeoref.north_up("EPSG:32633", 500_000.0, 5_200_000.0, 0.25, 0.25)
    return Orthomap(rgb, 0.25, 0.25, g, nodata=nd, name="test-map")


@pytest.fixture(scope="module")
def cogs(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("cogs")
    return {"deflate": write_cog(_map(), d / "deflate.tif", compress="deflate"),
            "jpeg": write_cog(_map(), d / "jpeg.tif", compress="jpeg"),
            "plain": write_cog(_map(nodata=False, seed=1), d / "plain.tif", compress="deflate")}


WINDOWS = [(0, 0, W, H), (0, 0, 1, 1), (511, 511, 2, 2), (100, 37, 700, 900), (1000, 600, 300, 500),
           (W - 1, H - 1, 1, 1), (512, 0, 512, 512)]


@pytest.mark.parametrize("kind", ["deflate", "jpeg"])
def test_windows_equal_the_whole_image_bit_for_bit(cogs, kind):
    whole = load_orthomap(cogs[kind])
    opened = open_map(cogs[kind], read="window")
    assert isinstance(opened, RasterMap) and isinstance(whole, Orthomap)
    assert (opened.width_px, opened.height_px) == (W, H)
    assert (opened.gsd_x_m, opened.gsd_y_m) == (whole.gsd_x_m, whole.gsd_y_m)
    assert opened.georef == whole.georef
    for u0, v0, w, h in WINDOWS:
        rgb, nd = opened.read(u0, v0, w, h)
        sl = np.s_[v0:v0 + h, u0:u0 + w]
        assert rgb.dtype == np.uint8 and rgb.shape == (h, w, 3)
        assert np.array_equal(rgb, whole.rgb[sl]), (u0, v0, w, h)
        assert np.array_equal(nd, whole.nodata[sl]), (u0, v0, w, h)
    win = opened.window(100, 37, 700, 900)
    crop = whole.crop(100, 37, 700, 900)
    assert np.array_equal(win.rgb, crop.rgb) and np.array_equal(win.nodata, crop.nodata)
    assert win.georef == crop.georef


def test_a_lossless_cog_keeps_the_pixels_and_the_nodata(cogs):
    src, back = _map(), load_orthomap(cogs["deflate"])
    assert np.array_equal(back.rgb, src.rgb)
    assert np.array_equal(back.nodata, src.nodata)      # the mask the COG carries, not a border search
    assert open_map(cogs["deflate"], read="window").n_overviews >= 1


def test_overview_levels_read_by_window(cogs):
    opened = open_map(cogs["deflate"], read="window")
    rgb, nd = opened.read(0, 0, (W + 1) // 2, (H + 1) // 2, level=1)
    assert rgb.shape == ((H + 1) // 2, (W + 1) // 2, 3)
    assert nd is not None and nd[0, 0] and not nd[-1, -1]
    with pytest.raises(MapError, match="level 9 does not exist"):
        opened.read(0, 0, 4, 4, level=9)
    with pytest.raises(MapError, match="not inside the 1300 x 1100 px map"):
        opened.read(1200, 0, 200, 10)


def test_striped_and_gdal_nodata_tiffs_read_by_window(tmp_path):
    import tifffile

    om = _map()
    rgb = om.rgb.copy()
    rgb[om.nodata] = 7
    keys = (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32633)
    path = tmp_path / "striped.tif"
    tifffile.imwrite(path, rgb, photometric="rgb", compression="deflate", rowsperstrip=64, extratags=[
        (33550, "d", 3, (0.25, 0.25, 0.0), True), (33922, "d", 6, (0, 0, 0, 500_000.0, 5_200_000.0, 0), True),
        (34735, "H", len(keys), keys, True), (42113, "s", 0, "7", True)])
    whole, opened = load_orthomap(path), open_map(path, read="window")
    for u0, v0, w, h in WINDOWS:
        got, nd = opened.read(u0, v0, w, h)
        assert np.array_equal(got, whole.rgb[v0:v0 + h, u0:u0 + w])
        assert np.array_equal(nd, whole.nodata[v0:v0 + h, u0:u0 + w])
    assert np.array_equal(whole.nodata, om.nodata)
    _check_blocks(opened.validity_blocks(), whole.nodata)


def _check_blocks(blocks: np.ndarray, nodata: np.ndarray) -> None:
    nb_h, nb_w = -(-nodata.shape[0] // BLOCK_PX), -(-nodata.shape[1] // BLOCK_PX)
    padded = np.zeros((nb_h * BLOCK_PX, nb_w * BLOCK_PX), bool)
    padded[:nodata.shape[0], :nodata.shape[1]] = nodata
    assert np.array_equal(blocks, padded.reshape(nb_h, BLOCK_PX, nb_w, BLOCK_PX).any(axis=(1, 3)))


def test_validity_blocks_from_the_mask(cogs):
    _check_blocks(open_map(cogs["deflate"], read="window").validity_blocks(), _map().nodata)
    assert open_map(cogs["plain"], read="window").validity_blocks() is None


def test_the_whole_layers_are_refused_with_the_size(cogs):
    opened = open_map(cogs["deflate"], read="window")
    for layer in ("rgb", "nodata"):
        with pytest.raises(MapError, match=r"1300 x 1100 px.*read by window.*map.read = 'whole'"):
            getattr(opened, layer)
    assert opened.dsm_m is None and opened.classes is None


def test_read_modes(cogs, tmp_path):
    assert isinstance(open_map(cogs["deflate"]), Orthomap)           # auto: small maps are loaded whole
    assert isinstance(open_map(cogs["deflate"], read="whole"), Orthomap)
    png = tmp_path / "map.png"
    cv2.imwrite(str(png), _texture(64, 64, 3))
    with pytest.raises(MapError, match="read='window' needs a TIFF file.*aerial-loc cog"):
        open_map(png, read="window", gsd_m=0.5)
    with pytest.raises(MapError, match="read='sometimes'"):
        open_map(png, read="sometimes")
    with pytest.raises(MapError, match="nodata='border_black' needs the whole image.*aerial-loc cog"):
        open_map(cogs["deflate"], read="window", nodata="border_black")


def test_auto_opens_large_tiled_files_by_window(cogs, monkeypatch):
    from aerial_loc_env.world.maps import io

    monkeypatch.setattr(io, "WINDOW_MIN_BYTES", 1000)
    assert isinstance(open_map(cogs["deflate"]), RasterMap)


def test_pickles_as_its_path(cogs):
    opened = open_map(cogs["jpeg"], read="window")
    back = pickle.loads(pickle.dumps(opened))
    assert np.array_equal(back.read(10, 20, 30, 40)[0], opened.read(10, 20, 30, 40)[0])


def test_the_file_handle_closes_with_the_map_without_a_warning(cogs):
    """A map read by window holds its file open while it lives: ``close`` releases it (a later read opens it again)
    and a map dropped without ``close`` releases it too, never left to the garbage collector's ResourceWarning."""
    import gc
    import os
    import warnings

    def open_fds() -> int:
        return len(os.listdir("/proc/self/fd"))

    gc.collect()
    before = open_fds()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        opened = open_map(cogs["deflate"], read="window")
        first = opened.read(10, 20, 30, 40)[0]
        assert open_fds() == before + 1
        opened.close()
        assert open_fds() == before
        assert np.array_equal(opened.read(10, 20, 30, 40)[0], first)     # opened again
        assert open_fds() == before + 1
        del opened
        gc.collect()
        assert open_fds() == before
    assert [str(w.message) for w in caught if issubclass(w.category, ResourceWarning)] == []


def test_a_map_larger_than_memory_is_refused_before_decoding(tmp_path, monkeypatch):
    png = tmp_path / "big.png"
    cv2.imwrite(str(png), _texture(300, 400, 4))
    monkeypatch.setattr(raster, "available_memory_bytes", lambda: 100_000)

    def no_decode(*args, **kwargs):
        raise AssertionError("decoded before the memory check")

    monkeypatch.setattr(cv2, "imdecode", no_decode)
    with pytest.raises(MapError, match=r"big.png: the image: 400 x 300 px; reading it needs about .* MB of memory, "
                                       r"more than the 0.1 MB available\. Convert it to a COG.*aerial-loc cog"):
        load_orthomap(png, gsd_m=0.5)


def test_a_tiled_map_larger_than_memory_points_to_reading_by_window(cogs, monkeypatch):
    monkeypatch.setattr(raster, "available_memory_bytes", lambda: 100_000)
    with pytest.raises(MapError, match=r"1300 x 1100 px.*read='window'"):
        open_map(cogs["deflate"], read="whole")
    assert isinstance(open_map(cogs["deflate"], read="window"), RasterMap)   # by window it opens


def test_write_cog_never_overwrites(cogs, tmp_path):
    with pytest.raises(MapError, match="already exists.*overwrite"):
        write_cog(_map(), cogs["deflate"])
    with pytest.raises(ConfigError, match="compress='gif'"):
        write_cog(_map(), tmp_path / "x.tif", compress="gif")
    assert not (tmp_path / "x.tif").exists() and not list(tmp_path.glob(".x.tif.tmp-*"))


def test_write_cog_without_rasterio_names_the_extra(tmp_path, monkeypatch):
    import sys

    from aerial_loc_env.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, "rasterio", None)     # import rasterio then raises ImportError
    with pytest.raises(MissingExtraError, match=r"Writing a COG.*pip install 'aerial-loc-env\[geo\]'"):
        write_cog(_map(), tmp_path / "x.tif")
    assert not (tmp_path / "x.tif").exists()


def test_cog_command(tmp_path, capsys):
    from aerial_loc_env.cli import main

    png = tmp_path / "in.png"
    rgb = _texture(200, 300, 5)
    rgb[:40, :40] = 0                      # a black border wedge: the loader's no-data, kept as the mask
    cv2.imwrite(str(png), rgb[..., ::-1])
    out = tmp_path / "out.tif"
    assert main(["cog", str(png), str(out), "--gsd-m", "0.5", "--compress", "deflate"]) == 0
    assert "300 x 200 px" in capsys.readouterr().out
    back, src = load_orthomap(out, gsd_m=0.5), load_orthomap(png, gsd_m=0.5)
    assert np.array_equal(back.rgb, src.rgb) and np.array_equal(back.nodata, src.nodata)
    assert main(["cog", str(png), str(out), "--gsd-m", "0.5"]) == 2
    assert "already exists" in capsys.readouterr().err


# --- the env over a map read by window -----------------------------------------------------------------------

def _frames(path: Path, read: str, seeds=(0, 3), steps: int = 6) -> list[np.ndarray]:
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401

    env = gym.make("AerialLoc/RealMap-v2", path=str(path), read=read, altitude_m=40.0, min_leg_m=20.0)
    out = []
    for seed in seeds:
        obs, info = env.reset(seed=seed)
        out += [obs["image"], info["true_pose"]]
        for _ in range(steps):
            obs, _, _, _, info = env.step(np.zeros(2, np.float32))
            out += [obs["image"], info["true_pose"]]
    return out


def test_env_by_window_flies_the_whole_maps_episodes(cogs):
    """Same tracks and poses; the frames equal the whole map's but where OpenCV's warp rounds a coordinate to its
    1/32 px grid differently (the window's affine is the map's shifted by an integer, its row offsets summed at
    another magnitude): a few pixels a frame, by at most 2 levels."""
    by_window, whole = _frames(cogs["plain"], "window"), _frames(cogs["plain"], "whole")
    assert len(by_window) == len(whole)
    for a, b in zip(by_window[1::2], whole[1::2], strict=True):
        assert np.array_equal(a, b)                       # the true poses
    for a, b in zip(by_window[::2], whole[::2], strict=True):
        diff = np.abs(a.astype(np.int16) - b)
        assert diff.max() <= 2 and np.count_nonzero(diff) <= a.size // 1000


def test_env_by_window_flies_over_valid_data_and_renders_overviews(cogs):
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401

    env = gym.make("AerialLoc/RealMap-v2", path=str(cogs["jpeg"]), read="window", altitude_m=40.0,
                   min_leg_m=20.0, render_mode="rgb_array")
    u = env.unwrapped
    assert u.world.windowed and u._renderer is None
    for seed in range(4):
        env.reset(seed=seed)         # strict rendering: a footprint off the window or on no-data would raise
        u0, v0, w, h = u._window_px
        assert w < W or h < H
        for _ in range(5):
            env.step(np.zeros(2, np.float32))
        assert env.render().shape == (512, 512, 3)
    assert isinstance(pickle.loads(pickle.dumps(u)).orthomap, RasterMap)


def test_env_refuses_an_epoch_on_a_map_read_by_window(cogs):
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401

    with pytest.raises(ConfigError, match=r"\[epoch\].*read by window.*map.read = 'whole'"):
        gym.make("AerialLoc/RealMap-v2", path=str(cogs["jpeg"]), read="window", epoch={"car_turnover": 0.5})


# --- RealMap on the real tiles: the frames they always had ---------------------------------------------------

def test_realmap_frames_on_the_real_tiles_unchanged(shared_data):
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401

    want = {"manila_pasig_river.tif": "f70fc0b928d46ba9", "valencia_orchard.tif": "4df4c53aab3b5ecf"}
    for tile, digest in want.items():
        env = gym.make("AerialLoc/RealMap-v2", path=str(shared_data / tile))
        assert isinstance(env.unwrapped.orthomap, Orthomap)
        h = hashlib.sha256()
        for seed in (0, 1):
            obs, info = env.reset(seed=seed)
            h.update(obs["image"].tobytes())
            h.update(np.asarray(info["true_pose"]).tobytes())
            for _ in range(12):
                obs, r, _, _, _ = env.step(np.zeros(2, np.float32))
                h.update(obs["image"].tobytes())
                h.update(np.float64(r).tobytes())
        assert h.hexdigest()[:16] == digest, tile


def test_env_refuses_an_episode_window_larger_than_memory_at_reset(cogs, monkeypatch):
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401

    env = gym.make("AerialLoc/RealMap-v2", path=str(cogs["jpeg"]), read="window", altitude_m=40.0, min_leg_m=20.0)
    monkeypatch.setattr(raster, "available_memory_bytes", lambda: 1000)
    with pytest.raises(MapError, match=r"the episode's window of map 'jpeg': \d+ x \d+ px; reading it needs about "
                                       r".* more than the 0.0 MB available\. Shorten the flight \(flight.duration_s"):
        env.reset(seed=0)
