"""The map-acquisition model (world/acquisition.py): identity when off, lean geometry, georeference bias, sensor."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.world.acquisition import AcquisitionConfig, acquire, acquire_layer, lean_buildings

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
