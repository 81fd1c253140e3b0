"""The compiled finishing pass (``sensors.render_kernels.finish``, and ``warp_finish`` with the baked box's warp)
against the OpenCV passes it replaced, bit for bit.

The reference is the renderer as it was: a subclass whose ``_finish`` runs the old OpenCV/NumPy passes (the baked
box's ``cv2.warpAffine``, RGB drop,
alpha threshold and count, or the float occlusion quantized, shaded and thresholded; motion blur; gamma LUT; gains
``cv2.transform``; the int16 sigma LUT times the noise bank; vignetting multiply; saturating add), with the same
random draws in the same order. Everything upstream (the warps, the views, the bake) is shared, so any difference
is the kernel's. The kernel reproduces each pass's arithmetic exactly (see its module docstring), so the frames,
masks and shadow fractions must be equal, not close.
"""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numba
import numpy as np
import pytest
from perspective_reference import facade_gains_numpy

from aerial_loc_env.sensors import render as render_mod
from aerial_loc_env.sensors import render_kernels as fk
from aerial_loc_env.sensors.camera import CameraModel, Pose
from aerial_loc_env.sensors.perspective import PerspectiveConfig
from aerial_loc_env.sensors.render import CameraRenderer, Photometry, _motion_kernel, gamma_lut, photometry_draws
from aerial_loc_env.world.shadows import ShadowGrid, shade, shading_lut

CAMERA = CameraModel(width_px=120, height_px=80)        # 0.25 m/px at 40 m: map level 0
POSES = [Pose(50.0, 50.0, 0.3, 40.0), Pose(47.0, 55.0, -2.1, 40.0)]
HIGH = Pose(50.0, 50.0, 0.3, 75.0)                        # 0.47 m/px: pyramid level 1 (never baked)
SHADING = {"strength": 0.9}
SETTINGS = {
    "ideal": Photometry.ideal(),
    "defaults": Photometry(),
    "strong noise": Photometry(read_noise_dn=20.0, shot_noise_gain=5.0, gamma_std=0.2),
    "no vignetting": Photometry(vignetting=0.0),
    "vignetting only": Photometry(read_noise_dn=0.0, shot_noise_gain=0.0, vignetting=1.0),
    "noise only": Photometry(vignetting=0.0, exposure_std=0.0, white_balance_std=0.0, gamma_std=0.0),
    "saturating gains": Photometry(gain=2.5, exposure_std=0.5, white_balance_std=0.3, gamma=0.6),
    "dark gains": Photometry(gain=0.3, gamma=2.0, read_noise_dn=8.0),
}


class _OpenCVRenderer(CameraRenderer):
    """The renderer with its finishing pass as the OpenCV passes it replaced (the reference); ``masks``: the
    shadow masks it made the old way (a threshold of the alpha or of the float occlusion), newest last."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.masks: list[np.ndarray] = []
        self.facades: list[int] = []      # the facade pixels of each view sampled from the baked box

    def _finish(self, src, occ, shading_params, rng, speed_mps, pose, mid):
        facades = None
        if isinstance(src, render_mod._BoxWarp):
            src = _warp_box(src.box, src.matrix, src.width_px, src.height_px)
        elif isinstance(src, render_mod._ViewWarp):    # the view's maps, cv2.remap, the facades as NumPy did
            view = src.view.view_of(src.plan)
            facades = (np.zeros(0, np.int64), np.zeros(0)) if view.facade is None else \
                (view.facade, facade_gains_numpy(src.view, view, src.sun_deg, src.gamma))
            src = _remap_box(src.box, view.x, view.y)
        elif isinstance(src, render_mod._LevelWarp):    # the level's warp, then the grid's (replicated border)
            occ = cv2.warpAffine(src.grid, src.grid_matrix, (src.width_px, src.height_px),
                                 flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REPLICATE)
            src = _warp_box(src.box, src.matrix, src.width_px, src.height_px)
        h, w, cn = src.shape
        image = cv2.cvtColor(src, cv2.COLOR_RGBA2RGB) if cn == 4 else src.copy()
        if facades is not None:
            self.facades.append(facades[0].size)
            _shade_pixels(image, *facades)
        alpha = render_mod._NO_VIG
        if occ is render_mod._BAKED_ALPHA:
            alpha = cv2.extractChannel(src, 3)
            mask = cv2.threshold(alpha, 127, 1, cv2.THRESH_BINARY)[1]
        elif occ is None:
            mask = np.zeros((h, w), np.uint8)
        else:
            lut = render_mod._shading_lut(shading_params)
            shade(image, cv2.convertScaleAbs(occ, alpha=255.0), lut, out=image)
            mask = (occ >= 0.5).view(np.uint8)
        for step in mid:
            image = step(image)
        p, camera = self.photometry, self.camera
        blur_px = speed_mps * p.exposure_time_s / (camera.gsd_m(pose.altitude_m) * camera.pixel_aspect)
        if blur_px >= 1.0:
            image = cv2.filter2D(image, -1, _motion_kernel(blur_px), borderType=cv2.BORDER_REPLICATE)
        gamma, gains = photometry_draws(p, rng)
        if gamma is not None:
            cv2.LUT(image, gamma_lut(gamma), dst=image)
        if gains is not None:
            cv2.transform(image, np.diag(gains).astype(np.float32), dst=image)
        noise = None
        if p.has_noise:
            dy, dx = rng.integers(0, render_mod._NOISE_MARGIN_PX + 1, size=2)
            sigma = cv2.LUT(image, self._sensor.sigma_lut)
            noise = cv2.multiply(sigma, self._noise_bank[dy:dy + h, dx:dx + w], scale=2.0 ** -19)
        vignette = self._vignetting_map(camera, p.vignetting)
        if vignette is not None:
            cv2.multiply(image, np.rint(vignette * 255.0).astype(np.uint8), dst=image, scale=1.0 / 255.0)
        if noise is not None:
            cv2.add(image, noise, dst=image, dtype=cv2.CV_8U)
        self.masks.append(mask.view(bool))
        return image, alpha, cv2.countNonZero(mask)


def _warp_box(box, matrix, width_px, height_px):
    """The reference warp of a baked box (uint32 RGBA pixels): OpenCV's."""
    rgba = box.view(np.uint8).reshape(*box.shape, 4)
    return cv2.warpAffine(rgba, matrix, (width_px, height_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))


