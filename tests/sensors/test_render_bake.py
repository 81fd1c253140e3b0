"""Cast shadows baked into the map at reset (``CameraRenderer.bake``) against the per-frame path.

Per frame the old path warps the map (bilinear weights w_i over the 2x2 map pixels a_i), warps the occlusion grid
to the camera (float, Q), then shades: ``A G(Q)`` with ``A = sum w_i a_i`` and G the per-channel shading LUT.
The baked path shades the map first, with the occlusion upsampled to map pixels and rounded (q_i), then warps:
``sum w_i a_i G(q_i)``. Their difference, per pixel and channel, splits into

    sum w_i (a_i - A)(G_i - Gbar)            <= Ra RG / 4     (a weighted covariance: half-range times half-range)
    A (Gbar - G(Q))                          <= A RG + A step (1 + 255 d_kink) / 255

with Ra, RG the ranges of a_i and G_i = G(q_i) over the 2x2 pixels, Gbar = sum w_i G_i (Gbar and G(Q) both lie in
[min G_i, max G_i] up to Q's own error), ``step`` the LUT's largest step (DN per occlusion level at a = 255) and
``d_kink`` the error of interpolating the bilinearly upsampled grid again instead of the grid itself (the
interpolant has kinks at the grid's pixel centres: at most D2 / (2 f), D2 the grid's largest second difference,
f its factor). Both paths round twice (the warp and the shading multiply): +2. Where the 2x2 pixels share one
shade (RG = 0, most of the frame) this leaves the rounding and one occlusion level: the same picture.

The shadow mask is the warped alpha >= 128 instead of the warped float occlusion >= 0.5: they can only disagree
where the float occlusion is within ``2 / 255 + D2 / (2 f) + slope (1 + 1 / f) / 32`` of 0.5 (two roundings, the
kinks, and the 1/32 px coordinate quantization of both warps over the grid's largest slope per grid pixel).
"""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from aerial_loc_env.sensors.camera import CameraModel, Pose, apply_affine
from aerial_loc_env.sensors.perspective import PerspectiveConfig, tilt_homography
from aerial_loc_env.sensors.render import BakedShadows, CameraRenderer, Photometry
from aerial_loc_env.world.shadows import ShadowGrid, shading_lut

CAMERA = CameraModel(width_px=120, height_px=80)       # 0.25 m/px at 40 m: map level 0
POSES = [Pose(50.0, 50.0, 0.3, 40.0), Pose(47.0, 55.0, -2.1, 40.0), Pose(55.0, 45.0, 1.2, 38.0)]
LEVEL_1_POSES = [Pose(50.0, 50.0, 0.3, 75.0), Pose(47.0, 55.0, -2.1, 75.0), Pose(55.0, 45.0, 1.2, 80.0)]  # 0.47 m/px
SHADING = {"strength": 0.9}


def _scene(hard: bool):
    """A textured 100 m map with a factor-2 occlusion grid: soft (every level) or hard (0/1 blocks)."""
    rng = np.random.default_rng(0)
    rgb = cv2.resize(rng.integers(0, 256, (50, 50, 3), dtype=np.uint8), (400, 400), interpolation=cv2.INTER_CUBIC)
    if hard:
        occ = cv2.resize((rng.random((10, 10)) < 0.5).astype(np.float32), (200, 200),
                         interpolation=cv2.INTER_NEAREST)
    else:
        occ = cv2.resize(rng.random((20, 20), dtype=np.float32), (200, 200), interpolation=cv2.INTER_LINEAR)
        occ = np.clip(2.0 * occ - 0.5, 0.0, 1.0)
    orthomap = SimpleNamespace(rgb=rgb, gsd_x_m=0.25, gsd_y_m=0.25, height_px=400, width_px=400, nodata=None,
                               name="bake-test")
    return orthomap, ShadowGrid(occ.astype(np.float32), 0.5, 0.5, 2)


def _grid_constants(grid: ShadowGrid) -> tuple[float, float]:
    """The grid's largest second difference and slope (per grid pixel) along either axis."""
    g = grid.data.astype(np.float64)
    d2 = max(np.abs(np.diff(g, 2, axis=0)).max(), np.abs(np.diff(g, 2, axis=1)).max())
    slope = max(np.abs(np.diff(g, axis=0)).max(), np.abs(np.diff(g, axis=1)).max())
    return float(d2), float(slope)


def _frames(renderer, grid, baked, pose):
    old = renderer.render(pose, np.random.default_rng(1), grid, SHADING)
    new = renderer.render(pose, np.random.default_rng(1), baked, None)
    return old, new


