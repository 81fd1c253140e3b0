"""The renderer's per-frame geometry and tone table in scalar form give the library's numpy results bit for bit."""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from aerial_loc_env.sensors.camera import CameraModel, Pose, apply_affine
from aerial_loc_env.sensors.perspective import footprint_px
from aerial_loc_env.sensors.render import CameraRenderer, Photometry, gamma_lut, photometry_draws, tone_lut


def _map(gsd_x: float, gsd_y: float) -> SimpleNamespace:
    rgb = np.zeros((300, 500, 3), np.uint8)
    return SimpleNamespace(rgb=rgb, gsd_x_m=gsd_x, gsd_y_m=gsd_y, height_px=300, width_px=500, nodata=None)


@pytest.mark.parametrize("camera", [CameraModel(), CameraModel(width_px=321, height_px=203, hfov_deg=57.3,
                                                                 pixel_aspect=1.137)])
@pytest.mark.parametrize("gsd", [(0.25, 0.25), (0.3137, 0.2719), (np.float32(0.41), np.float32(0.23))])
def test_pose_affine_and_corners_equal_camera_to_map_bit_for_bit(camera, gsd):
    renderer = CameraRenderer(_map(*gsd), camera)
    rng = np.random.default_rng(5)
    for x, y, yaw, alt in zip(rng.uniform(-50, 200, 300), rng.uniform(-50, 200, 300), rng.uniform(-7, 7, 300),
                              rng.uniform(20, 900, 300), strict=True):
        pose = Pose(float(x), float(y), float(yaw), float(alt))
        expected = camera.camera_to_map(renderer.orthomap, *pose)
        got = camera.project_pose(renderer.orthomap, pose)
        assert got.dtype == expected.dtype and got.tobytes() == expected.tobytes()
        # the renderer's, with the terms it keeps per altitude: a new altitude, then the same one again
        for again in (pose, Pose(pose.y_m, pose.x_m, -pose.yaw_rad, pose.altitude_m)):
            assert renderer.camera_to_map(again).tobytes() == camera.camera_to_map(renderer.orthomap, *again).tobytes()
        corners = footprint_px(got, camera)     # the renderer's corners of a frame (perspective_kernels.map_corners)
        assert corners.tobytes() == np.ascontiguousarray(apply_affine(expected, camera.corners_px())).tobytes()


def test_photometry_draws_are_numpys_arithmetic_on_the_same_draws():
    """The frame's gamma and gains in Python floats equal the NumPy expression they replaced (the same draws in the
    same order, ``portable.exp``), bit for bit, and leave the generator where it left it."""
    from aerial_loc_env import portable

    for seed in range(600):
        with_gamma, with_gains = seed % 3 != 1, seed % 3 != 2   # both effects, the gains alone, the curve alone
        p = Photometry(gain=float(1.0 + seed % 5) if with_gains else 1.0, exposure_std=0.5 if with_gains else 0.0,
                       white_balance_std=0.2 if with_gains else 0.0, gamma_std=0.3 if with_gamma else 0.0)
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        gamma, gains = photometry_draws(p, a)
        ref_gamma = p.gamma * math.exp(p.gamma_std * b.standard_normal()) if with_gamma else None
        assert gamma == ref_gamma
        if with_gains:
            ref_gains = p.gain * portable.exp(p.exposure_std * b.standard_normal() + p.white_balance_std
                                              * b.standard_normal(3))
            assert gains.dtype == np.float64 and gains.tobytes() == ref_gains.tobytes()
        else:
            assert gains is None
        assert a.standard_normal() == b.standard_normal()
    assert photometry_draws(Photometry.ideal(), np.random.default_rng(0)) == (None, None)


def test_tone_lut_is_the_opencv_operations_over_all_levels():
    levels = np.repeat(np.arange(256, dtype=np.uint8)[None, :, None], 3, axis=2)
    rng = np.random.default_rng(2)
    # (the gains by compiled arithmetic, not OpenCV: many draws, gains far below and above 1, saturating, and the
    # renderer's own draws)
    draws = [photometry_draws(Photometry(exposure_std=0.5, white_balance_std=0.2, gamma_std=0.3), rng)
             for _ in range(300)]
    for gamma, gains in [(None, None), (0.83, None), (None, np.array([0.7, 1.0, 1.6])),
                         *[(float(g), rng.uniform(0.5, 2.5, 3)) for g in rng.uniform(0.5, 2.0, 20)],
                         *[(None, rng.uniform(0.0, 300.0, 3)) for _ in range(20)], *draws]:
        ref = levels.copy()
        if gamma is not None:
            cv2.LUT(ref, gamma_lut(gamma), dst=ref)
        if gains is not None:
            cv2.transform(ref, np.diag(gains).astype(np.float32), dst=ref)
        got = tone_lut(gamma, gains)
        assert got.flags.c_contiguous and got.shape == (3, 256)
        np.testing.assert_array_equal(got, ref[0].T)
