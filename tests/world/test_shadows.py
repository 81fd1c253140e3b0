"""Cast shadows, soft occlusion, shading and clouds (aerial_loc_env.world.shadows)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.world.shadows import (
    SUN_ANGULAR_DIAMETER_DEG,
    CloudField,
    ShadowConfig,
    Sun,
    apply_shading,
    bake_shadows,
    cast_shadow_bruteforce,
    cast_shadow_mask,
    cast_shadows,
    combine_occlusion,
    sun_from_ranges,
    sun_occlusion,
    upsample,
)

# azimuths: axis-aligned, exact diagonals, and generic ones; with gsd_x != gsd_y the diagonal is not 45 deg
SUNS = [Sun(0.0, 40.0), Sun(90.0, 25.0), Sun(180.0, 55.0), Sun(270.0, 33.0), Sun(45.0, 30.0), Sun(135.0, 20.0),
        Sun(17.0, 35.0), Sun(118.5, 62.0), Sun(203.0, 28.0), Sun(301.7, 45.0), Sun(352.0, 15.0)]
GSDS = [(0.25, 0.25), (0.3, 0.45), (0.5, 0.2)]


def random_city(rng: np.random.Generator, h: int = 36, w: int = 41, rough_m: float = 0.3,
                boxes: int = 7) -> np.ndarray:
    """Boxes on rough ground: height edges like a DSM, continuous values so no exact ties."""
    dsm = rng.uniform(0.0, rough_m, (h, w))
    for _ in range(boxes):
        r, c = rng.integers(0, h), rng.integers(0, w)
        dsm[r:r + rng.integers(1, 8), c:c + rng.integers(1, 8)] += rng.uniform(2.0, 15.0)
    return dsm


def minor_axis(sun: Sun, gx: float, gy: float) -> int:
    """The axis the rays cross at most one pixel per step on: rows (0) when columns dominate, else columns."""
    a = math.radians(sun.azimuth_deg)
    return 0 if abs(math.sin(a)) / gx >= abs(math.cos(a)) / gy else 1


def shifted_stack(a: np.ndarray, axis: int, fill: float) -> np.ndarray:
    """a shifted by -1, 0, +1 along ``axis`` (outside the map: ``fill``), stacked on a new first axis."""
    pad = [(0, 0), (0, 0)]
    pad[axis] = (1, 1)
    p = np.pad(a, pad, constant_values=fill)
    n = a.shape[axis]
    return np.stack([np.take(p, np.arange(k, k + n), axis=axis) for k in range(3)])


# ------------------------------------------------------------------------------------------ sun, inputs


def test_sun_validates_ranges():
    Sun(0.0, 90.0)
    Sun(359.9, 0.1)
    for az, el in ((360.0, 30.0), (-1.0, 30.0), (10.0, 0.0), (10.0, 90.5), (float("nan"), 30.0)):
        with pytest.raises(ConfigError, match="Sun"):
            Sun(az, el)


def test_bad_inputs_raise_clear_errors():
    sun = Sun(180.0, 40.0)
    with pytest.raises(MapError, match="dsm_m"):
        cast_shadow_mask(np.zeros(5), 1.0, 1.0, sun)
    with pytest.raises(MapError, match="NaN"):
        cast_shadow_mask(np.array([[0.0, np.nan]]), 1.0, 1.0, sun)
    with pytest.raises(MapError, match="gsd_y_m"):
        cast_shadow_mask(np.zeros((3, 3)), 1.0, 0.0, sun)
    with pytest.raises(ConfigError, match="downsample"):
        cast_shadows(np.zeros((3, 3)), 1.0, 1.0, sun, downsample=0)


# ------------------------------------------------------------------------------------- the sweep is exact


@pytest.mark.parametrize("sun", SUNS, ids=lambda s: f"az{s.azimuth_deg:g}")
def test_sweep_equals_bruteforce_on_its_digital_lines(sun):
    rng = np.random.default_rng(int(sun.azimuth_deg * 10))
    for gx, gy in GSDS:
        dsm = random_city(rng)
        fast = cast_shadow_mask(dsm, gx, gy, sun)
        slow = cast_shadow_bruteforce(dsm, gx, gy, sun, lines="digital")
        assert fast.dtype == np.bool_ and fast.shape == dsm.shape
        np.testing.assert_array_equal(fast, slow)


@pytest.mark.parametrize("sun", SUNS, ids=lambda s: f"az{s.azimuth_deg:g}")
def test_sweep_is_bounded_by_ray_marches_of_eroded_and_dilated_occluders(sun):
    """The digital line samples, at every step, a pixel at most one pixel (across the ray) from the geometric
    ray's nearest pixel: round(x + y) - round(x) - round(y) is in {-1, 0, 1}. So the sweep's shadows contain the
    ray march over occluders eroded by one pixel across the ray and are contained in the one over occluders
    dilated by one pixel; disagreement with the plain ray march is confined to that band."""
    rng = np.random.default_rng(1000 + int(sun.azimuth_deg * 10))
    for gx, gy in GSDS:
        dsm = random_city(rng)
        axis = minor_axis(sun, gx, gy)
        fast = cast_shadow_mask(dsm, gx, gy, sun)
        # one pixel of margin across the rays, where the digital line may step off the map while the ray has not
        pad = [(0, 0), (0, 0)]
        pad[axis] = (1, 1)
        receivers = np.pad(dsm, pad)
        occluders = np.pad(dsm, pad, constant_values=-np.inf)     # nothing outside the map
        eroded = shifted_stack(occluders, axis, -np.inf).min(axis=0)
        dilated = shifted_stack(occluders, axis, -np.inf).max(axis=0)
        crop = (slice(None), slice(1, -1)) if axis == 1 else (slice(1, -1), slice(None))

        def march(occ, gx=gx, gy=gy, receivers=receivers, crop=crop):
            return cast_shadow_bruteforce(receivers, gx, gy, sun, lines="ray", occluders_m=occ)[crop]

        lower, upper, ray = march(eroded), march(dilated), march(occluders)
        assert not (lower & ~fast).any()
        assert not (fast & ~upper).any()
        assert not ((fast != ray) & ~(upper & ~lower)).any()
        assert (fast != ray).mean() < (upper & ~lower).mean() + 1e-12


# ------------------------------------------------------------------------------------------- geometry


@pytest.mark.parametrize("gx, gy", [(0.25, 0.25), (0.2, 0.35)])
def test_box_building_shadow_points_north_with_length_h_over_tan_el(gx, gy):
    h_m, el = 12.0, 31.0
    dsm = np.zeros((260, 120))
    top, bottom = 200, 230                 # rows of the building (rows grow south)
    dsm[top:bottom, 40:80] = h_m
    sun = Sun(180.0, el)                   # sun in the south: the shadow falls north, to smaller rows
    m = cast_shadow_mask(dsm, gx, gy, sun)
    assert not m[bottom:].any()            # nothing south of the building
    assert not m[:, :40].any() and not m[:, 80:].any()
    col = m[:top, 60]
    length_px = int(col.sum())
    assert col[top - length_px:].all()     # one contiguous shadow attached to the north wall
    expected_px = h_m / math.tan(math.radians(el)) / gy
    assert abs(length_px - expected_px) <= 1.0
    assert m[top - length_px:top, 40:80].all()


@pytest.mark.parametrize("az", [0.0, 33.0, 90.0, 145.0, 180.0, 222.0, 270.0, 310.0])
def test_pole_shadow_tip_is_at_h_over_tan_el_opposite_the_sun(az):
    gx, gy, h_m = 0.25, 0.4, 20.0
    dsm = np.zeros((301, 301))
    dsm[150, 150] = h_m
    sun = Sun(az, 35.0)
    r, c = np.nonzero(cast_shadow_mask(dsm, gx, gy, sun))
    east, north = (c - 150) * gx, (150 - r) * gy
    se, sn = sun.towards_sun_en
    along = -(east * se + north * sn)      # metres along the anti-sun direction
    assert along.min() > 0                  # every shadow pixel lies on the side away from the sun
    tip = np.argmax(along)
    length = sun.shadow_length_m(h_m)
    # the tip pixel centre lies within one pixel (its diagonal) of the geometric tip
    assert math.hypot(east[tip] + length * se, north[tip] + length * sn) <= math.hypot(gx, gy)
    assert np.abs(east * sn - north * se).max() <= max(gx, gy)   # within a pixel of the anti-sun line


def test_flat_ground_and_gentle_slopes_cast_nothing():
    sun = Sun(135.0, 20.0)
    assert not cast_shadow_mask(np.full((30, 40), 7.5), 0.25, 0.3, sun).any()
    yy, xx = np.mgrid[0:30, 0:40]
    slope = 0.9 * math.tan(math.radians(20.0))       # rises towards the sun more gently than the rays
    se, sn = sun.towards_sun_en
    plane = slope * (xx * 0.25 * se - yy * 0.3 * sn)
    assert not cast_shadow_mask(plane, 0.25, 0.3, sun).any()
    assert not cast_shadow_mask(random_city(np.random.default_rng(1)), 0.25, 0.25, Sun(10.0, 90.0)).any()


def test_downsampled_shadows_are_those_of_the_block_maximum():
    rng = np.random.default_rng(8)
    dsm = random_city(rng, 47, 52)
    sun = Sun(118.5, 35.0)
    for f in (2, 3, 5):
        ref = np.array([[dsm[i:i + f, j:j + f].max() for j in range(0, 52, f)] for i in range(0, 47, f)])
        grid = cast_shadows(dsm, 0.25, 0.3, sun, downsample=f)
        np.testing.assert_array_equal(grid.data, cast_shadow_mask(ref, 0.25 * f, 0.3 * f, sun))
        assert (grid.gsd_x_m, grid.gsd_y_m, grid.factor) == (pytest.approx(0.25 * f), pytest.approx(0.3 * f), f)


def test_downsampled_shadows_match_within_one_coarse_pixel():
    dsm = np.zeros((201, 203))
    dsm[120:150, 60:100] = 10.0
    sun = Sun(180.0, 35.0)
    full = cast_shadow_mask(dsm, 0.25, 0.25, sun)
    grid = cast_shadows(dsm, 0.25, 0.25, sun, downsample=3)
    assert grid.data.shape == (67, 68) and grid.gsd_x_m == pytest.approx(0.75) and grid.factor == 3
    up = upsample(grid._replace(data=grid.data.astype(np.float32)), dsm.shape) > 0.5
    diff = up != full
    # every disagreement lies within one coarse pixel (3 map pixels) of the full-resolution shadow edge
    near = np.zeros_like(full)
    for dr in range(-3, 4):
        for dc in range(-3, 4):
            near |= np.roll(full, (dr, dc), axis=(0, 1)) != full
    assert not (diff & ~near).any()


# ----------------------------------------------------------------------------------------- soft shadows


def test_soft_occlusion_is_a_fraction_and_agrees_with_the_hard_mask():
    dsm = random_city(np.random.default_rng(3), 80, 90, rough_m=0.0, boxes=5)
    sun = Sun(118.5, 40.0)
    occ = sun_occlusion(dsm, 0.25, 0.3, sun).data
    hard = cast_shadow_mask(dsm, 0.25, 0.3, sun)
    assert occ.dtype == np.float32 and occ.shape == dsm.shape
    assert occ.min() >= 0.0 and occ.max() <= 1.0
    # penumbrae (at most the widest physical one, for the longest occluder distance in the map) and the
    # anti-aliasing blur (3 sigma) only touch pixels near an edge of the hard mask
    el = math.radians(sun.elevation_deg)
    d_max = math.hypot(80 * 0.3, 90 * 0.25)
    penumbra_px = d_max * math.radians(SUN_ANGULAR_DIAMETER_DEG) / (math.sin(el) * math.cos(el)) / 0.25
    r = math.ceil(penumbra_px + 3 * 0.7) + 1
    uniform = np.ones_like(hard)
    for dr in range(-r, r + 1):
        for dc in range(-r, r + 1):
            uniform &= np.roll(hard, (dr, dc), axis=(0, 1)) == hard
    uniform[:r] = uniform[-r:] = False
    uniform[:, :r] = uniform[:, -r:] = False
    assert uniform.sum() > 0.2 * uniform.size
    np.testing.assert_allclose(occ[uniform], hard[uniform].astype(np.float32), atol=0.01)
    sharp = sun_occlusion(dsm, 0.25, 0.3, sun, penumbra_scale=0.0, antialias_px=0.0).data
    np.testing.assert_array_equal(sharp > 0.5, hard)


def test_penumbra_width_grows_with_occluder_distance_as_the_solar_disc_predicts():
    el, gsd, scale = 30.0, 0.25, 8.0
    rho = math.radians(SUN_ANGULAR_DIAMETER_DEG / 2.0) * scale
    widths = []
    for h_m in (6.0, 18.0):
        dsm = np.zeros((400, 20))
        dsm[380:390] = h_m                  # an east-west wall, sun in the south
        occ = sun_occlusion(dsm, gsd, gsd, Sun(180.0, el), penumbra_scale=scale, antialias_px=0.0).data
        profile = occ[:380, 10]
        length = h_m / math.tan(math.radians(el))
        expected = 2.0 * rho * length / (math.sin(math.radians(el)) * math.cos(math.radians(el)))
        width = float(((profile > 0.0) & (profile < 1.0)).sum()) * gsd
        assert abs(width - expected) <= 2.0 * gsd + 0.1 * expected   # pixel quantization; D varies +-w/2
        # half of the disc is hidden exactly at the geometric shadow tip (profile rises towards the wall)
        half_row = float(np.interp(0.5, profile, np.arange(380.0)))
        assert abs(half_row - (380 - length / gsd)) <= 1.0
        widths.append(width)
    assert widths[1] > 2.0 * widths[0]


def test_azimuth_strips_give_lateral_penumbrae_growing_with_distance():
    el, gsd, scale, h_m = 30.0, 0.25, 8.0, 30.0
    rho = math.radians(SUN_ANGULAR_DIAMETER_DEG / 2.0) * scale
    dsm = np.zeros((300, 60), np.float32)
    dsm[280:290, 20:40] = h_m                    # a block, sun in the south: lateral edges run north-south
    sun = Sun(180.0, el)

    def lateral_width(occ, dist_m):
        row = 280 - int(round(dist_m / gsd))
        prof = occ[row, :30]
        return float(((prof > 0.01) & (prof < 0.99)).sum()) * gsd

    one = sun_occlusion(dsm, gsd, gsd, sun, penumbra_scale=scale, antialias_px=0.0).data
    five = sun_occlusion(dsm, gsd, gsd, sun, penumbra_scale=scale, antialias_px=0.0, azimuth_samples=5).data
    assert lateral_width(one, 20.0) == 0.0        # one sweep: hard lateral edges (the blur softens them)
    near, far = lateral_width(five, 5.0), lateral_width(five, 20.0)
    assert far > near
    # the 5 strips span 4/5 of the disc's width: 0.8 * 2 rho D / cos(el), up to a pixel
    full = 2.0 * rho * 20.0 / math.cos(math.radians(el))
    assert abs(far - 0.8 * full) <= gsd
    # away from the lateral edges the strips reproduce the disc profile of the tip (rectangles vs disc)
    np.testing.assert_allclose(five[:270, 30], one[:270, 30], atol=0.05)
    assert five[270, 30] == pytest.approx(1.0) and five[270, 50] == 0.0


# -------------------------------------------------------------------------------------------- shading


def test_shading_identity_darker_bluer_and_monotone():
    rng = np.random.default_rng(11)
    img = rng.integers(30, 256, (40, 50, 3), dtype=np.uint8)
    occ = np.zeros((40, 50), np.float32)
    occ[:, 25:] = 1.0
    np.testing.assert_array_equal(apply_shading(img, np.zeros_like(occ), 1.0), img)
    np.testing.assert_array_equal(apply_shading(img, occ, 0.0), img)
    prev = img.astype(int)
    for s in np.linspace(0.1, 1.0, 10):
        cur = apply_shading(img, occ, float(s)).astype(int)
        assert (cur <= prev).all()
        np.testing.assert_array_equal(cur[:, :25], img[:, :25])
        prev = cur
    shade = prev[:, 25:].astype(float) + 0.5
    orig = img[:, 25:].astype(float) + 0.5
    assert (shade.sum(axis=2) < orig.sum(axis=2)).all()
    assert ((shade[..., 2] / shade[..., 0]) > (orig[..., 2] / orig[..., 0])).mean() > 0.99


def test_full_shadow_keeps_shadow_ratio_of_luminance_in_linear_light():
    img = np.full((8, 8, 3), 200, np.uint8)
    for ratio in (0.2, 0.35, 0.5):
        out = apply_shading(img, np.ones((8, 8), np.float32), 1.0, shadow_ratio=ratio)
        lin_in = (200 / 255.0) ** 2.2
        lin_out = (out[0, 0].astype(float) / 255.0) ** 2.2
        lum = float(np.dot((0.2126, 0.7152, 0.0722), lin_out)) / lin_in
        # one grey level of rounding at ~120/255 is 2.2/120 relative in linear light, two roundings
        assert lum == pytest.approx(ratio, rel=2 * 2.2 / 120)


def test_uint8_occlusion_matches_float_and_bad_arguments_raise():
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    occ8 = rng.integers(0, 256, (20, 30), dtype=np.uint8)
    a = apply_shading(img, occ8, 0.8)
    b = apply_shading(img, occ8.astype(np.float32) / 255.0, 0.8)
    np.testing.assert_array_equal(a, b)
    out = np.empty_like(img)
    assert apply_shading(img, occ8, 0.8, out=out) is not None
    np.testing.assert_array_equal(out, a)
    with pytest.raises(ConfigError, match="strength"):
        apply_shading(img, occ8, 1.5)
    with pytest.raises(ConfigError, match="occlusion shape"):
        apply_shading(img, occ8[:5], 0.5)
    with pytest.raises(ConfigError, match="uint8"):
        apply_shading(img.astype(np.float32), occ8, 0.5)


def test_combine_occlusion_multiplies_visible_sun():
    a = np.array([0.0, 0.5, 1.0], np.float32)
    b = np.array([0.5, 0.5, 0.0], np.float32)
    np.testing.assert_allclose(combine_occlusion(a, b), [0.5, 0.75, 1.0])


def test_bake_shadows_darkens_only_where_the_other_sun_casts_shadow():
    dsm = np.zeros((60, 70), np.float32)
    dsm[30:40, 30:40] = 8.0
    img = np.full((60, 70, 3), 150, np.uint8)
    sun = Sun(90.0, 40.0)                    # morning sun in the east: shadow to the west (smaller columns)
    out = bake_shadows(img, dsm, 0.25, 0.25, sun, 1.0)
    occ = sun_occlusion(dsm, 0.25, 0.25, sun).data
    np.testing.assert_array_equal(out[occ == 0], img[occ == 0])
    assert out[35, 20].sum() < img[35, 20].sum() and (out[35, 50] == img[35, 50]).all()


# --------------------------------------------------------------------------------------------- clouds


def test_clouds_are_deterministic_and_cover_the_requested_fraction():
    a = CloudField(np.random.default_rng(5), 400.0, 300.0, cover=0.35, scale_m=80.0)
    b = CloudField(np.random.default_rng(5), 400.0, 300.0, cover=0.35, scale_m=80.0)
    c = CloudField(np.random.default_rng(6), 400.0, 300.0, cover=0.35, scale_m=80.0)
    np.testing.assert_array_equal(a.grid, b.grid)
    assert not np.array_equal(a.grid, c.grid)
    for cover in (0.1, 0.35, 0.7):
        g = CloudField(np.random.default_rng(9), 400.0, 300.0, cover=cover, scale_m=80.0).grid
        n = g.size
        assert abs((g >= 0.5).mean() - cover) <= 2.0 / n          # the quantile threshold, up to ties
        ramp = ((g > 0) & (g < 1)).mean()
        assert abs(g.mean() - (g >= 0.5).mean()) <= 0.5 * ramp + 1e-6
        assert ramp > 0.0 and (g == 1.0).any() and (g == 0.0).any()   # soft edges around umbra and sun
    assert not CloudField(np.random.default_rng(1), 100.0, 100.0, cover=0.0).grid.any()


def test_cloud_drift_moves_the_field_by_v_t():
    cell = 2.0
    cf = CloudField(np.random.default_rng(4), 300.0, 200.0, cover=0.4, scale_m=60.0, drift_mps=(3.0, -1.5),
                    cell_m=cell)
    ny, nx = cf.shape
    grid_to_world = np.array([[cell, 0.0, 0.5 * cell], [0.0, -cell, (ny - 0.5) * cell]])
    at0 = cf.occlusion_image(0.0, grid_to_world, (ny, nx))
    np.testing.assert_allclose(at0, cf.grid, atol=1e-3)
    t = 4.0                                    # 12 m east (6 cells), 6 m south (3 cells)
    moved = cf.occlusion_image(t, grid_to_world, (ny, nx))
    expected = np.roll(cf.grid, (3, 6), axis=(0, 1))   # south = larger rows, east = larger columns
    np.testing.assert_allclose(moved, expected, atol=1e-3)
    # pointwise sampling agrees with the warped image
    x = np.array([10.3, 250.0, 77.7])
    y = np.array([5.0, 190.1, 1000.0])
    u = (x - 0.5 * cell) / cell
    v = (ny - 0.5) - y / cell
    img_to_world = np.array([[cell, 0.0, 0.0], [0.0, -cell, 0.0]])
    pts = [cf.occlusion_image(t, img_to_world + np.array([[0, 0, xx], [0, 0, yy]]), (1, 1))[0, 0]
           for xx, yy in zip(x, y, strict=True)]
    np.testing.assert_allclose(cf.occlusion_at(t, x, y), pts, atol=1e-3)
    assert u.shape == v.shape


# --------------------------------------------------------------------------------------------- config


def test_shadow_config_ranges_and_draws():
    cfg = build_config(ShadowConfig, {"sun_azimuth_range_deg": [300, 60], "sun_elevation_range_deg": [20, 30],
                                      "cloud_cover": 0.3}, where="envs/test.toml")
    rng = np.random.default_rng(0)
    for _ in range(200):
        sun = cfg.draw_sun(rng)
        assert sun.azimuth_deg >= 300.0 or sun.azimuth_deg <= 60.0
        assert 20.0 <= sun.elevation_deg <= 30.0
        assert cfg.strength_range[0] <= cfg.draw_strength(rng) <= cfg.strength_range[1]
    clouds = cfg.draw_clouds(rng, 300.0, 200.0)
    assert isinstance(clouds, CloudField)
    assert math.hypot(*clouds.drift_mps) <= cfg.cloud_speed_range_mps[1]
    assert build_config(ShadowConfig, {}).draw_clouds(rng, 300.0, 200.0) is None
    with pytest.raises(ConfigError, match="allowed keys"):
        build_config(ShadowConfig, {"sun_colour": 1}, where="envs/test.toml")
    with pytest.raises(ConfigError, match="envs/test.toml.*sun_elevation_range_deg"):
        build_config(ShadowConfig, {"sun_elevation_range_deg": [0, 30]}, where="envs/test.toml")
    with pytest.raises(ConfigError, match="cloud_edge_m"):
        build_config(ShadowConfig, {"cloud_edge_m": -1.0})
    with pytest.raises(ConfigError, match="lo <= hi"):
        build_config(ShadowConfig, {"strength_range": [0.9, 0.2]})
    with pytest.raises(ConfigError, match="elevation"):
        sun_from_ranges(rng, (0, 360), (40, 30))
    assert set(cfg.shading_kwargs()) == {"shadow_ratio", "sky_tint_rgb", "gamma"}


def test_database_sun_bakes_shadows_of_another_hour():
    dsm = np.zeros((60, 70), np.float32)
    dsm[30:40, 30:40] = 8.0
    img = np.full((60, 70, 3), 150, np.uint8)
    assert build_config(ShadowConfig, {}).database_image(img, dsm, 0.25, 0.25) is img
    cfg = build_config(ShadowConfig, {"database_sun_deg": [90.0, 40.0], "downsample": 1})
    baked = cfg.database_image(img, dsm, 0.25, 0.25)
    np.testing.assert_array_equal(baked, bake_shadows(img, dsm, 0.25, 0.25, Sun(90.0, 40.0), 1.0))
    with pytest.raises(MapError, match="height model"):
        cfg.database_image(img, None, 0.25, 0.25)
    with pytest.raises(ConfigError, match="database_sun_deg"):
        build_config(ShadowConfig, {"database_sun_deg": [90.0, 0.0]}, where="envs/x.toml")


def test_disc_fraction_computes_the_penumbra_alone_with_the_same_floats():
    """``_disc_fraction`` evaluates the arcsine only where -1 < x < 1 and thresholds the rest: the same float32
    values as the formula over the whole (clipped) array, and exactly 0 / 1 outside the penumbra."""
    from aerial_loc_env.world.shadows import _disc_formula, _disc_fraction

    rng = np.random.default_rng(5)
    x = rng.normal(0.0, 3.0, (301, 257)).astype(np.float32)
    x[::7, ::5] = -np.inf                                  # pixels with no occluder
    x[1, :4] = [-1.0, 1.0, np.nextafter(np.float32(-1), np.float32(0)), np.nextafter(np.float32(1), np.float32(2))]
    expected = _disc_formula(np.clip(x, -1.0, 1.0))
    got = _disc_fraction(x.copy())
    assert got.dtype == np.float32 and got.shape == x.shape
    np.testing.assert_array_equal(got, expected)
    assert np.all(got[x <= -1.0] == 0.0) and np.all(got[x >= 1.0] == 1.0)
    inner = (x > -1.0) & (x < 1.0)
    assert 0.1 < inner.mean() < 0.5 and np.all(np.abs(got[inner] - 0.5) <= 0.5 + 1e-6)
    assert np.all(np.diff(got[0][np.argsort(x[0])]) >= -1e-6)        # monotone in x


# ------------------------------------------------------------------------------------------ the compiled sweep

def _numpy_sweep(a, geo, soft):
    """The sweep as it was before the compiled loop (world.shadows_kernels.sweep): NumPy vector operations per slice."""
    from aerial_loc_env.world.shadows import _round_half_up

    n0, n1 = a.shape
    dtype = a.dtype
    s = _round_half_up(np.arange(n0, dtype=np.float64) * geo.mu)
    order = range(n0 - 1, -1, -1) if geo.sun_dir > 0 else range(n0)
    drop, step = dtype.type(geo.step_m * geo.tan_el), dtype.type(geo.step_m)
    hor, tmp = np.full(n1, -np.inf, dtype=dtype), np.empty(n1, dtype=dtype)
    margin, dist_out = np.empty((n0, n1), dtype=dtype), np.empty((n0, n1), dtype=dtype)
    dist, dtmp, newmax = np.full(n1, step, dtype=dtype), np.empty(n1, dtype=dtype), np.empty(n1, dtype=bool)
    mask = np.empty((n0, n1), dtype=bool)
    prev = -1
    for i in order:
        if prev >= 0:
            row = a[prev]
            d = int(s[prev] - s[i])
            np.greater_equal(row, hor, out=newmax)
            np.copyto(dist, 0, where=newmax)
            np.add(dist, step, out=dtmp)
            np.maximum(hor, row, out=tmp)
            tmp -= drop
            if d == 0:
                hor, tmp = tmp, hor
                dist, dtmp = dtmp, dist
            elif d == 1:
                hor[:-1], hor[-1] = tmp[1:], -np.inf
                dist[:-1], dist[-1] = dtmp[1:], step
            else:
                hor[1:], hor[0] = tmp[:-1], -np.inf
                dist[1:], dist[0] = dtmp[:-1], step
        np.subtract(hor, a[i], out=margin[i])
        dist_out[i] = dist
        np.less(a[i], hor, out=mask[i])
        prev = i
    return (margin, dist_out) if soft else mask


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_sweep_is_bit_identical_to_the_numpy_sweep(dtype):
    """Every sun of SUNS on three grids, hard and soft, on rough ground with boxes, on plateaus of equal heights and
    on a ramp whose every slice ties with the horizon (a row equal to the horizon restarts the distance)."""
    from aerial_loc_env.world.shadows import _ray_geometry, _sweep

    rng = np.random.default_rng(7)
    for sun in SUNS:
        for gx, gy in GSDS:
            geo = _ray_geometry(gx, gy, sun)
            drop = dtype(geo.step_m * geo.tan_el)
            ramp = np.empty((31, 26), dtype)          # falls by exactly the horizon's drop per slice from the sun:
            ramp[0 if geo.sun_dir < 0 else -1] = 40.0     # every slice ties with the horizon cast onto it
            for i in (range(1, 31) if geo.sun_dir < 0 else range(29, -1, -1)):
                ramp[i] = ramp[i + geo.sun_dir] - drop
            for dsm in (random_city(rng, 37, 29), np.round(random_city(rng, 23, 44), 0), ramp):
                a = np.ascontiguousarray(dsm.astype(dtype))
                np.testing.assert_array_equal(_sweep(a, geo, soft=False), _numpy_sweep(a, geo, soft=False))
                for got, want in zip(_sweep(a, geo, soft=True), _numpy_sweep(a, geo, soft=True), strict=True):
                    assert got.dtype == want.dtype == dtype
                    np.testing.assert_array_equal(got, want)