def _bound(renderer, baked: BakedShadows, grid: ShadowGrid, pose, view=None) -> np.ndarray:
    """The per-pixel, per-channel bound of the module docstring (DN); ``view``: the map points of a perspective
    or tilted view (``sensors.perspective.ViewMaps``) instead of the affine footprint. A box baked at a coarser
    pyramid level (``baked.level``) is bounded against that level's pixels, its grid ``f / 2**level`` of them per
    cell."""
    scale = 1 << baked.level
    affine = renderer.camera_to_map(pose) / scale
    v, u = np.mgrid[0:CAMERA.height_px, 0:CAMERA.width_px]
    if view is None:
        xy = apply_affine(affine, np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64))
    else:
        xy = np.stack([view.x.ravel(), view.y.ravel()], axis=1).astype(np.float64)
    c0, r0 = baked.origin_px
    x0 = np.floor(xy[:, 0]).astype(int) - c0
    y0 = np.floor(xy[:, 1]).astype(int) - r0
    rgb = renderer.map_level(baked.level)[r0:, c0:, :3].astype(np.float64)
    q = baked.rgba[..., 3]
    lut = shading_lut(SHADING["strength"]).astype(np.float64) / 255.0       # (3, 256)
    a = np.stack([rgb[y0 + dy, x0 + dx] for dy in (0, 1) for dx in (0, 1)])            # (4, n, 3)
    gains = np.stack([lut[:, q[y0 + dy, x0 + dx]].T for dy in (0, 1) for dx in (0, 1)])  # (4, n, 3)
    ra, rg = np.ptp(a, axis=0), np.ptp(gains, axis=0)
    big_a = a.max(axis=0)
    step = np.abs(np.diff(shading_lut(SHADING["strength"]).astype(np.float64), axis=1)).max()
    d2, _ = _grid_constants(grid)
    d_kink = d2 / (2.0 * grid.factor / scale)
    bound = ra * rg / 4.0 + big_a * rg + big_a * step * (1.0 + 255.0 * d_kink) / 255.0 + 2.0
    shape = (CAMERA.height_px, CAMERA.width_px, 3)
    return bound.reshape(shape), rg.reshape(shape)


@pytest.mark.parametrize("hard", [False, True])
@pytest.mark.parametrize("level", [0, 1])
def test_baked_frame_within_the_derived_bound_of_the_per_frame_shading(hard, level):
    """At level 0 and from the box baked at pyramid level 1 (a higher flight: the level's pixels shaded, then
    warped, against the level warped, then shaded)."""
    orthomap, grid = _scene(hard)
    renderer = CameraRenderer(orthomap, CAMERA, Photometry.ideal())
    baked = renderer.bake(grid, SHADING, (40, 40, 360, 360))
    assert isinstance(baked, BakedShadows)
    for pose in POSES if level == 0 else LEVEL_1_POSES:
        old, new = _frames(renderer, grid, baked, pose)
        assert old.pyramid_level == new.pyramid_level == level
        if level:
            baked_at = baked.levels[level]
            assert baked_at.level == level and baked_at.baked_tiles.any() and not baked.baked_tiles.any()
        else:
            baked_at = baked
        diff = np.abs(old.image.astype(int) - new.image.astype(int))
        bound, rg = _bound(renderer, baked_at, grid, pose)
        assert np.all(diff <= bound), f"max excess {(diff - bound).max():.2f} DN"
        # fully lit or fully shaded (the 2x2 pixels share one shade, the float occlusion is 0 or 1): only the
        # two roundings differ
        flat = (rg.max(axis=2) == 0) & ((old.occlusion == 0) | (old.occlusion == 1))
        assert flat.mean() > (0.5 if hard else 0.05)
        assert diff[flat].max() <= 2
        assert 0.05 < old.shadow_fraction < 0.95


