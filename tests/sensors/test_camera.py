"""Camera geometry: footprint vs altitude/fov, yaw convention, eq. (3) transforms and their inverses."""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.sensors.camera import CameraModel, Pose, apply_affine, invert_affine, world_to_map_affine


@dataclass(frozen=True)
class GridStandIn:
    """The part of the Orthomap contract the camera uses (pixel size and height)."""

    gsd_x_m: float = 0.25
    gsd_y_m: float = 0.25
    height_px: int = 2000
    width_px: int = 3000


def test_default_camera_is_the_papers_crop():
    cam = CameraModel()
    assert (cam.width_px, cam.height_px) == (600, 400)
    assert cam.hfov_deg == pytest.approx(41.11, abs=0.005)
    assert cam.gsd_m(200.0) == pytest.approx(0.25, rel=1e-12)
    assert cam.footprint_m(200.0) == pytest.approx((150.0, 100.0), rel=1e-12)


@pytest.mark.parametrize("hfov_deg", [20.0, 41.11, 90.0])
@pytest.mark.parametrize("altitude_m", [50.0, 200.0, 731.0])
def test_footprint_scales_with_altitude_and_fov(hfov_deg, altitude_m):
    cam = CameraModel(width_px=320, height_px=240, hfov_deg=hfov_deg)
    width_m, length_m = cam.footprint_m(altitude_m)
    expected_w = 2.0 * altitude_m * math.tan(math.radians(hfov_deg) / 2.0)
    assert width_m == pytest.approx(expected_w, rel=1e-12)
    assert length_m == pytest.approx(expected_w * 240 / 320, rel=1e-12)
    corners = cam.footprint_corners_m(10.0, -5.0, 0.7, altitude_m)
    sides = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    assert sides == pytest.approx([expected_w, length_m, expected_w, length_m], rel=1e-9)
    assert corners.mean(axis=0) == pytest.approx([10.0, -5.0])


def test_yaw_convention_top_is_heading_and_north_is_left_when_flying_east():
    cam = CameraModel(width_px=60, height_px=40)
    a = cam.camera_to_world(100.0, 200.0, 0.0, 100.0)  # nose east
    top_centre, left_centre = apply_affine(a, np.array([[29.5, 0.0], [0.0, 19.5]]))
    assert top_centre[0] > 100.0 and top_centre[1] == pytest.approx(200.0)  # top of image = east
    assert left_centre[1] > 200.0 and left_centre[0] == pytest.approx(100.0)  # left of image = north
    a_north = cam.camera_to_world(100.0, 200.0, math.pi / 2, 100.0)  # nose north
    top_n, left_n = apply_affine(a_north, np.array([[29.5, 0.0], [0.0, 19.5]]))
    assert top_n[1] > 200.0 and top_n[0] == pytest.approx(100.0)
    assert left_n[0] < 100.0 and left_n[1] == pytest.approx(200.0)  # left = west


def test_camera_to_map_is_s_r_plus_t_and_centre_lands_on_the_vehicle():
    cam, grid = CameraModel(), GridStandIn(gsd_x_m=0.5, gsd_y_m=0.25)
    yaw = np.array([-2.0, 0.0, 0.4, 3.0])
    a = cam.camera_to_map(grid, [100.0, 150.0, 200.0, 250.0], 60.0, yaw, 120.0)
    s, r = cam.scale_rotation(grid, yaw, 120.0)
    assert np.allclose(a[..., :2], s @ r)
    assert np.allclose(r @ np.swapaxes(r, -1, -2), np.eye(2))  # R is a rotation
    assert np.allclose(np.linalg.det(r), 1.0)
    centre = apply_affine(a, np.array([cam.center_px]))[:, 0]
    # world -> map pixel: u = x / gsd_x - 0.5, v = H - 0.5 - y / gsd_y
    assert np.allclose(centre[:, 0], np.array([100.0, 150.0, 200.0, 250.0]) / 0.5 - 0.5)
    assert np.allclose(centre[:, 1], grid.height_px - 0.5 - 60.0 / 0.25)


def test_inverse_and_project_pixels_agree_with_the_affine():
    cam, grid = CameraModel(), GridStandIn()
    rng = np.random.default_rng(3)
    n = 7
    x, y = rng.uniform(100, 600, n), rng.uniform(100, 400, n)
    yaw, alt = rng.uniform(-math.pi, math.pi, n), rng.uniform(80, 300, n)
    uv = rng.uniform(0, 600, (11, 2))
    mp = cam.project_pixels(grid, uv, x, y, yaw, alt)
    assert mp.shape == (n, 11, 2)
    back = np.stack([apply_affine(m, mp[i]) for i, m in enumerate(cam.map_to_camera(grid, x, y, yaw, alt))])
    assert np.allclose(back, uv[None], atol=1e-9)
    a = cam.camera_to_map(grid, x, y, yaw, alt)
    assert np.allclose(invert_affine(invert_affine(a)), a)
    single = cam.project_pixels(grid, uv, x[2], y[2], yaw[2], alt[2])
    assert single.shape == (1, 11, 2) and np.allclose(single[0], mp[2])
    assert np.allclose(cam.project_pose(grid, Pose(x[2], y[2], yaw[2], alt[2])), a[2])


