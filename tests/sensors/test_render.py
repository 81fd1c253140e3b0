"""Camera rendering: the frame shows the map region it claims, anti-aliasing, shadows, photometry, footprints."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from aerial_loc_env.errors import ConfigError, FootprintError
from aerial_loc_env.sensors.camera import CameraModel, Pose
from aerial_loc_env.sensors.render import CameraRenderer, Photometry, _motion_kernel
from aerial_loc_env.world.maps.geo import LocalTangentGeoref
from aerial_loc_env.world.maps.orthomap import Orthomap
from aerial_loc_env.world.shadows import ShadowGrid

GSD = 0.25
CAM = CameraModel(width_px=60, height_px=40)  # gsd = altitude / 80: the map's 0.25 m at 20 m


def make_map(rgb: np.ndarray, nodata: np.ndarray | None = None, gsd: float = GSD) -> Orthomap:
    georef = LocalTangentGeoref(origin_lat_deg=47.0, origin_lon_deg=8.0, gsd_x_m=gsd, gsd_y_m=gsd)
    return Orthomap(rgb=rgb, gsd_x_m=gsd, gsd_y_m=gsd, georef=georef, nodata=nodata, name="test-map")


def smooth_map(size: int = 400, seed: int = 0, feature_px: int = 8) -> np.ndarray:
    rng = np.random.default_rng(seed)
    cells = size // feature_px
    return cv2.resize(rng.integers(0, 256, (cells, cells, 3), dtype=np.uint8), (size, size),
                      interpolation=cv2.INTER_CUBIC)


def ideal(orthomap: Orthomap, camera: CameraModel = CAM, **kw) -> CameraRenderer:
    return CameraRenderer(orthomap, camera, Photometry.ideal(), **kw)


@pytest.mark.parametrize("yaw", [0.0, math.pi / 2])
def test_frame_equals_the_map_region_it_claims(yaw):
    rgb = smooth_map()
    renderer = ideal(make_map(rgb))
    pose = Pose(50.0 * GSD * 4, 60.0 * GSD * 4, yaw, 20.0)  # whole map pixels: the warp is an exact copy
    frame = renderer.render(pose, np.random.default_rng(0))
    a = renderer.camera_to_map(pose)
    assert np.allclose(a[:, 2], np.rint(a[:, 2]), atol=1e-9)
    vc, uc = np.mgrid[0:CAM.height_px, 0:CAM.width_px]
    mu = np.rint(a[0, 0] * uc + a[0, 1] * vc + a[0, 2]).astype(int)
    mv = np.rint(a[1, 0] * uc + a[1, 1] * vc + a[1, 2]).astype(int)
    expected = rgb[mv, mu]
    if yaw == 0.0:  # nose east: image rows run west (tail), columns south (right): the map turned 90 deg CCW
        u0, v0 = int(mu[-1, 0]), int(mv[0, 0])
        crop = rgb[v0:v0 + CAM.width_px, u0:u0 + CAM.height_px]
        assert np.array_equal(expected, np.rot90(crop, k=1))
    else:           # nose north: a plain crop
        assert np.array_equal(expected, rgb[mv[0, 0]:mv[0, 0] + 40, mu[0, 0]:mu[0, 0] + 60])
    assert np.abs(frame.image.astype(int) - expected).max() <= 1
    assert frame.valid and frame.status == "valid" and frame.shadow_fraction == 0.0
    assert np.array_equal(renderer.database_patch(pose), frame.image)


@pytest.mark.parametrize("altitude_m", [20.0, 43.0, 80.0, 170.0])  # pyramid levels 0, 1, 2, 3
@pytest.mark.parametrize("yaw", [0.3, -2.2])
def test_project_pixels_lands_on_the_rendered_ground_point(altitude_m, yaw):
    size = 1200
    rgb = np.full((size, size, 3), 30, np.uint8)
    mu0, mv0 = 617, 583                            # a bright marker centred on this map pixel
    rgb[mv0 - 2:mv0 + 3, mu0 - 2:mu0 + 3] = 255
    orthomap = make_map(rgb)
    renderer = ideal(orthomap)
    x, y = orthomap.pixel_to_world(mu0, mv0)
    pose = Pose(float(x) + 2.0, float(y) - 1.5, yaw, altitude_m)  # marker off-centre in the frame
    frame = renderer.render(pose, np.random.default_rng(0))
    w = frame.image[..., 0].astype(float) - 30.0
    assert w.max() > 5, "the marker must be visible"
    vc, uc = np.mgrid[0:CAM.height_px, 0:CAM.width_px]
    centroid = np.array([(w * uc).sum(), (w * vc).sum()]) / w.sum()
    landed = CAM.project_pixels(orthomap, centroid[None], *pose)[0, 0]
    map_px_per_cam_px = CAM.gsd_m(altitude_m) / GSD
    assert np.hypot(*(landed - (mu0, mv0))) < 0.1 * max(map_px_per_cam_px, 1.0)


def test_yaw_convention_in_pixels_marker_north_is_left_when_flying_east():
    rgb = np.zeros((400, 400, 3), np.uint8)
    orthomap = make_map(rgb)
    x, y = 50.0, 50.0
    u, v = (int(round(float(c))) for c in orthomap.world_to_pixel(x, y + 5.0))    # 5 m north: red
    rgb[v - 1:v + 2, u - 1:u + 2, 0] = 255
    u, v = (int(round(float(c))) for c in orthomap.world_to_pixel(x + 5.0, y))    # 5 m east: green
    rgb[v - 1:v + 2, u - 1:u + 2, 1] = 255
    img = ideal(orthomap).render(Pose(x, y, 0.0, 20.0), np.random.default_rng(0)).image
    cu, cv = CAM.center_px
    red_v, red_u = np.argwhere(img[..., 0] > 128).mean(axis=0)
    green_v, green_u = np.argwhere(img[..., 1] > 128).mean(axis=0)
    assert red_u == pytest.approx(cu - 20.0, abs=0.6) and red_v == pytest.approx(cv, abs=0.6)      # left
    assert green_v == pytest.approx(cv - 20.0, abs=0.6) and green_u == pytest.approx(cu, abs=0.6)  # top


def test_antialiasing_checkerboard_renders_mean_grey_not_moire():
    size = 1600
    board = ((np.indices((size, size)).sum(axis=0) % 2) * 255).astype(np.uint8)
    orthomap = make_map(np.repeat(board[..., None], 3, axis=2))
    renderer = ideal(orthomap)
    pose = Pose(200.0, 200.0, 0.37, 80.0)          # camera gsd 1 m: 4x the map's
    frame = renderer.render(pose, np.random.default_rng(0))
    assert frame.pyramid_level == 2
    grey = frame.image.astype(float)
    assert grey.mean() == pytest.approx(127.5, abs=1.0)
    assert grey.std() < 1.5
    # the same warp straight from the full-resolution map aliases badly: the test can fail
    naive = cv2.warpAffine(orthomap.rgb, renderer.camera_to_map(pose), (CAM.width_px, CAM.height_px),
                           flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    assert naive.astype(float).std() > 30.0


def test_determinism_same_seed_same_bytes():
    orthomap = make_map(smooth_map())
    occ = np.zeros((400, 400), np.float32)
    occ[:, 200:] = 1.0

    def frame(seed: int) -> bytes:
        renderer = CameraRenderer(orthomap, CAM, Photometry(exposure_time_s=0.05), noise_seed=3)
        f = renderer.render(Pose(50.0, 50.0, 1.0, 20.0), np.random.default_rng(seed), occ, {"strength": 0.8},
                            speed_mps=10.0)
        return f.image.tobytes()

    assert frame(11) == frame(11)
    assert frame(11) != frame(12)


def test_footprint_outside_the_map_is_reported():
    orthomap = make_map(smooth_map())                # 100 m x 100 m; footprint at 20 m: 15 m x 10 m
    renderer = ideal(orthomap)
    inside, outside = Pose(50.0, 50.0, 0.5, 20.0), Pose(96.0, 50.0, 0.0, 20.0)
    assert renderer.footprint_status(inside) == "valid"
    assert renderer.footprint_status(outside) == "outside"
    with pytest.raises(FootprintError, match=r"leaves the map.*x_m=96\.00.*map bounds x in \[0, 100\.0\]"):
        renderer.render(outside, np.random.default_rng(0))
    with pytest.raises(FootprintError):
        renderer.database_patch(outside, strict=True)
    frame = renderer.render(outside, np.random.default_rng(0), strict=False)
    assert not frame.valid and frame.status == "outside"
    assert np.all(frame.image[:4] == 0)              # 1 m (4 rows) beyond the east edge (top rows) is black
    assert np.all(frame.image[5:].max(axis=2) > 0)


def test_footprint_touching_nodata_is_reported_and_near_misses_are_not():
    rgb = smooth_map(800)
    nodata = np.zeros((800, 800), bool)
    nodata[390:394, 600:603] = True                  # a small hole around world (150.4, 101.5) m
    orthomap = make_map(rgb, nodata)
    renderer = ideal(orthomap)
    for alt in (20.0, 80.0):                         # level 0 and level 2
        half_diag = 0.5 * math.hypot(*CAM.footprint_m(alt))
        assert renderer.footprint_status(Pose(150.0, 101.5, 0.3, alt)) == "nodata"
        far = Pose(150.0 - half_diag - 6.0, 101.5, 0.3, alt)
        assert renderer.footprint_status(far) == "valid"
    with pytest.raises(FootprintError, match="no-data"):
        renderer.render(Pose(150.0, 101.5, 0.3, 20.0), np.random.default_rng(0))
    # flying east at 20 m the footprint reaches 5 m ahead; the hole spans x in [150, 150.75] m
    assert renderer.footprint_status(Pose(145.1, 102.0, 0.0, 20.0)) == "nodata"   # overlaps by 0.1 m
    assert renderer.footprint_status(Pose(144.5, 102.0, 0.0, 20.0)) == "valid"    # misses by 0.5 m


def test_cast_shadow_mask_matches_the_occlusion_grid_and_darkens():
    rgb = smooth_map(800)
    orthomap = make_map(rgb)
    renderer = ideal(orthomap)
    data = np.zeros((400, 400), np.float32)          # factor 2: 400 x 400 cells over the 800 x 800 map
    data[150:260, 180:300] = 1.0
    grid = ShadowGrid(data, 2 * GSD, 2 * GSD, 2)
    pose = Pose(148.0, 100.0, 0.8, 20.0)             # the shadow's east edge (x = 150 m) crosses the frame
    lit = renderer.render(pose, np.random.default_rng(0))
    shaded = renderer.render(pose, np.random.default_rng(0), grid, {"strength": 1.0})
    mp = CAM.project_pixels(orthomap, np.stack(np.meshgrid(np.arange(60), np.arange(40)), -1).reshape(-1, 2),
                            *pose)[0]
    cell = np.floor((mp + 0.5) / 2).astype(int)     # map pixel u lies in cell floor((u + 0.5) / 2)
    expected = (data[cell[:, 1], cell[:, 0]] > 0.5).reshape(40, 60)
    assert 0.05 < expected.mean() < 0.95
    assert (shaded.shadow_mask == expected).mean() > 0.98
    assert shaded.shadow_fraction == pytest.approx(shaded.shadow_mask.mean())
    dark = shaded.image[shaded.shadow_mask].astype(float).mean() / lit.image[shaded.shadow_mask].mean()
    assert dark < 0.8
    assert np.array_equal(shaded.image[~expected & (shaded.occlusion == 0)], lit.image[~expected &
                                                                                        (shaded.occlusion == 0)])
    # a map-sized field and a sequence of sources are accepted; a wrong grid is a clear error
    full = cv2.resize(data, (800, 800), interpolation=cv2.INTER_NEAREST)
    assert (renderer.render(pose, np.random.default_rng(0), [full]).shadow_mask == expected).mean() > 0.98
    with pytest.raises(ConfigError, match="occlusion grid must be float32 of shape"):
        renderer.render(pose, np.random.default_rng(0), data)


def test_noise_statistics_follow_read_plus_shot_noise():
    level = 100
    orthomap = make_map(np.full((400, 400, 3), level, np.uint8))
    phot = Photometry(exposure_std=0.0, white_balance_std=0.0, gamma_std=0.0, vignetting=0.0,
                      read_noise_dn=2.0, shot_noise_gain=0.05)
    renderer = CameraRenderer(orthomap, CameraModel(width_px=200, height_px=120), phot)
    img = renderer.render(Pose(50.0, 50.0, 0.0, 20.0), np.random.default_rng(5)).image.astype(float)
    sigma = math.sqrt(2.0 ** 2 + 0.05 * level)
    n = img.size
    assert img.mean() == pytest.approx(level, abs=4 * sigma / math.sqrt(n) + 0.05)
    # rounding to integers adds 1/12 DN^2; the sample std has relative error ~ 1/sqrt(2n)
    assert img.std() == pytest.approx(math.sqrt(sigma ** 2 + 1 / 12), rel=5 / math.sqrt(2 * n) + 0.01)


def test_vignetting_darkens_corners_by_cos4():
    orthomap = make_map(np.full((400, 400, 3), 200, np.uint8))
    phot = Photometry(exposure_std=0.0, white_balance_std=0.0, gamma_std=0.0, read_noise_dn=0.0,
                      shot_noise_gain=0.0, vignetting=1.0)
    img = CameraRenderer(orthomap, CAM, phot).render(Pose(50.0, 50.0, 0.0, 20.0), np.random.default_rng(0)).image
    f_px = 30.0 / math.tan(math.radians(CAM.hfov_deg) / 2.0)
    r2 = 29.5 ** 2 + 19.5 ** 2
    corner = 200 * (f_px ** 2 / (f_px ** 2 + r2)) ** 2
    assert img[0, 0, 0] == pytest.approx(corner, abs=1.0)
    assert img[19:21, 29:31].min() >= 199


def test_exposure_jitter_changes_brightness_by_the_configured_amount():
    orthomap = make_map(np.full((400, 400, 3), 100, np.uint8))
    phot = Photometry(exposure_std=0.1, white_balance_std=0.0, gamma_std=0.0, read_noise_dn=0.0,
                      shot_noise_gain=0.0, vignetting=0.0)
    renderer = CameraRenderer(orthomap, CameraModel(width_px=8, height_px=8), phot)
    rng = np.random.default_rng(9)
    means = np.array([renderer.render(Pose(50.0, 50.0, 0.0, 20.0), rng).image.mean() for _ in range(400)])
    log_gain = np.log(means / 100.0)
    assert log_gain.std() == pytest.approx(0.1, rel=0.15)     # 400 samples: std error ~ 3.5 %; rounding < 1 %


def test_motion_blur_smears_along_the_heading_only():
    kernel = _motion_kernel(3.4)
    assert kernel.sum() == pytest.approx(1.0) and kernel.shape == (5, 1)
    assert (kernel.ravel() * (np.arange(5) - 2) ** 2).sum() == pytest.approx(3.4 ** 2 / 12, rel=0.15)
    stripes = np.zeros((400, 400, 3), np.uint8)
    stripes[:, ::8] = 255                           # north-south lines: parallel to a northward heading
    across = np.zeros((400, 400, 3), np.uint8)
    across[::8] = 255                               # east-west lines: across the heading
    phot = Photometry.ideal().__class__(**{**Photometry.ideal().__dict__, "exposure_time_s": 0.1})
    pose = Pose(50.0, 50.0, math.pi / 2, 20.0)
    for rgb, changes in ((stripes, False), (across, True)):
        r_blur = CameraRenderer(make_map(rgb), CAM, phot)
        sharp = r_blur.render(pose, np.random.default_rng(0)).image
        blurred = r_blur.render(pose, np.random.default_rng(0), speed_mps=10.0).image  # 1 m = 4 px
        assert (np.abs(sharp.astype(int) - blurred).max() > 50) == changes


def test_database_patch_resized_keeps_the_footprint():
    orthomap = make_map(smooth_map(800, feature_px=40))  # 10 m features, well above the 1 m patch pixels
    renderer = ideal(orthomap)
    pose = Pose(100.0, 100.0, 0.4, 40.0)
    full = renderer.database_patch(pose)
    small = renderer.database_patch(pose, size=(30, 20))
    assert small.shape == (20, 30, 3)
    ref = cv2.resize(full, (30, 20), interpolation=cv2.INTER_AREA).astype(float)
    assert np.abs(small.astype(float) - ref).mean() < 3.0


def test_bad_inputs_are_clear_errors():
    renderer = ideal(make_map(smooth_map()))
    with pytest.raises(ConfigError, match="finite"):
        renderer.render(Pose(float("nan"), 1.0, 0.0, 20.0), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="altitude_m"):
        renderer.render(Pose(50.0, 50.0, 0.0, -1.0), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="occlusion must be"):
        renderer.render(Pose(50.0, 50.0, 0.0, 20.0), np.random.default_rng(0), occlusion="shadows")


def test_pictures_writes_overview_and_frame_pairs(tmp_path):
    from aerial_loc_env.pictures import main, write_pictures

    rng = np.random.default_rng(4)
    rgb = smooth_map(600)
    dsm = np.zeros((600, 600), np.float32)
    for u, v in rng.integers(20, 560, (30, 2)):
        dsm[v:v + 20, u:u + 25] = rng.uniform(3.0, 12.0)
        rgb[v:v + 20, u:u + 25] = 200
    georef = LocalTangentGeoref(origin_lat_deg=47.0, origin_lon_deg=8.0, gsd_x_m=GSD, gsd_y_m=GSD)
    orthomap = Orthomap(rgb=rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=georef, dsm_m=dsm, name="tiny")
    written = write_pictures(tmp_path, seed=3, altitude_m=30.0, n_frames=2, orthomap=orthomap)
    names = sorted(p.name for p in written)
    assert names == sorted(["overview.png", "overview_shadows.png", "contact_sheet.png"]
                           + [f"frame_{k:02d}_{kind}.png" for k in range(2) for kind in ("database", "camera", "pair")])
    overview = cv2.imread(str(tmp_path / "overview.png"))
    assert overview.shape[1] == 600 and overview.shape[0] > 600          # the map plus a caption banner
    camera = cv2.imread(str(tmp_path / "frame_00_camera.png"))
    pair = cv2.imread(str(tmp_path / "frame_00_pair.png"))
    assert camera.shape == (400, 600, 3)
    assert np.array_equal(pair[-400:, 606:1206], camera)                # database | camera | mask
    assert main(["--out", str(tmp_path / "bad"), "--frames", "0"]) == 2


def test_rgb_and_rgba_warp_paths_give_the_same_bytes():
    orthomap = make_map(smooth_map(800))
    pose = Pose(97.3, 101.1, 2.1, 55.0)
    frames = [CameraRenderer(orthomap, CAM, noise_seed=1, rgba=flag).render(pose, np.random.default_rng(2))
              for flag in (True, False)]
    assert np.array_equal(frames[0].image, frames[1].image)


def test_warp_map_is_the_same_warp_as_database_patches():
    renderer = ideal(make_map(smooth_map(800)))
    pose = Pose(100.0, 90.0, -0.6, 70.0)
    view = renderer.warp_map(renderer.camera_to_map(pose), (CAM.width_px, CAM.height_px))
    assert np.array_equal(view, renderer.database_patch(pose))
    with pytest.raises(ConfigError, match="2x3"):
        renderer.warp_map(np.eye(3), (10, 10))
