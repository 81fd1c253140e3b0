"""The integer photometry of ``CameraRenderer`` against the float arithmetic it replaced (kept here as the reference).

Shading (three 1-channel LUTs merged instead of one 3-channel LUT), gamma (uint8 LUT) and gains (``cv2.transform``)
are the same operations on the same bytes: bit-identical. Vignetting and noise changed arithmetic:

- reference: ``y = round(h * v + sigma(h) * z)`` in float32 (h the uint8 level after gains, v the vignetting gain,
  z the float32 normal from the bank), rounded once;
- now: ``y = sat(round(h * V / 255) + round(S(h) * Z / 2**19))`` with ``V = round(255 v)`` (uint8),
  ``S = round(256 sigma)`` and ``Z = round(2048 z)`` (int16).

Error budget against the exact value ``h v + sigma z``: the uint8 vignetting gain is off by <= 0.5 / 255, so
``h V / 255`` by <= 0.5 DN, and its rounding adds 0.5; the noise term is off by <= |z| / 512 (sigma) +
sigma / 4096 (z), i.e. < 0.04 DN for |z| < 16 and sigma <= 71, and its rounding adds 0.5. The reference rounds the
exact value once (0.5). So |now - reference| < 0.5 + 0.5 + 0.04 + 0.5 + 0.5 = 2.04, and both are integers:
**at most 2 grey levels**; without vignetting, < 0.5 + 0.04 + 0.5 = 1.04: **at most 1 grey level**.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from aerial_loc_env.sensors.camera import CameraModel, Pose
from aerial_loc_env.sensors.render import CameraRenderer, Photometry, _motion_kernel
from aerial_loc_env.world.shadows import ShadowGrid, _shadow_gains, apply_shading

CAMERA = CameraModel(width_px=120, height_px=80)       # 0.25 m/px at 40 m
POSE = Pose(50.0, 50.0, 0.3, 40.0)
MARGIN_PX = 97                                           # the renderer's noise bank margin


def _scene(seed: int = 0):
    """A textured 100 m map with a soft shadow grid (factor 2) holding 0, 1 and every level in between."""
    rng = np.random.default_rng(seed)
    rgb = cv2.resize(rng.integers(0, 256, (50, 50, 3), dtype=np.uint8), (400, 400), interpolation=cv2.INTER_CUBIC)
    occ = cv2.resize(rng.random((20, 20), dtype=np.float32), (200, 200), interpolation=cv2.INTER_LINEAR)
    grid = ShadowGrid(np.clip(2.0 * occ - 0.5, 0.0, 1.0).astype(np.float32), 0.5, 0.5, 2)
    orthomap = SimpleNamespace(rgb=rgb, gsd_x_m=0.25, gsd_y_m=0.25, height_px=400, width_px=400, nodata=None,
                               name="photometry-test")
    return orthomap, grid


def _reference_shading(rgb, occlusion, strength, shadow_ratio=0.15, sky_tint_rgb=(0.55, 0.65, 0.85), gamma=2.2):
    """apply_shading as it was: the grey occlusion to RGB, one 3-channel LUT, one multiply."""
    occ = occlusion if occlusion.dtype == np.uint8 else cv2.convertScaleAbs(occlusion, alpha=255.0)
    q = np.arange(256, dtype=np.float64) / 255.0
    gains = _shadow_gains(strength, shadow_ratio, sky_tint_rgb)
    lin = 1.0 - q[:, None] * (1.0 - gains[None, :])
    lut = np.clip(np.rint(255.0 * lin ** (1.0 / gamma)), 0, 255).astype(np.uint8).reshape(256, 1, 3)
    return cv2.multiply(rgb, cv2.LUT(cv2.cvtColor(occ, cv2.COLOR_GRAY2RGB), lut), scale=1.0 / 255.0)


def _reference_photometry(image, rng, p: Photometry, camera: CameraModel, bank, blur_px: float):
    """The float32 photometry as it was (same draws in the same order, the float32 bank)."""
    if blur_px >= 1.0:
        image = cv2.filter2D(image, -1, _motion_kernel(blur_px), borderType=cv2.BORDER_REPLICATE)
    if p.gamma != 1.0 or p.gamma_std > 0.0:
        gamma = p.gamma * math.exp(p.gamma_std * rng.standard_normal())
        image = cv2.LUT(image, np.rint(255.0 * (np.arange(256) / 255.0) ** gamma).astype(np.uint8))
    if p.gain != 1.0 or p.exposure_std > 0.0 or p.white_balance_std > 0.0:
        gains = p.gain * np.exp(p.exposure_std * rng.standard_normal() + p.white_balance_std
                                * rng.standard_normal(3))
        image = cv2.transform(image, np.diag(gains).astype(np.float32))
    vignette = CameraRenderer._vignetting_map(camera, p.vignetting)
    if not p.has_noise and vignette is None:
        return image
    signal = image if vignette is None else cv2.multiply(image, vignette, dtype=cv2.CV_32F)
    if not p.has_noise:
        return cv2.convertScaleAbs(signal)
    h, w = image.shape[:2]
    dy, dx = rng.integers(0, MARGIN_PX + 1, size=2)
    sigma_lut = np.sqrt(p.read_noise_dn ** 2 + p.shot_noise_gain * np.arange(256, dtype=np.float32))
    sigma = cv2.LUT(image.reshape(h, w * 3), sigma_lut.astype(np.float32)).reshape(h, w, 3)
    return cv2.add(signal, cv2.multiply(sigma, bank[dy:dy + h, dx:dx + w]), dtype=cv2.CV_8U)


def _both(p: Photometry, seed: int, speed_mps: float = 0.0, strength: float = 0.9):
    orthomap, grid = _scene()
    renderer = CameraRenderer(orthomap, CAMERA, p, noise_seed=seed)
    frame = renderer.render(POSE, np.random.default_rng(seed + 1), grid, {"strength": strength},
                            speed_mps=speed_mps)
    bank = np.random.default_rng(seed).standard_normal((CAMERA.height_px + MARGIN_PX,
                                                        CAMERA.width_px + MARGIN_PX, 3), dtype=np.float32)
    occ = renderer.occlusion_in_camera(grid, POSE)
    shaded = _reference_shading(renderer.database_patch(POSE), occ, strength)
    blur_px = speed_mps * p.exposure_time_s / CAMERA.gsd_m(POSE.altitude_m)
    ref = _reference_photometry(shaded, np.random.default_rng(seed + 1), p, CAMERA, bank, blur_px)
    np.testing.assert_array_equal(frame.occlusion, occ)
    return frame.image.astype(int), ref.astype(int)


@pytest.mark.parametrize("speed_mps", [0.0, 200.0])    # 200 m/s: a 1.6 px motion blur between shading and gamma
def test_shading_gamma_and_gains_are_bit_identical(speed_mps):
    p = Photometry(read_noise_dn=0.0, shot_noise_gain=0.0, vignetting=0.0, gamma_std=0.1, exposure_std=0.2)
    for seed in range(3):
        now, ref = _both(p, seed, speed_mps)
        np.testing.assert_array_equal(now, ref)
        assert 0 < now.mean() < 255


@pytest.mark.parametrize("vignetting, bound_dn", [(0.0, 1), (0.5, 2), (1.0, 2)])
def test_vignetting_and_integer_noise_within_the_derived_bound(vignetting, bound_dn):
    p = Photometry(vignetting=vignetting, read_noise_dn=3.0, shot_noise_gain=0.5)
    for seed in range(3):
        now, ref = _both(p, seed)
        diff = np.abs(now - ref)
        assert diff.max() <= bound_dn
        # the two agree on the noise itself: the same draws, not merely the same statistics
        assert np.corrcoef(now.ravel(), ref.ravel())[0, 1] > 0.999


def test_vignetting_without_noise_within_one_level():
    """No noise: the reference rounds h v once; now h V / 255 with |V / 255 - v| <= 0.5 / 255: < 1 DN apart."""
    now, ref = _both(Photometry(read_noise_dn=0.0, shot_noise_gain=0.0, vignetting=1.0), 4)
    assert np.abs(now - ref).max() <= 1


def test_same_seed_same_frame_bit_for_bit():
    orthomap, grid = _scene()
    frames = []
    for _ in range(2):
        renderer = CameraRenderer(orthomap, CAMERA, Photometry(), noise_seed=11)
        rng = np.random.default_rng(12)
        frames.append([renderer.render(POSE, rng, grid, {"strength": 0.8}).image for _ in range(3)])
    for a, b in zip(*frames, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(frames[0][0], frames[0][1])      # a new noise offset and draws per frame


@pytest.mark.parametrize("occ_dtype", [np.float32, np.uint8])
def test_apply_shading_is_bit_identical_to_the_three_channel_lut(occ_dtype):
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    occ = rng.random((64, 96), dtype=np.float32)
    occ = occ if occ_dtype == np.float32 else (occ * 255).astype(np.uint8)
    for strength, kwargs in [(0.9, {}), (0.4, {"shadow_ratio": 0.3, "sky_tint_rgb": [0.6, 0.7, 0.9], "gamma": 1.8})]:
        expected = _reference_shading(rgb, occ, strength, **kwargs)
        np.testing.assert_array_equal(apply_shading(rgb, occ, strength, **kwargs), expected)
        out = np.empty_like(rgb)
        assert apply_shading(rgb, occ, strength, out=out, **kwargs) is out
        np.testing.assert_array_equal(out, expected)