@pytest.mark.parametrize("relief", [False, True])
def test_perspective_and_tilted_views_sample_the_bake_within_the_same_bound(relief):
    """A tilted view (and a perspective view of a height model) samples the baked box through its maps: the same
    bilinear reads at the view's map points, so the same bound at those points; facade pixels (a gain <= 1 on the
    roof's colour, applied after the shading instead of before it) get one more rounding."""
    orthomap, grid = _scene(hard=True)
    tilt = (0.01, -0.008)
    if relief:
        dsm = np.zeros((400, 400), np.float32)
        dsm[150:200, 215:265] = 12.0                 # a 12 m box east of the poses, seen from 40 m
        orthomap = SimpleNamespace(**vars(orthomap), dsm_m=dsm)
    renderer = CameraRenderer(orthomap, CAMERA, Photometry.ideal(), perspective=PerspectiveConfig(enabled=True))
    baked = renderer.bake(grid, SHADING, (40, 40, 360, 360))
    assert isinstance(baked, BakedShadows)
    for pose in POSES:
        old = renderer.render(pose, np.random.default_rng(1), grid, SHADING, tilt_rad=tilt)
        new = renderer.render(pose, np.random.default_rng(1), baked, None, tilt_rad=tilt)
        view = renderer._view.maps(renderer.camera_to_map(pose), pose.altitude_m, CAMERA,
                                   tilt_homography(CAMERA, *tilt))
        bound, _ = _bound(renderer, baked, grid, pose, view)
        if view.facade is not None:
            bound.reshape(-1, 3)[view.facade] += 1.0
        diff = np.abs(old.image.astype(int) - new.image.astype(int))
        assert np.all(diff <= bound), f"max excess {(diff - bound).max():.2f} DN"
        assert np.count_nonzero(diff) > 0           # the baked path did serve the frame
    if relief:
        assert view.facade is not None and view.facade.size > 50


@pytest.mark.parametrize("level", [0, 1])
def test_baked_shadow_mask_differs_only_next_to_half_occlusion(level):
    """The bound with the grid's cells ``f / 2**level`` pixels of the level the frame is warped from."""
    orthomap, grid = _scene(hard=False)
    renderer = CameraRenderer(orthomap, CAMERA, Photometry.ideal())
    baked = renderer.bake(grid, SHADING, (40, 40, 360, 360))
    d2, slope = _grid_constants(grid)
    f = grid.factor / (1 << level)
    delta = 2.0 / 255.0 + d2 / (2.0 * f) + slope * (1.0 + 1.0 / f) / 32.0
    assert delta < 0.15                         # a meaningful bound on this smooth grid
    for pose in POSES if level == 0 else LEVEL_1_POSES:
        old, new = _frames(renderer, grid, baked, pose)
        differ = old.shadow_mask != new.shadow_mask
        assert np.all(np.abs(old.occlusion[differ] - 0.5) <= delta)
        assert abs(old.shadow_fraction - new.shadow_fraction) <= differ.mean() + 1e-12
        assert np.abs(old.occlusion - new.occlusion).max() <= delta
        assert new.occlusion.dtype == np.float32 and new.shadow_mask.dtype == bool


def test_frames_the_bake_cannot_serve_use_the_grid_exactly():
    """Outside the box, or tilted (at level 0 and above it): the per-frame path, bit for bit."""
    orthomap, grid = _scene(hard=False)
    renderer = CameraRenderer(orthomap, CAMERA, Photometry())
    baked = renderer.bake(grid, SHADING, (150, 150, 250, 250))       # smaller than the footprints
    cases = [(POSES[0], {}), (Pose(50.0, 50.0, 0.3, 40.0), {"tilt_rad": (0.01, -0.01)})]
    wide = CameraRenderer(orthomap, CAMERA, Photometry())
    full = wide.bake(grid, SHADING, (0, 0, 400, 400))
    cases_full = [(LEVEL_1_POSES[0], {"tilt_rad": (0.01, -0.01)})]      # pyramid level 1, tilted
    for r, b, these in ((renderer, baked, cases), (wide, full, cases_full)):
        for pose, kw in these:
            old = r.render(pose, np.random.default_rng(3), grid, SHADING, **kw)
            new = r.render(pose, np.random.default_rng(3), b, None, **kw)
            np.testing.assert_array_equal(old.image, new.image)
            np.testing.assert_array_equal(old.shadow_mask, new.shadow_mask)


def test_bake_applies_only_where_it_can_and_checks_its_inputs():
    orthomap, grid = _scene(hard=False)
    assert CameraRenderer(orthomap, CAMERA, rgba=False).bake(grid, SHADING, (0, 0, 400, 400)) is None
    relief = SimpleNamespace(**vars(orthomap), dsm_m=np.zeros((400, 400), np.float32))
    persp = CameraRenderer(relief, CAMERA, perspective=PerspectiveConfig(enabled=True))
    assert isinstance(persp.bake(grid, SHADING, (0, 0, 400, 400)), BakedShadows)   # views sample it by their maps
    renderer = CameraRenderer(orthomap, CAMERA)
    with pytest.raises(Exception, match="box_px"):
        renderer.bake(grid, SHADING, (500, 500, 600, 600))
    with pytest.raises(Exception, match="float32 of shape"):
        renderer.bake(ShadowGrid(grid.data[:10], 0.5, 0.5, 2), SHADING, (0, 0, 400, 400))