def _remap_box(box, map_x, map_y):
    """The reference sampling of a baked box (uint32 RGBA pixels) through a view's maps: OpenCV's."""
    rgba = box.view(np.uint8).reshape(*box.shape, 4)
    return cv2.remap(rgba, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _shade_pixels(image, pixels, gains):
    """The facades' shading as NumPy does it: the RGB bytes of ``pixels`` times their gain, rounded, clipped."""
    flat = image.reshape(-1, 3)
    flat[pixels] = np.clip(np.rint(flat[pixels] * gains[:, None]), 0, 255).astype(np.uint8)


def _scene(relief: bool = False):
    """A textured 100 m map (every level, saturated patches) and a soft shadow grid holding 0, 1 and between."""
    rng = np.random.default_rng(0)
    rgb = cv2.resize(rng.integers(0, 256, (50, 50, 3), dtype=np.uint8), (400, 400), interpolation=cv2.INTER_CUBIC)
    rgb[100:140, 100:140] = 255
    rgb[160:200, 100:140] = 0
    occ = cv2.resize(rng.random((20, 20), dtype=np.float32), (200, 200), interpolation=cv2.INTER_LINEAR)
    grid = ShadowGrid(np.clip(2.0 * occ - 0.5, 0.0, 1.0).astype(np.float32), 0.5, 0.5, 2)
    orthomap = SimpleNamespace(rgb=rgb, gsd_x_m=0.25, gsd_y_m=0.25, height_px=400, width_px=400, nodata=None,
                               name="kernel-test")
    if relief:
        dsm = np.zeros((400, 400), np.float32)
        dsm[150:200, 215:265] = 12.0
        orthomap.dsm_m = dsm
    return orthomap, grid


def _pair(photometry, *, rgba=None, perspective=None, relief=False, seed=5):
    orthomap, grid = _scene(relief)
    kw = {"noise_seed": seed, "rgba": rgba, "perspective": perspective}
    return CameraRenderer(orthomap, CAMERA, photometry, **kw), _OpenCVRenderer(orthomap, CAMERA, photometry, **kw), grid


def _assert_same(new, ref, ref_r):
    np.testing.assert_array_equal(new.image, ref.image)
    np.testing.assert_array_equal(new.shadow_mask, ref_r.masks[-1])
    assert new.shadow_fraction == ref.shadow_fraction
    if ref.occlusion_q is not None:
        np.testing.assert_array_equal(new.occlusion_q, ref.occlusion_q)
    assert new.image.dtype == np.uint8 and new.shadow_mask.dtype == bool and new.image.flags.c_contiguous
    assert new.image.shape == ref.image.shape and new.image.flags.writeable


def _render_both(new_r, ref_r, pose, occlusion, seed, **kw):
    new = new_r.render(pose, np.random.default_rng(seed), occlusion, SHADING, **kw)
    ref = ref_r.render(pose, np.random.default_rng(seed), occlusion, SHADING, **kw)
    _assert_same(new, ref, ref_r)
    return new


@pytest.mark.parametrize("name", list(SETTINGS))
def test_baked_per_frame_and_unshadowed_frames_equal_the_opencv_passes(name):
    """Baked shadows (level 0), the per-frame grid (level 1), no shadows; at rest and with motion blur."""
    new_r, ref_r, grid = _pair(SETTINGS[name])
    if SETTINGS[name].vignetting > 0.0:      # symmetric: the kernel reads the top rows for the bottom ones too
        assert new_r._sensor.vig.shape == ((CAMERA.height_px + 1) // 2, 3 * CAMERA.width_px)
    new_b = new_r.bake(grid, SHADING, (20, 20, 380, 380))
    ref_b = ref_r.bake(grid, SHADING, (20, 20, 380, 380))
    for i, pose in enumerate(POSES):
        for speed_mps in (0.0, 150.0):                       # 150 m/s: a 1.2 px blur between shading and gamma
            new = new_r.render(pose, np.random.default_rng(i), new_b, None, speed_mps=speed_mps)
            ref = ref_r.render(pose, np.random.default_rng(i), ref_b, None, speed_mps=speed_mps)
            _assert_same(new, ref, ref_r)
            np.testing.assert_array_equal(new.occlusion_q > 127, new.shadow_mask)   # the warped alpha
            assert 0.05 < new.shadow_fraction < 0.95
            _render_both(new_r, ref_r, pose, None, i, speed_mps=speed_mps)
        frame = _render_both(new_r, ref_r, HIGH, grid, i)
        assert frame.pyramid_level == 1 and 0.05 < frame.shadow_fraction < 0.95
        np.testing.assert_array_equal(frame.occlusion >= 0.5, frame.shadow_mask)   # warped on first read
        # the level pass split around a scene step and a 1.3 px motion blur (300 m/s)
        _render_both(new_r, ref_r, HIGH, grid, i, speed_mps=300.0,
                     pre_sensor=lambda image: cv2.convertScaleAbs(image, alpha=0.8))
    if name == "saturating gains":                           # the gains do clip, both ways
        assert (frame.image == 255).mean() > 0.05 and (frame.image == 0).any()


def test_rgb_maps_scene_steps_and_views_equal_the_opencv_passes():
    """An RGB-held map (3-channel warps), a pre-sensor step, combined occluders, tilted and perspective views."""
    p = Photometry(read_noise_dn=4.0, shot_noise_gain=0.3)
    new_r, ref_r, grid = _pair(p, rgba=False)
    dim = {"pre_sensor": lambda image: cv2.convertScaleAbs(image, alpha=0.8)}
    for i, pose in enumerate(POSES):
        _render_both(new_r, ref_r, pose, grid, i)
        _render_both(new_r, ref_r, pose, [grid, grid], i, **dim)
    for relief in (False, True):
        new_r, ref_r, grid = _pair(p, perspective=PerspectiveConfig(enabled=True), relief=relief)
        new_b = new_r.bake(grid, SHADING, (20, 20, 380, 380))
        ref_b = ref_r.bake(grid, SHADING, (20, 20, 380, 380))
        for i, pose in enumerate(POSES):
            for kw in ({"tilt_rad": (0.01, -0.008)}, {"tilt_rad": (0.01, -0.008), **dim}, {}, dim):
                if kw or relief:      # (a flat untilted view is the affine warp)
                    _render_both(new_r, ref_r, pose, grid, i, **kw)
                for sun in ((200.0, 40.0), None):   # float32 / float64 facade gains
                    new = new_r.render(pose, np.random.default_rng(i), new_b, None, sun_deg=sun, **kw)
                    ref = ref_r.render(pose, np.random.default_rng(i), ref_b, None, sun_deg=sun, **kw)
                    _assert_same(new, ref, ref_r)
        if relief:    # the baked views went through view_finish, facades included
            assert len(ref_r.facades) == 16 and min(ref_r.facades) > 0


def _sigma_f32_fails(r: float, g: float) -> bool:
    a32, b32 = np.float32(r * r * 65536), np.float32(g * 65536)
    lut = np.rint(np.sqrt(r * r + g * np.arange(256, dtype=np.float64)) * 256).astype(np.int32)
    return not np.array_equal(fk.sigma_levels(fk.SIGMA_F32, a32, b32, r * r, g), lut)


def test_sigma_in_float32_only_where_it_reproduces_the_lut_else_float64():
    """The renderer computes sigma in float32 only where all 256 levels equal the int16 LUT; a setting where
    float32 misses one level takes float64, and the frames still equal the LUT-based reference."""
    rng = np.random.default_rng(0)
    r, g = next((r, g) for r, g in zip(rng.uniform(0, 50, 500), rng.uniform(0, 10, 500), strict=True)
                if _sigma_f32_fails(r, g))
    for read, shot, mode in ((2.0, 0.05, fk.SIGMA_F32), (r, g, fk.SIGMA_F64)):
        p = Photometry(read_noise_dn=read, shot_noise_gain=shot)
        new_r, ref_r, grid = _pair(p)
        assert new_r._sensor.sigma_mode == mode
        levels = fk.sigma_levels(mode, new_r._sensor.a32, new_r._sensor.b32, new_r._sensor.a64, new_r._sensor.b64)
        np.testing.assert_array_equal(levels, new_r._sensor.sigma_lut)
        for i, pose in enumerate(POSES):
            _render_both(new_r, ref_r, pose, grid, i)


def test_kernel_arithmetic_matches_opencv_over_every_level():
    """Exhaustive: the uint8 x uint8 / 255 multiply over all 65536 pairs (vignetting and shading), and the
    occlusion's quantization and threshold around every rounding boundary (float32 neighbours of (k + 1/2) / 255
    and of 1/2)."""
    a = np.repeat(np.arange(256, dtype=np.uint8), 256).reshape(256, 256)
    b = np.ascontiguousarray(a.T)
    src = np.repeat(a[:, :, None], 3, axis=2)
    vig = np.repeat(b[:, :, None], 3, axis=2).reshape(256, -1)
    out = np.empty(256 * 768, np.uint8)
    ident = render_mod._IDENTITY
    fk.finish(src.reshape(256, -1), 3, fk.OCC_NONE, render_mod._NO_OCC, render_mod._IDENTITY_RO, ident, out,
              render_mod._NO_VIG, True, vig, render_mod._NO_BANK, 0, 0, fk.NOISE_OFF,
              np.float32(0), np.float32(0), 0.0, 0.0)
    np.testing.assert_array_equal(out.reshape(256, 256, 3), cv2.multiply(src, vig.reshape(256, 256, 3),
                                                                         scale=1.0 / 255.0))
    # the occlusion: 41 float32 neighbours of each boundary, shading an all-255 image by a LUT q -> q
    base = np.concatenate([(np.arange(256) + 0.5) / 255.0, [0.5]]).astype(np.float32)
    steps = [base]
    for direction in (np.float32(2.0), np.float32(-1.0)):
        x = base
        for _ in range(20):
            x = np.nextafter(x, direction)
            steps.append(x)
    occ = np.clip(np.stack(steps), 0.0, 1.0).astype(np.float32)      # (41, 257)
    h, w = occ.shape
    qlut = np.repeat(np.arange(256, dtype=np.uint8)[None], 3, axis=0)
    qlut.flags.writeable = False
    white = np.full((h, 3 * w), 255, np.uint8)
    out = np.empty(h * 3 * w, np.uint8)
    count = fk.finish(white, 3, fk.OCC_FLOAT, occ, qlut, ident, out, render_mod._NO_VIG, False, render_mod._NO_VIG,
                      render_mod._NO_BANK, 0, 0, fk.NOISE_OFF, np.float32(0), np.float32(0), 0.0, 0.0)
    np.testing.assert_array_equal(out.reshape(h, w, 3)[..., 0], cv2.convertScaleAbs(occ, alpha=255.0))
    assert count == np.count_nonzero(occ >= 0.5)
    # the baked alpha: copied out and counted above 127, the RGBA frame turned into RGB in its own memory
    rgba = np.concatenate([np.full((h, w, 3), 7, np.uint8), out.reshape(h, w, 3)[..., :1]], axis=2)
    alpha = np.empty((h, w), np.uint8)
    count = fk.finish(rgba.reshape(h, -1), 4, fk.OCC_ALPHA, render_mod._NO_OCC, render_mod._IDENTITY_RO, ident,
                      rgba.reshape(-1), alpha, False, render_mod._NO_VIG, render_mod._NO_BANK, 0, 0, fk.NOISE_OFF,
                      np.float32(0), np.float32(0), 0.0, 0.0)
    np.testing.assert_array_equal(alpha, cv2.convertScaleAbs(occ, alpha=255.0))
    assert count == np.count_nonzero(occ >= 0.5)
    assert (rgba.reshape(-1)[:h * w * 3] == 7).all()


def test_same_seed_same_frames_and_the_noise_moves():
    orthomap, grid = _scene()
    runs = []
    for _ in range(2):
        renderer = CameraRenderer(orthomap, CAMERA, Photometry(), noise_seed=11)
        baked = renderer.bake(grid, SHADING, (20, 20, 380, 380))
        rng = np.random.default_rng(12)
        runs.append([renderer.render(POSES[0], rng, baked).image for _ in range(3)])
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
    assert not np.array_equal(runs[0][0], runs[0][1])


@numba.njit
def _noise_terms(s, z):
    out = np.empty(s.size, np.int32)
    for i in range(s.size):
        out[i] = np.int32(fk._noise(np.float32(s[i]), z[i]))
    return out


def test_noise_term_rounds_like_opencv_at_its_ties():
    """``cv2.multiply(S, Z, scale=2**-19)`` on int16 rounds the product to float32 first: products within half a
    float32 step of an odd multiple of 2**18 (a tie after scaling) round differently from the exact product.
    Every sigma the LUT can hold against the draws nearest to such ties, and random pairs."""
    rng = np.random.default_rng(0)
    s = np.repeat(np.arange(256, 18_200, 7), 64)
    k = rng.integers(-1100, 1100, s.size)
    z = np.rint((2 * k + 1) * 2.0 ** 18 / s) + rng.integers(-2, 3, s.size)
    keep = np.abs(z) <= 32767
    s = np.concatenate([s[keep], rng.integers(0, 18_200, 200_000)]).astype(np.int16)
    z = np.concatenate([z[keep], rng.integers(-32767, 32768, 200_000)]).astype(np.int16)
    expected = cv2.multiply(s.reshape(-1, 1), z.reshape(-1, 1), scale=2.0 ** -19).ravel()
    exact = np.rint(s.astype(np.float64) * z * 2.0 ** -19)
    assert np.count_nonzero(expected != exact) > 10          # the ties are hit: the test can tell the two apart
    np.testing.assert_array_equal(_noise_terms(s, z), expected)


@pytest.mark.parametrize("channels", [3, 4])
def test_shade_on_strided_tiles_equals_the_opencv_passes(channels):
    """``world.shadows.shade`` (the bake's tiles: a view of the map into a view of the box, float occlusion from a
    view of the upsampled grid) against convertScaleAbs, three 1-channel LUTs merged and one multiply."""
    rng = np.random.default_rng(4)
    big = rng.integers(0, 256, (90, 130, channels), dtype=np.uint8)
    big[..., 3:] = 255
    occ_big = rng.random((90, 130), dtype=np.float32)
    occ_big[:5] = np.array([0.0, 0.5, 1.0, 127.5 / 255.0, 0.25], np.float32)[:, None]
    src, occ = big[7:71, 11:107], occ_big[7:71, 11:107]
    for strength, kwargs in [(0.9, {}), (0.5, {"shadow_ratio": 0.3, "sky_tint_rgb": (0.6, 0.7, 0.9), "gamma": 1.8})]:
        lut = shading_lut(strength, **kwargs)
        q = cv2.convertScaleAbs(occ, alpha=255.0)
        gains = [cv2.LUT(q, lut[c]) for c in range(3)] + ([q] if channels == 4 else [])
        expected = cv2.multiply(np.ascontiguousarray(src), cv2.merge(gains), scale=1.0 / 255.0)
        box = np.zeros((80, 120, channels), np.uint8)
        assert shade(src, occ, lut, out=box[5:69, 9:105]) is not None
        np.testing.assert_array_equal(box[5:69, 9:105], expected)
        assert not box[:5].any() and not box[69:].any() and not box[:, :9].any() and not box[:, 105:].any()
        np.testing.assert_array_equal(shade(src, q, lut), expected)        # uint8 levels, a fresh output


def test_shade_refuses_what_its_kernel_would_index_out_of_bounds():
    """``shade``'s kernel runs without bounds checks: a wrong dtype, shape, table or output is a ConfigError."""
    from aerial_loc_env.errors import ConfigError

    rgb, occ, lut = np.zeros((8, 6, 3), np.uint8), np.zeros((8, 6), np.float32), shading_lut(0.9)
    bad = [(rgb.astype(np.float32), occ, lut, None), (rgb[..., :2], occ, lut, None), (rgb[0], occ[0], lut, None),
           (rgb, occ[:7], lut, None), (rgb, occ.T, lut, None), (rgb, occ.astype(np.int16), lut, None),
           (rgb, occ, lut[:, :255], None), (rgb, occ, lut.astype(np.int16), None), (rgb, occ, lut[:2], None),
           (rgb, occ, lut, np.zeros((8, 5, 3), np.uint8)), (rgb, occ, lut, np.zeros((8, 6, 3), np.float32)),
           (rgb, occ, lut, np.zeros((8, 6, 4), np.uint8))]
    for args in bad:
        with pytest.raises(ConfigError, match="shade: "):
            shade(*args[:3], out=args[3])


def test_quantize_saturates_nan_inf_and_huge_occlusion_as_opencv():
    """NaN, inf and occlusions beyond int32 levels quantize as convertScaleAbs does (to 0), not to an index out of
    the shading table; the occlusion's float path (``shade`` and the frame kernel) goes through the same helper."""
    from aerial_loc_env.world.shadows import apply_shading

    occ = np.float32([[np.nan, np.inf, -np.inf, 1e10, -1e10, 8.4e6, 2.0, -0.5, 1.0, 0.25, 3e7 / 255, 2.2e9 / 255]])
    rgb = np.full(occ.shape + (3,), 200, np.uint8)
    lut = shading_lut(0.9)
    q = cv2.convertScaleAbs(occ, alpha=255.0)
    assert q[0, 0] == q[0, 1] == q[0, 3] == 0 and q[0, 5] == 255     # the cases hit: 0 and the saturation
    expected = shade(rgb, q, lut)
    np.testing.assert_array_equal(shade(rgb, occ, lut), expected)
    np.testing.assert_array_equal(apply_shading(rgb, occ, 0.9), expected)


def test_pre_sensor_must_return_the_uint8_frame():
    """The image ``pre_sensor`` returns goes on into the kernel, which indexes its tables by the bytes: anything but
    the (H, W, 3) uint8 frame is a ConfigError (an int16 image would read out of the tone table)."""
    from aerial_loc_env.errors import ConfigError

    renderer, _, grid = _pair(SETTINGS["defaults"])
    for step in (lambda im: im.astype(np.int16) + 300, lambda im: im[:, :, 0], lambda im: np.ascontiguousarray(
            im.transpose(1, 0, 2))):
        with pytest.raises(ConfigError, match="pre_sensor"):
            renderer.render(POSES[0], np.random.default_rng(0), grid, SHADING, pre_sensor=step)


def test_a_held_frame_is_its_own_memory():
    """A frame's image is a view into the memory its warp wrote (no copy): it must be that frame's alone, so that a
    recorded episode or an estimator keeping the previous frame sees it unchanged by the frames rendered after
    it, and a caller writing into one frame's image changes no other frame (baked, per-frame and unshadowed)."""
    renderer, _, grid = _pair(SETTINGS["defaults"])
    baked = renderer.bake(grid, SHADING, (20, 20, 380, 380))
    for occlusion in (baked, grid, None):
        rng = np.random.default_rng(1)
        first = renderer.render(POSES[0], rng, occlusion, SHADING)
        assert (first.occlusion_q is not None) == (occlusion is baked)     # each path taken
        kept = first.image.copy(), first.shadow_mask.copy(), None if first.occlusion is None else first.occlusion.copy()
        later = [renderer.render(pose, rng, occlusion, SHADING) for pose in (POSES[1], POSES[0], POSES[1])]
        np.testing.assert_array_equal(first.image, kept[0])
        np.testing.assert_array_equal(first.shadow_mask, kept[1])
        if kept[2] is not None:
            np.testing.assert_array_equal(first.occlusion, kept[2])
        for frame in later:
            assert not np.shares_memory(frame.image, first.image)
        first.image[...] = 0
        assert later[1].image.any()


@pytest.mark.parametrize("size", [(600, 400), (120, 80), (128, 40), (37, 9)])
def test_box_warp_equals_opencv_warp_affine_over_random_affines(size):
    """``warp_finish``'s warp against ``cv2.warpAffine`` (8UC4, INTER_LINEAR, zero border): rotations, scales
    0.5-2, subpixel offsets, footprints inside, across and off the box's edges; widths with and without the
    scalar tail (W mod ``WARP_STEP_PX``). Where OpenCV dispatches its AVX2 kernel (x86-64 since 2013, this
    project's machines) the RGB, alpha and count are equal; elsewhere its coordinates can differ by an ulp or two,
    which moves a value by one level where the bilinear sum is within ~1e-3 of a rounding tie: at most one level,
    in few values."""
    w, h = size
    rng = np.random.default_rng(w)
    box = rng.integers(0, 256, (460, 620, 4), dtype=np.uint8)
    box[40:70, 50:90] = 255                                      # saturated patches
    box[90:120, 20:60] = 0
    box32 = box.view(np.uint32).reshape(460, 620)
    ident = np.tile(np.arange(256, dtype=np.uint8), (3, 1))
    exact = cv2.checkHardwareSupport(13)     # CV_CPU_AVX2 (the Python module of OpenCV 5 exports no name for it)
    for t in range(40):
        angle, scale = rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 2.0)
        m = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        centre = rng.uniform(-150.0, 770.0, 2) if t % 4 == 0 else rng.uniform(150.0, 310.0, 2)  # across / inside
        matrix = np.hstack([m, (centre - m @ (np.array([w, h]) / 2.0 + rng.uniform(0.0, 1.0, 2)))[:, None]])
        out = np.empty(h * w * 3, np.uint8)
        alpha = np.empty((h, w), np.uint8)
        count = fk.warp_finish(box32, matrix, ident, out, alpha, False, render_mod._NO_VIG, render_mod._NO_BANK, 0,
                               0, fk.NOISE_OFF, np.float32(0), np.float32(0), 0.0, 0.0)
        ref = _warp_box(box32, matrix, w, h)
        got = np.dstack([out.reshape(h, w, 3), alpha])
        if exact:
            np.testing.assert_array_equal(got, ref)
        else:
            assert np.abs(got.astype(int) - ref).max() <= 1 and (got != ref).mean() < 0.01
        assert count == np.count_nonzero(alpha > 127)


@pytest.mark.parametrize("size", [(600, 400), (120, 80), (37, 9)])
def test_level_warp_equals_opencv_warps_then_shading_over_random_affines(size):
    """``level_finish`` against ``cv2.warpAffine`` of the level (8UC4, zero border) and of the shadow grid (32FC1,
    replicated border), then the float occlusion's shading (``shade``) and its count (occlusion >= 0.5): rotations,
    scales, footprints inside, across and beyond the edges (the grid's replicated border read far out), a grid
    with levels 0, 1 and between, shadings that leave level 0 alone and that do not. Equal where OpenCV runs its
    AVX2 kernels, as for ``warp_finish``."""
    w, h = size
    rng = np.random.default_rng(w + 1)
    level = rng.integers(0, 256, (300, 380, 4), dtype=np.uint8)
    level[40:70, 50:90] = 255
    box32 = level.view(np.uint32).reshape(300, 380)
    grid = np.clip(2.0 * cv2.resize(rng.random((15, 19), dtype=np.float32), (190, 150)) - 0.5, 0.0, 1.0)
    ident = np.tile(np.arange(256, dtype=np.uint8), (3, 1))
    exact = cv2.checkHardwareSupport(13)
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    for t in range(30):
        angle, scale = rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 2.0)
        m = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        centre = rng.uniform(-150.0, 530.0, 2) if t % 3 == 0 else rng.uniform(100.0, 250.0, 2)
        matrix = np.hstack([m, (centre - m @ (np.array([w, h]) / 2.0 + rng.uniform(0.0, 1.0, 2)))[:, None]])
        gm = matrix / 2.0
        gm[:, 2] += 0.25 - 0.5
        lut = shading_lut(0.9) if t % 2 else shading_lut(0.7, shadow_ratio=0.4, sky_tint_rgb=(0.2, 0.3, 0.9))
        lut = lut.copy() if t % 4 == 1 else lut
        if t % 4 == 1:
            lut[:, 0] = (250, 255, 240)        # level 0 shaded too
        out = np.empty(h * w * 3, np.uint8)
        count = fk.level_finish(box32, matrix, grid, gm, lut, h, w, ident, out, False, render_mod._NO_VIG,
                                render_mod._NO_BANK, 0, 0, fk.NOISE_OFF, np.float32(0), np.float32(0), 0.0, 0.0)
        occ = cv2.warpAffine(grid, gm, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        ref = np.ascontiguousarray(_warp_box(box32, matrix, w, h)[..., :3])
        shade(ref, cv2.convertScaleAbs(occ, alpha=255.0), lut, out=ref)
        got = out.reshape(h, w, 3)
        if exact:
            np.testing.assert_array_equal(got, ref)
            assert count == np.count_nonzero(occ >= 0.5)
        else:
            assert np.abs(got.astype(int) - ref).max() <= 2 and (got != ref).mean() < 0.01


@numba.njit
def _remap_through(box, map_x, map_y, pixels, gains, lut, out, alpha, ahead):
    """``view_finish``'s rows through given maps (no sensor stage): each row sampled (``_warp_row``, box lines
    ``ahead`` prefetched), its facades shaded (``_shade_row``, the pixels walked in flat-index order), toned."""
    h_px, w_px = alpha.shape
    flat, _, _, _, _ = fk._box_layout(box)
    fa, fb, idx, q00, q01, q10, q11, c00, c01, c10, c11, rgba, o, no_occ = fk._row_buffers(w_px)
    l0, l1, l2, tabs = fk._tone_tables(lut)
    count, t = 0, 0
    for y in range(h_px):
        fk._warp_row(box, flat, ahead, map_x[y], map_y[y], fa, fb, idx, rgba, q00, q01, q10, q11, c00, c01, c10, c11)
        t = fk._shade_row(rgba, pixels, gains, t, pixels.size, np.int64(y) * w_px, w_px)
        count += fk._scene_row(rgba, o, alpha[y], no_occ, 4, w_px, fk.OCC_ALPHA, l0, l1, l2, l0, l1, l2, False, tabs)
        out[3 * w_px * y:3 * w_px * (y + 1)] = o
    return count


@pytest.mark.parametrize("size", [(600, 400), (120, 80), (37, 9)])
def test_map_warp_equals_opencv_remap_then_facades_over_random_maps(size):
    """The rows of ``perspective_kernels.view_finish`` (``_remap_through``: the library's row helpers as that pass
    composes them) against ``cv2.remap`` (8UC4, INTER_LINEAR, zero border) then the facades' gains: maps of random
    rotations and scales with per-pixel jitter (as relief displaces a view's points), inside the box, across its
    edges and beyond them, integral and half-integral points (rounding ties of the weights), NaN and infinite points
    (zero, not a read outside the box); facade pixels in flat-index order (as the maps kernel lists them), with
    float32 and float64 gains (with and without a sun), some saturating. The RGB, alpha and count are equal where
    OpenCV runs its AVX2 kernel, as for ``warp_finish``."""
    w, h = size
    rng = np.random.default_rng(h)
    box = rng.integers(0, 256, (300, 420, 4), dtype=np.uint8)
    box[40:70, 50:90] = 255
    box32 = box.view(np.uint32).reshape(300, 420)
    ident = np.tile(np.arange(256, dtype=np.uint8), (3, 1))
    exact = cv2.checkHardwareSupport(13)
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    clipped = False
    for t in range(24):
        angle, scale = rng.uniform(-np.pi, np.pi), rng.uniform(0.5, 2.0)
        centre = rng.uniform(-100.0, 520.0, 2) if t % 3 == 0 else rng.uniform(120.0, 300.0, 2)
        u, v = xs - w / 2.0, ys - h / 2.0
        map_x = centre[0] + scale * (np.cos(angle) * u - np.sin(angle) * v) + rng.normal(0.0, 2.0, (h, w))
        map_y = centre[1] + scale * (np.sin(angle) * u + np.cos(angle) * v) + rng.normal(0.0, 2.0, (h, w))
        if t % 4 == 1:
            map_x, map_y = np.round(map_x * 2.0) / 2.0, np.round(map_y * 2.0) / 2.0
        map_x, map_y = map_x.astype(np.float32), map_y.astype(np.float32)
        if t % 5 == 2:        # non-finite points read the border, as in cv2.remap (and never outside the box)
            map_x.flat[rng.choice(h * w, 5)] = np.nan
            map_y.flat[rng.choice(h * w, 5)] = np.inf
            map_x.flat[rng.choice(h * w, 5)] = -np.inf
        pixels = np.sort(rng.choice(h * w, size=(h * w) // 5, replace=False)).astype(np.int64)
        gains = rng.uniform(0.2, 1.6, pixels.size)
        gains = gains.astype(np.float32) if t % 2 else gains
        out = np.empty(h * w * 3, np.uint8)
        alpha = np.empty((h, w), np.uint8)
        count = _remap_through(box32, map_x, map_y, pixels, gains, ident, out, alpha, 8 * 420 + 3 * (t % 3 - 1))
        ref = _remap_box(box32, map_x, map_y)
        ref_alpha = ref[..., 3].copy()
        ref = np.ascontiguousarray(ref[..., :3])
        _shade_pixels(ref, pixels, gains)
        got = out.reshape(h, w, 3)
        gain_px = got.reshape(-1, 3)[pixels]
        if exact:
            np.testing.assert_array_equal(got, ref)
            np.testing.assert_array_equal(alpha, ref_alpha)
        else:
            assert np.abs(got.astype(int) - ref).max() <= 1 and (got != ref).mean() < 0.01
        assert count == np.count_nonzero(alpha > 127)
        clipped |= bool((gain_px == 255).any())
    assert clipped     # some gain saturated a shaded byte


def test_wide_vectors_marks_the_calling_kernel_only():
    """The frame pass's codegen hint (``jit.wide_vectors``) reaches LLVM as an attribute of the function
    that calls it, which stays a function of its own (noinline: inlined into numba's wrappers it would take theirs),
    and changes nothing computed: the hinted and plain versions of one loop agree bit for bit."""
    from aerial_loc_env.jit import fma32, wide_vectors

    def body(a, out):
        for i in range(a.shape[0]):
            out[i] = np.rint(fma32(a[i], np.float32(1.7), np.float32(0.3)))

    @numba.njit
    def hinted(a, out):
        wide_vectors()
        body_jit(a, out)

    body_jit = numba.njit(inline="always")(body)
    plain = numba.njit(body)
    a = np.random.default_rng(3).normal(0.0, 100.0, 4099).astype(np.float32)
    out_h, out_p = np.empty_like(a), np.empty_like(a)
    hinted(a, out_h)
    plain(a, out_p)
    assert np.array_equal(out_h, out_p)
    ir = next(iter(hinted.inspect_llvm().values()))
    define = next(line for line in ir.splitlines() if line.startswith("define") and "hinted" in line
                  and "cpython" not in line and "cfunc" not in line)
    group = define.rsplit("#", 1)[1].split()[0]
    attrs = next(line for line in ir.splitlines() if line.startswith(f"attributes #{group} "))
    assert '"prefer-vector-width"="512"' in attrs and "noinline" in attrs
    plain_ir = next(iter(plain.inspect_llvm().values()))
    assert "prefer-vector-width" not in plain_ir


def test_gather_pairs16_reads_each_indexed_pixel_and_the_next():
    """``jit.gather_pairs16`` (the box-sampling passes' neighbour loads where AVX-512 gathers pay) is
    plain indexing, 16 points at a time at any offset into the index row: the pixel at each index plus ``off`` and
    the pixel after it. Elsewhere the passes take the scalar loads (compared with OpenCV above) and this intrinsic
    cannot compile (LLVM has no gather instruction to select)."""
    from aerial_loc_env import jit as kernels

    if not kernels.FAST_GATHER:
        pytest.skip(f"this host's CPU ({kernels._host_cpu()}) takes the scalar loads: no fast AVX-512 gather")

    @numba.njit
    def rows(flat, idx, off, first, second):
        for x in range(0, idx.shape[0] - 15, 16):
            kernels.gather_pairs16(flat, idx, x, off, first, second)
        kernels.gather_pairs16(flat, idx, 3, off, first, second)   # unaligned: lanes 3..18 again, same values

    rng = np.random.default_rng(5)
    flat = rng.integers(0, 2 ** 32, 5000, dtype=np.uint32)
    for off in (0, 1, 61, 62):
        idx = rng.integers(0, flat.size - off - 1, 96).astype(np.uint32)
        first, second = np.zeros(96, np.uint32), np.zeros(96, np.uint32)
        rows(flat, idx, np.uint32(off), first, second)
        np.testing.assert_array_equal(first, flat[idx.astype(np.int64) + off])
        np.testing.assert_array_equal(second, flat[idx.astype(np.int64) + off + 1])


def test_gather_f32x16_reads_each_indexed_value():
    """``jit.gather_f32x16`` (the perspective maps' height lookups where AVX-512 gathers pay) is plain
    indexing, 16 points at a time at any offset into the index row, the first and last table entries included
    (non-finite values copied as they are). Elsewhere the maps take the scalar loads (compared with the OpenCV
    reference in tests/sensors/test_perspective_kernels.py, as here)."""
    from aerial_loc_env import jit as kernels

    if not kernels.FAST_GATHER:
        pytest.skip(f"this host's CPU ({kernels._host_cpu()}) takes the scalar loads: no fast AVX-512 gather")

    @numba.njit
    def lookups(table, idx, out):
        for x in range(0, idx.shape[0] - 15, 16):
            kernels.gather_f32x16(table, idx, x, out)
        kernels.gather_f32x16(table, idx, 5, out)   # unaligned: lanes 5..20 again, same values

    rng = np.random.default_rng(6)
    table = rng.normal(0.0, 30.0, 70_001).astype(np.float32)
    table[[3, 17]] = np.nan, np.inf
    idx = rng.integers(0, table.size, 160).astype(np.int32)
    idx[:4] = 0, table.size - 1, 3, 17
    out = np.zeros(160, np.float32)
    lookups(table, idx, out)
    np.testing.assert_array_equal(out, table[idx])


def test_lut_rgba16_matches_the_scalar_lookups():
    """``jit.lut_rgba16`` (the box-sampling passes' tone lookups, 16 RGBA pixels at a time): compiled
    (by VBMI byte permutes where the CPU has them) it writes the same colour bytes, alphas and count as its plain
    Python definition, at aligned and unaligned pixel offsets, every table entry reached (indices above and below
    128 select the table's two halves)."""
    from aerial_loc_env import jit as kernels

    @numba.njit
    def blocks(src, tabs, out, alpha, starts):
        total = 0
        for x in starts:
            total += kernels.lut_rgba16(src, x, tabs, out, alpha)
        return total

    rng = np.random.default_rng(11)
    w = 80
    src = rng.integers(0, 256, 4 * w, dtype=np.uint8)
    src[:256] = np.arange(256, dtype=np.uint8)        # every level in every channel
    tabs = rng.integers(0, 256, 768, dtype=np.uint8)
    starts = np.array([0, 16, 32, 48, 64, 5, 63], np.int64)
    out_j, alpha_j = np.zeros(3 * w, np.uint8), np.zeros(w, np.uint8)
    out_p, alpha_p = np.zeros(3 * w, np.uint8), np.zeros(w, np.uint8)
    count_j = blocks(src, tabs, out_j, alpha_j, starts)
    count_p = sum(kernels.lut_rgba16(src, int(x), tabs, out_p, alpha_p) for x in starts)
    np.testing.assert_array_equal(out_j, out_p)
    np.testing.assert_array_equal(alpha_j, alpha_p)
    assert count_j == count_p
    rgba = src.reshape(w, 4)
    np.testing.assert_array_equal(out_p.reshape(w, 3), tabs.reshape(3, 256)[np.arange(3), rgba[:, :3]])
    np.testing.assert_array_equal(alpha_p, rgba[:, 3])


def test_bilinear_rgba8_equals_the_per_pixel_blend():
    """``jit.bilinear_rgba8`` (the box-sampling passes' samples, 8 pixels a call) writes the bytes of the loop it
    replaced (``_gather_row`` and ``_blend_row``: four neighbour loads and the fma chain per channel), at aligned
    and unaligned pixel offsets, with weights at 0, just below 1 and halfway between levels (rounding ties)."""
    from aerial_loc_env import jit

    @numba.njit
    def vector(flat, idx, stride, fa, fb, out, starts):
        for x in starts:
            jit.bilinear_rgba8(flat, idx, stride, fa, fb, out, x)

    @numba.njit
    def scalar(flat, idx, stride, fa, fb, out, starts, q):
        q00, q01, q10, q11 = q[0], q[1], q[2], q[3]
        for x in starts:
            fk._gather_row(flat, idx[:x + 8], stride, q00, q01, q10, q11, x)
            fk._blend_row(q00.view(np.uint8), q01.view(np.uint8), q10.view(np.uint8), q11.view(np.uint8),
                          fa[:x + 8], fb[:x + 8], out, x)

    rng = np.random.default_rng(12)
    stride, n = 97, 64
    flat = rng.integers(0, 2 ** 32, 97 * 60, dtype=np.uint32)
    idx = rng.integers(0, flat.size - stride - 1, n).astype(np.uint32)
    idx[:3] = 0, flat.size - stride - 2, 5
    fa = rng.random(n, dtype=np.float32)
    fb = rng.random(n, dtype=np.float32)
    fa[:4], fb[:4] = (0.0, np.nextafter(np.float32(1), np.float32(0)), 0.5, 0.25), (0.5, 0.0, 0.5, 0.75)
    starts = np.array([0, 8, 16, 24, 32, 40, 48, 56, 3, 51], np.int64)
    out_v, out_s = np.zeros(4 * n, np.uint8), np.zeros(4 * n, np.uint8)
    vector(flat, idx, np.uint32(stride), fa, fb, out_v, starts)
    scalar(flat, idx, np.uint32(stride), fa, fb, out_s, starts, np.zeros((4, n), np.uint32))
    np.testing.assert_array_equal(out_v, out_s)


_AVX2_RUN = """
import hashlib, sys
import numpy as np
from aerial_loc_env import jit
from aerial_loc_env.sensors import render_kernels as fk
# _level_frame
print(jit.FAST_LUT, jit.FAST_GATHER)
rng = np.random.default_rng(4)
w = 45
src = rng.integers(0, 256, 4 * w, dtype=np.uint8)
tabs = rng.integers(0, 256, 768, dtype=np.uint8)
o, m = np.zeros(3 * w, np.uint8), np.zeros(w, np.uint8)
count = fk._scene_row(src, o, m, np.zeros(1, np.float32), 4, w, fk.OCC_ALPHA, tabs[:256], tabs[256:512], tabs[512:],
                      tabs[:256], tabs[256:512], tabs[512:], False, tabs)
print(count, hashlib.sha1(o.tobytes() + m.tobytes()).hexdigest())
print(*_level_frame(fk))
"""


def _level_frame(fk):
    """``level_finish`` of a fixed random level, grid and affine (across the edges) with a random tone table:
    (count, digest of the frame), compared between the host's code and the AVX2 code."""
    import hashlib

    rng = np.random.default_rng(5)
    box = rng.integers(0, 256, (90, 130, 4), dtype=np.uint8).view(np.uint32).reshape(90, 130)
    grid = rng.random((45, 65), dtype=np.float32)
    shade_lut = rng.integers(0, 256, (3, 256), dtype=np.uint8)
    matrix = np.array([[0.83, -0.41, 20.3], [0.39, 0.87, -12.6]])
    gm = matrix / 2.0
    gm[:, 2] -= 0.25
    out = np.empty(47 * 150 * 3, np.uint8)
    count = fk.level_finish(box, matrix, grid, gm, shade_lut, 47, 150, rng.integers(0, 256, (3, 256), dtype=np.uint8),
                            out, False, np.zeros((1, 1), np.uint8), np.zeros((1, 1), np.int16), 0, 0, fk.NOISE_OFF,
                            np.float32(0), np.float32(0), 0.0, 0.0)
    return count, hashlib.sha1(out.tobytes()).hexdigest()


def test_the_kernels_compiled_for_an_avx2_cpu_give_the_same_bytes(avx2_numba_cache):
    """Compiled for an AVX2 CPU without AVX-512 (``NUMBA_CPU_NAME=znver3`` with its own features, on any x86-64
    host; elsewhere for LLVM's generic CPU), the tone lookups take the portable path (``FAST_LUT`` off: scalar
    lookups of whole 32-bit pixels) and give the bytes of this process's path (the byte permutes where the host
    has VBMI)."""
    import hashlib
    import inspect
    import os
    import platform
    import subprocess
    import sys
    from pathlib import Path

    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    x86 = platform.machine().lower() in ("x86_64", "amd64")
    env.update(NUMBA_CACHE_DIR=str(avx2_numba_cache), NUMBA_CPU_FEATURES="",
               NUMBA_CPU_NAME="znver3" if x86 else "generic")
    repo = Path(__file__).resolve().parents[2]
    script = _AVX2_RUN.replace("# _level_frame\n", inspect.getsource(_level_frame))
    r = subprocess.run([sys.executable, "-c", script], env=env, cwd=repo, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    flags, result, level = r.stdout.splitlines()
    assert flags == "False False"
    rng = np.random.default_rng(4)
    w = 45
    src = rng.integers(0, 256, 4 * w, dtype=np.uint8)
    tabs = rng.integers(0, 256, 768, dtype=np.uint8)
    o, m = np.zeros(3 * w, np.uint8), np.zeros(w, np.uint8)
    count = fk._scene_row(src, o, m, np.zeros(1, np.float32), 4, w, fk.OCC_ALPHA, tabs[:256], tabs[256:512],
                          tabs[512:], tabs[:256], tabs[256:512], tabs[512:], False, tabs)
    assert result == f"{count} {hashlib.sha1(o.tobytes() + m.tobytes()).hexdigest()}"
    assert level == " ".join(str(v) for v in _level_frame(fk))
    rgba = src.reshape(w, 4)
    np.testing.assert_array_equal(o.reshape(w, 3), tabs.reshape(3, 256)[np.arange(3), rgba[:, :3]])
    assert count == np.count_nonzero(rgba[:, 3] > 127)