def test_resized_keeps_the_footprint():
    cam = CameraModel()
    for w, h in [(150, 100), (224, 224), (64, 48)]:
        small = cam.resized(w, h)
        assert small.footprint_m(173.0) == pytest.approx(cam.footprint_m(173.0), rel=1e-12)
        corners = small.footprint_corners_m(5, 6, 1.0, 173.0)
        assert np.allclose(corners, cam.footprint_corners_m(5, 6, 1.0, 173.0))
        s, r = small.scale_rotation(GridStandIn(), 1.0, 173.0)
        lin = small.camera_to_map(GridStandIn(), 5, 6, 1.0, 173.0)[:, :2]
        assert np.allclose(s @ r @ np.diag([1.0, small.pixel_aspect]), lin)


@pytest.mark.parametrize("override", [{"width_px": 0}, {"hfov_deg": 180.0}, {"hfov_deg": -3}, {"bogus": 1}])
def test_bad_configs_are_rejected_with_the_field_name(override):
    with pytest.raises(ConfigError, match=next(iter(override))):
        build_config(CameraModel, override, where="camera.toml")


def test_bad_altitude_is_rejected():
    with pytest.raises(ConfigError, match="altitude_m"):
        CameraModel().gsd_m(0.0)
    with pytest.raises(ConfigError, match="altitude_m"):
        CameraModel().camera_to_world(0, 0, 0, [100.0, float("nan")])


def _camera_to_world_reference(cam: CameraModel, x_m, y_m, yaw_rad, altitude_m) -> np.ndarray:
    """The replaced entry: every argument broadcast to a float64 array first (the altitude too, so the pixel
    size is an array) before the per-element arithmetic, which is unchanged."""
    return cam.camera_to_world(*np.broadcast_arrays(*(np.asarray(a, dtype=np.float64)
                                                      for a in (x_m, y_m, yaw_rad, altitude_m))))


def _camera_to_map_reference(cam: CameraModel, grid, *pose) -> np.ndarray:
    to_world = _camera_to_world_reference(cam, *pose)
    hom = np.zeros(to_world.shape[:-2] + (3, 3))
    hom[..., :2, :] = to_world
    hom[..., 2, 2] = 1.0
    return world_to_map_affine(grid) @ hom


@pytest.mark.parametrize("gsd_xy", [(0.25, 0.25), (0.3, 0.21), (1.0, 0.5)])
def test_camera_to_map_is_the_composed_affine_bit_for_bit(gsd_xy):
    cam = CameraModel(width_px=640, height_px=360, hfov_deg=50.0, pixel_aspect=1.1)
    grid = SimpleNamespace(gsd_x_m=gsd_xy[0], gsd_y_m=gsd_xy[1], height_px=1234)
    g = np.random.default_rng(7)
    n = 5000
    x, y, yaw = g.uniform(-50, 900, n), g.uniform(-50, 900, n), g.uniform(-4, 4, n)
    alts = g.uniform(50, 400, n)
    cases = [(x, y, yaw, 200.0), (x, y, yaw, 173), (x, y, yaw, np.float64(88.8)), (x, y, yaw, alts),
             (x[0], y[0], yaw[0], 150.0), (x[:7], 42.0, yaw[:7], 120.0), (1.0, 2.0, yaw[:3], alts[:3]),
             (x.reshape(50, 100), y.reshape(50, 100), yaw.reshape(50, 100), np.array(210.0))]
    for pose in cases:
        ref = _camera_to_map_reference(cam, grid, *pose)
        out = cam.camera_to_map(grid, *pose)
        assert out.shape == ref.shape
        np.testing.assert_array_equal(out, ref)
        np.testing.assert_array_equal(cam.camera_to_world(*pose), _camera_to_world_reference(cam, *pose))


def test_gsd_of_a_plain_number_equals_the_array_path_and_bad_altitudes_still_fail():
    cam = CameraModel()
    for alt in (200, 200.0, 57.3, np.float64(123.4), 1e-3, 19999.9):
        assert cam.gsd_m(alt) == float(cam.gsd_m(np.array([alt]))[0])
        assert isinstance(cam.gsd_m(alt), float)
    for bad in (0.0, -5.0, float("nan"), float("inf"), 0):
        with pytest.raises(ConfigError, match="altitude_m"):
            cam.gsd_m(bad)
        with pytest.raises(ConfigError, match="altitude_m"):
            cam.camera_to_map(SimpleNamespace(gsd_x_m=1.0, gsd_y_m=1.0, height_px=10), 0.0, 0.0, 0.0, bad)