def test_baked_frames_are_deterministic():
    orthomap, grid = _scene(hard=False)
    images = []
    for _ in range(2):
        renderer = CameraRenderer(orthomap, CAMERA, Photometry(), noise_seed=5)
        baked = renderer.bake(grid, SHADING, (40, 40, 360, 360))
        rng = np.random.default_rng(6)
        images.append([renderer.render(p, rng, baked, None).image for p in POSES])
    for a, b in zip(*images, strict=True):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("level", [0, 1])
def test_tiles_are_baked_lazily_and_do_not_depend_on_the_order(level):
    orthomap, grid = _scene(hard=False)
    bakes = []
    # at level 1 (128-px tiles of the 200 x 200 px level) footprints within its first tile
    corner = [Pose(32.0, 32.0, 0.0, 75.0), Pose(33.0, 31.0, 0.03, 75.0), Pose(31.0, 33.0, -0.03, 75.0)]
    for poses in (POSES, POSES[::-1]) if level == 0 else (corner, corner[::-1]):
        renderer = CameraRenderer(orthomap, CAMERA, Photometry.ideal())
        baked = renderer.bake(grid, SHADING, (0, 0, 400, 400))
        assert not baked.baked_tiles.any() and not baked.levels
        renderer.render(poses[0], np.random.default_rng(0), baked, None)
        baked = baked.levels[level] if level else baked
        assert 0 < baked.baked_tiles.sum() < baked.baked_tiles.size     # only the tiles the footprint reads
        for pose in poses[1:]:
            renderer.render(pose, np.random.default_rng(0), baked, None)
        bakes.append(baked)
    a, b = bakes
    np.testing.assert_array_equal(a.baked_tiles, b.baked_tiles)
    tile = 128
    for ty, tx in zip(*np.nonzero(a.baked_tiles), strict=True):
        sl = np.s_[ty * tile:(ty + 1) * tile, tx * tile:(tx + 1) * tile]
        np.testing.assert_array_equal(a.rgba[sl], b.rgba[sl])


def test_baked_frame_carries_the_occlusion_quantized_and_its_mask_and_fraction_agree():
    """The float occlusion of a baked frame is made on first read from the warped alpha; the mask and the shadow
    fraction come from the same alpha (>= 128) without it."""
    orthomap, grid = _scene(hard=False)
    renderer = CameraRenderer(orthomap, CAMERA, Photometry(), noise_seed=5)
    baked = renderer.bake(grid, SHADING, (40, 40, 360, 360))
    for pose in POSES:
        frame = renderer.render(pose, np.random.default_rng(2), baked, None)
        alpha = frame.occlusion_q
        assert alpha.dtype == np.uint8 and alpha.shape == frame.image.shape[:2]
        assert frame.shadow_mask.dtype == bool
        np.testing.assert_array_equal(frame.shadow_mask, alpha >= 128)
        assert frame.shadow_fraction == pytest.approx(float(np.mean(alpha >= 128)), abs=1e-12)
        assert 0.0 < frame.shadow_fraction < 1.0
        occ = frame.occlusion
        assert occ.dtype == np.float32 and frame.occlusion is occ          # made once, then kept
        np.testing.assert_array_equal(occ, alpha.astype(np.float32) * np.float32(1.0 / 255.0))


def test_shading_an_rgba_tile_gives_the_shaded_rgb_and_the_occlusion_as_alpha():
    from aerial_loc_env.world.shadows import shade

    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    occ_q = rng.integers(0, 256, (64, 96), dtype=np.uint8)
    lut = shading_lut(0.9)
    rgba = shade(cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA), occ_q, lut)
    np.testing.assert_array_equal(rgba[..., :3], shade(rgb, occ_q, lut))
    np.testing.assert_array_equal(rgba[..., 3], occ_q)


@pytest.mark.parametrize("factor", [1, 2, 3, 4, 8, 32])
def test_tile_upsampling_equals_the_per_frame_warp_bit_for_bit(factor):
    """A tile's occlusion (``_upsample_tile``: a resize of the grid block for power-of-two factors) is the same
    floats as the bilinear warp the per-frame path uses, at the grid's edges and for narrow tiles too."""
    from aerial_loc_env.sensors.render import _upsample_tile

    rng = np.random.default_rng(factor)
    gh, gw = 37, 53
    data = np.clip(cv2.GaussianBlur(rng.random((gh, gw), dtype=np.float32), (0, 0), 1.5) * 3.0 - 1.0, 0.0, 1.0)
    data[5:9, 7:20] = 1.0                               # a hard edge as well
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    mh, mw = gh * factor, gw * factor
    cases = [(0, 0, min(128, mw), min(128, mh)), (mw - 7, mh - 5, 7, 5), (0, mh - 1, 1, 1)]
    cases += [(int(rng.integers(0, mw - 1)), int(rng.integers(0, mh - 1)), 0, 0) for _ in range(40)]
    for u0, v0, w, h in cases:
        w = w or int(rng.integers(1, min(128, mw - u0) + 1))
        h = h or int(rng.integers(1, min(128, mh - v0) + 1))
        a = np.array([[1.0 / factor, 0.0, (u0 + 0.5) / factor - 0.5], [0.0, 1.0 / factor, (v0 + 0.5) / factor - 0.5]])
        ref = cv2.warpAffine(data, a, (w, h), flags=flags, borderMode=cv2.BORDER_REPLICATE)
        np.testing.assert_array_equal(_upsample_tile(data, factor, u0, v0, w, h), ref)


@pytest.mark.parametrize("relief", [False, True])
def test_a_box_in_a_freed_box_memory_renders_the_same_frames(relief):
    """A renderer keeps a freed box's memory for its next boxes (its pages already committed): the next box of the
    same renderer lies in it, its frames (flat, tilted, perspective, and the box's level-1 copy) are a fresh box's
    whatever bytes the old box left there (a frame reads only tiles it baked), and two live boxes never share
    memory."""
    orthomap, grid = _scene(hard=False)
    if relief:
        dsm = np.zeros((400, 400), np.float32)
        dsm[150:200, 215:265] = 12.0
        orthomap = SimpleNamespace(**vars(orthomap), dsm_m=dsm)
    views = [(pose, (0.0, 0.0)) for pose in POSES + LEVEL_1_POSES] + [(pose, (0.01, -0.008)) for pose in POSES]

    def frames(renderer, baked):
        rng = np.random.default_rng(6)
        return [renderer.render(pose, rng, baked, None, tilt_rad=tilt).image for pose, tilt in views]

    def make():
        return CameraRenderer(orthomap, CAMERA, Photometry(), noise_seed=5,
                              perspective=PerspectiveConfig(enabled=True))

    expected = frames(fresh := make(), fresh.bake(grid, SHADING, (40, 40, 360, 360)))
    renderer = make()
    old = renderer.bake(grid, SHADING, (0, 0, 400, 400))
    frames(renderer, old)                                   # an episode: tiles (and a level-1 box) baked
    boxes = [old, *old.levels.values()]
    assert len(boxes) == (1 if relief else 2)               # perspective views above level 0: the per-frame path
    memory = [box.rgba.base for box in boxes]
    for k, box in enumerate(boxes):
        box.rgba[...] = 0xA5 ^ k                            # what a freed box leaves is arbitrary
    del old, boxes, box
    baked = renderer.bake(grid, SHADING, (40, 40, 360, 360))
    got = frames(renderer, baked)
    for box, buf in zip([baked, *baked.levels.values()], memory, strict=True):
        assert np.shares_memory(box.rgba, buf)
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_array_equal(a, b)
    other = renderer.bake(grid, SHADING, (40, 40, 360, 360))   # while ``baked`` lives: memory of its own
    assert not any(np.shares_memory(other.rgba, box.rgba) for box in [baked, *baked.levels.values()])


def test_the_box_pool_keeps_few_buffers_within_its_byte_limit(monkeypatch):
    from aerial_loc_env.sensors import render

    monkeypatch.setattr(render, "_BOX_POOL_MAX_BYTES", 12_000)
    pool = render._BoxPool()
    boxes = [pool.take((10, 10 * k, 4)) for k in range(1, 7)]   # 400 .. 2400 bytes, buffers half again as large
    assert [box.base.size for box in boxes] == [600 * k for k in range(1, 7)]
    for box in boxes:
        pool.give(box)
    assert sorted(buf.size for buf in pool._free) == [1800, 2400, 3000, 3600]   # the largest four, 10800 bytes
    assert np.shares_memory(pool.take((10, 30, 4)), boxes[2])       # the smallest that holds it
    monkeypatch.setattr(render, "_BOX_POOL_MAX_BYTES", 9_000)
    pool.give(boxes[2])
    assert sorted(buf.size for buf in pool._free) == [2400, 3000, 3600]        # within the byte limit
    big = pool.take((40, 40, 4))                                    # none holds 6400 bytes: the kept ones freed
    assert not pool._free and big.base.size == 9600
    pool.give(big)                                                  # over the byte limit: never kept
    assert not pool._free
