"""The perspective camera over the height model: relief displacement against the pinhole geometry, facades,
occlusion, shadows on the surfaces they fall on, the flat case against the affine warp, and the gimbal tilt."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.sensors.camera import CameraModel, Pose
from aerial_loc_env.sensors.perspective import PerspectiveConfig, ReliefView, footprint_px, tilt_homography
from aerial_loc_env.sensors.render import CameraRenderer, Photometry
from aerial_loc_env.world.maps.geo import LocalTangentGeoref
from aerial_loc_env.world.maps.orthomap import Orthomap
from aerial_loc_env.world.shadows import ShadowGrid

GSD = 0.25
SIZE_PX = 1600                     # a 400 m map
H = 200.0                          # flight height: the 600 x 400 camera sees 0.25 m/px, map level 0
CAM = CameraModel()
NADIR = Pose(200.0, 200.0, math.pi / 2, H)   # nose north: image u grows east, v grows south
GROUND, ROOF = 60, 220
FACADE = PerspectiveConfig(enabled=True).facade_gain * ROOF


def box_map(r_in_m: float, r_out_m: float, height_m: float, half_depth_m: float = 20.0,
            marker: tuple[float, float] | None = None) -> Orthomap:
    """Flat grey ground with one box building east of nadir spanning ground distances [r_in, r_out]."""
    rgb = np.full((SIZE_PX, SIZE_PX, 3), GROUND, np.uint8)
    dsm = np.zeros((SIZE_PX, SIZE_PX), np.float32)
    # world x = (u + 0.5) * gsd: the pixel boundary u + 0.5 = x / gsd
    u0, u1 = round((NADIR.x_m + r_in_m) / GSD), round((NADIR.x_m + r_out_m) / GSD)
    vc = SIZE_PX - NADIR.y_m / GSD
    v0, v1 = round(vc - half_depth_m / GSD), round(vc + half_depth_m / GSD)
    rgb[v0:v1, u0:u1] = ROOF
    dsm[v0:v1, u0:u1] = height_m
    if marker is not None:   # a ground stripe (red) at these ground distances
        m0, m1 = round((NADIR.x_m + marker[0]) / GSD), round((NADIR.x_m + marker[1]) / GSD)
        rgb[v0:v1, m0:m1] = (255, 0, 0)
    georef = LocalTangentGeoref(origin_lat_deg=47.0, origin_lon_deg=8.0, gsd_x_m=GSD, gsd_y_m=GSD)
    return Orthomap(rgb=rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=georef, dsm_m=dsm, name="box")


def renderer(orthomap: Orthomap, perspective: bool = True) -> CameraRenderer:
    cfg = PerspectiveConfig(enabled=True) if perspective else None
    return CameraRenderer(orthomap, CAM, Photometry.ideal(), perspective=cfg)


def centre_row(image: np.ndarray) -> np.ndarray:
    """Mean grey of the two rows around the principal point (v = 199.5), as float."""
    return image[199:201, :, 1].astype(np.float64).mean(axis=0)


def crossing(profile: np.ndarray, start: int, level: float, falling: bool) -> float:
    """Sub-pixel column (pixel centres at integers) where ``profile`` first crosses ``level`` after ``start``."""
    for j in range(start + 1, profile.size):
        a, b = profile[j - 1], profile[j]
        if (a >= level > b) if falling else (a < level <= b):
            return j - 1 + (a - level) / (a - b)
    raise AssertionError(f"no crossing of {level} after column {start}")


@pytest.mark.parametrize(("r_out", "height"), [(20.0, 50.0), (40.0, 60.0), (50.0, 30.0), (60.0, 20.0),
                                               (30.0, 10.0)])
def test_roof_edge_lands_where_the_pinhole_geometry_says(r_out, height):
    """A roof at height h, ground distance r from nadir, appears at r H / (H - h): displaced by r h / (H - h)."""
    r_in = r_out - 10.0
    image = renderer(box_map(r_in, r_out, height)).render(NADIR, np.random.default_rng(0)).image
    prof = centre_row(image)
    cu = CAM.center_px[0]
    scale = H / (H - height)
    # outer roof edge: roof -> ground (the far wall faces away from the camera)
    outer = crossing(prof, int(cu + r_in * scale / GSD) + 2, (ROOF + GROUND) / 2, falling=True)
    assert outer == pytest.approx(cu + r_out * scale / GSD, abs=1.0)
    # inner side: ground up to the wall's foot at r_in, facade up to the roof's inner edge at r_in H / (H - h)
    foot = crossing(prof, int(cu), (GROUND + FACADE) / 2, falling=False)
    assert foot == pytest.approx(cu + r_in / GSD, abs=1.0)
    inner = crossing(prof, int(foot) + 1, (FACADE + ROOF) / 2, falling=False)
    assert inner == pytest.approx(cu + r_in * scale / GSD, abs=1.0)
    mid = int(round(cu + r_in * (1 + scale) / 2 / GSD))
    assert prof[mid] == pytest.approx(FACADE, abs=2.0)
    # the affine warp puts the whole roof on its ground footprint
    flat = centre_row(renderer(box_map(r_in, r_out, height), perspective=False).render(
        NADIR, np.random.default_rng(0)).image)
    assert crossing(flat, int(cu + r_in / GSD) + 2, (ROOF + GROUND) / 2, True) == pytest.approx(
        cu + r_out / GSD, abs=0.6)


def test_ground_behind_a_tall_building_is_hidden():
    """A red ground stripe just beyond a 50 m building's far edge is hidden in perspective, seen when flat."""
    om = box_map(30.0, 45.0, 50.0, marker=(46.0, 50.0))     # hidden up to 45 * 50 / 150 = 15 m beyond the edge
    red = [(r.render(NADIR, np.random.default_rng(0)).image[150:250, :, :] == (255, 0, 0)).all(axis=2).sum()
           for r in (renderer(om), renderer(om, perspective=False))]
    assert red[0] == 0 and red[1] > 1000


def test_shadows_stay_on_the_roof_they_fall_on():
    """A shadow field covering exactly the roof (map coordinates) shades exactly the displaced roof and facades."""
    om = box_map(30.0, 50.0, 40.0)
    occlusion = (om.dsm_m > 0).astype(np.float32)
    r = renderer(om)
    plain = r.render(NADIR, np.random.default_rng(0)).image
    frame = r.render(NADIR, np.random.default_rng(0), occlusion, {"strength": 1.0})
    building = plain[..., 1] > (GROUND + FACADE) / 2
    union = (building | frame.shadow_mask).sum()
    assert (building & frame.shadow_mask).sum() / union > 0.98
    assert frame.image[building].mean() < 0.6 * plain[building].mean()


def test_zero_height_model_gives_the_affine_frame_bit_for_bit():
    om = box_map(30.0, 50.0, 0.0)
    occlusion = np.zeros(om.dsm_m.shape, np.float32)
    occlusion[700:900, 700:900] = 1.0
    frames = [CameraRenderer(om, CAM, Photometry(), perspective=cfg).render(
        Pose(190.0, 205.0, 0.3, H), np.random.default_rng(5), occlusion, {"strength": 0.8}, speed_mps=20.0)
        for cfg in (None, PerspectiveConfig(enabled=True))]
    assert np.array_equal(frames[0].image, frames[1].image)
    assert np.array_equal(frames[0].occlusion, frames[1].occlusion)
    # and with the shadows baked into the map (the env's path for a lone cast-shadow grid)
    grid = ShadowGrid(np.ascontiguousarray(occlusion[::2, ::2]), 2 * GSD, 2 * GSD, 2)
    baked = []
    for cfg in (None, PerspectiveConfig(enabled=True)):
        r = CameraRenderer(om, CAM, Photometry(), perspective=cfg)
        box = r.bake(grid, {"strength": 0.8}, (300, 300, 1300, 1300))
        baked.append(r.render(Pose(190.0, 205.0, 0.3, H), np.random.default_rng(5), box, speed_mps=20.0))
    assert np.array_equal(baked[0].image, baked[1].image)
    assert np.array_equal(baked[0].shadow_mask, baked[1].shadow_mask)


@pytest.mark.parametrize("tilt_rad", [(0.0, 0.0), (0.004, -0.003)])
def test_maps_in_a_box_frame_are_the_map_frame_maps_shifted(tilt_rad):
    """A baked box is sampled through maps made in the box's pixels (``origin_px``): the same decisions (facades),
    the same points up to float32 rounding (coordinates below 1024 px: half an ulp, 6e-5 px, per operation); every
    sample lies in ``reads_px``'s box, the bake's coverage test."""
    r = renderer(box_map(30.0, 50.0, 40.0))
    a = r.camera_to_map(NADIR)
    tilt = tilt_homography(CAM, *tilt_rad) if any(tilt_rad) else None
    view = r._view.maps(a, H, CAM, tilt)
    boxed = r._view.maps(a, H, CAM, tilt, origin_px=(517, 333))
    assert boxed.origin_px == (517, 333)
    assert np.abs(boxed.xy - view.xy).max() < 1e-3
    assert view.facade.size > 100 and np.array_equal(np.sort(view.facade), np.sort(boxed.facade))
    reads = r._view.reads_px(a, CAM, tilt)
    lo, hi = reads.min(axis=0), reads.max(axis=0)
    assert lo[0] <= view.x.min() and view.x.max() <= hi[0] and lo[1] <= view.y.min() and view.y.max() <= hi[1]


@pytest.mark.parametrize("tilt_rad", [(0.0, 0.0), (0.004, -0.003)])
@pytest.mark.parametrize("relief", [True, False])
def test_the_reads_bounds_are_reads_pxs(tilt_rad, relief):
    """``reads_bounds_px`` (the renderer's cover test and tile range, in plain Python) is the box of ``reads_px``'s
    points, bit for bit, with a height model and without one."""
    r = renderer(box_map(30.0, 50.0, 40.0))
    view = r._view if relief else ReliefView(None)
    tilt = tilt_homography(CAM, *tilt_rad) if any(tilt_rad) else None
    for pose in (NADIR, Pose(183.7, 221.3, 1.1, H)):
        a = r.camera_to_map(pose)
        reads = view.reads_px(a, CAM, tilt)
        assert view.reads_bounds_px(footprint_px(a, CAM, tilt)) == (*reads.min(axis=0).tolist(),
                                                                    *reads.max(axis=0).tolist())


def test_remap_path_with_negligible_relief_matches_the_affine_warp_within_interpolation():
    """A 1 mm bump forces the per-pixel path; away from it the frame equals the affine warp within 1 DN (both
    interpolate bilinearly on OpenCV's 1/32-pixel grid)."""
    rng = np.random.default_rng(3)
    om = box_map(30.0, 50.0, 0.0)
    import cv2

    rgb = cv2.resize(rng.integers(0, 256, (200, 200, 3), dtype=np.uint8), (SIZE_PX, SIZE_PX),
                     interpolation=cv2.INTER_CUBIC)
    dsm = np.zeros_like(om.dsm_m)
    dsm[800, 800] = 1e-3
    om = Orthomap(rgb=rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=om.georef, dsm_m=dsm, name="bump")
    pose = Pose(199.0, 201.0, 0.4, H)
    flat = renderer(om, perspective=False).render(pose, np.random.default_rng(0)).image.astype(int)
    persp = renderer(om).render(pose, np.random.default_rng(0)).image.astype(int)
    assert np.abs(flat - persp).max() <= 1


@pytest.mark.parametrize(("roll", "pitch"), [(0.0, 0.01), (0.01, 0.0), (-0.005, 0.008)])
def test_tilt_moves_the_principal_point_by_h_tan_angle(roll, pitch):
    """Positive pitch looks ahead (north here), positive roll to the right (east): by H tan(angle)."""
    om = box_map(30.0, 50.0, 0.0)
    om = Orthomap(rgb=om.rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=om.georef, dsm_m=None, name="flat")
    r = renderer(om)
    tilt = tilt_homography(CAM, roll, pitch)
    view = r._view.maps(r.camera_to_map(NADIR), H, CAM, tilt)
    cu, cv = CAM.center_px
    x, y = view.xy[int(cv), int(cu)]   # pixel (299, 199): half a pixel from centre
    east = (x + 0.5) * GSD - NADIR.x_m + 0.5 * GSD
    north = SIZE_PX * GSD - (y + 0.5) * GSD - NADIR.y_m - 0.5 * GSD
    assert east == pytest.approx(H * math.tan(roll), abs=0.02)
    assert north == pytest.approx(H * math.tan(pitch), abs=0.02)


def test_env_perspective_is_deterministic_and_changes_only_the_frames():
    import gymnasium as gym

    import aerial_loc_env  # noqa: F401

    def episode(**overrides) -> tuple[list[np.ndarray], list[np.ndarray]]:
        env = gym.make("AerialLoc/Small-v3", flight={"duration_s": 2.0}, **overrides)
        obs, info = env.reset(seed=11)
        frames, poses = [obs["image"]], [info["true_pose"]]
        done = False
        while not done:
            obs, _, term, trunc, info = env.step(np.zeros(2, np.float32))
            frames.append(obs["image"])
            poses.append(info["true_pose"])
            done = term or trunc
        env.close()
        return frames, poses

    a, pa = episode(perspective={"enabled": True})
    b, pb = episode(perspective={"enabled": True})
    flat, pf = episode()
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert all(np.array_equal(x, y) for x, y in zip(pa, pf, strict=True))   # same track: no extra draws
    assert any(not np.array_equal(x, y) for x, y in zip(a, flat, strict=True))


def test_map_without_height_model_keeps_the_affine_warp():
    om = box_map(30.0, 50.0, 40.0)
    flat = Orthomap(rgb=om.rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=om.georef, dsm_m=None, name="no-dsm")
    frames = [CameraRenderer(flat, CAM, Photometry(), perspective=cfg).render(NADIR, np.random.default_rng(2))
              for cfg in (None, PerspectiveConfig(enabled=True))]
    assert np.array_equal(frames[0].image, frames[1].image)


def test_tilted_relief_path_agrees_with_the_nadir_one_at_negligible_tilt():
    """The tilted path (rays through the homography, a margin around the march grid) gives the nadir maps."""
    om = box_map(30.0, 50.0, 40.0)
    r = renderer(om)
    a = r.camera_to_map(NADIR)
    nadir = r._view.maps(a, H, CAM, None)
    tilted = r._view.maps(a, H, CAM, tilt_homography(CAM, 1e-9, -1e-9))
    close = np.abs(tilted.xy - nadir.xy).max(axis=2) < 1e-2
    assert close.mean() > 0.999


@pytest.mark.parametrize(("azimuth", "lit"), [(270.0, True), (90.0, False)])
def test_facades_are_lit_by_the_sun_they_face(azimuth, lit):
    """The visible wall of a building east of nadir faces west: a western sun lights it, an eastern one leaves it
    the sky's half (linear light ambient / 2), both times the facade albedo and the 2.2 tone curve."""
    cfg = PerspectiveConfig(enabled=True)
    r = CameraRenderer(box_map(40.0, 55.0, 50.0), CAM, Photometry.ideal(), perspective=cfg)
    image = r.render(NADIR, np.random.default_rng(0), sun_deg=(azimuth, 30.0)).image
    prof = centre_row(image)
    mid = int(round(CAM.center_px[0] + 40.0 * (1 + H / (H - 50.0)) / 2 / GSD))
    el = math.radians(30.0)
    linear = 0.5 * cfg.ambient + (1 - cfg.ambient) / math.tan(el) if lit else 0.5 * cfg.ambient
    assert prof[mid] == pytest.approx(ROOF * cfg.facade_gain * min(linear, 1.5) ** (1 / 2.2), abs=1.0)


def test_flat_ground_keeps_the_affine_map_coordinates_and_the_roof_moves():
    """Pixels whose neighbourhood is flat ground skip the refinement: exactly the affine coordinates there; the
    roof (east of nadir, r h / (H - h) further out) does not."""
    r = renderer(box_map(30.0, 50.0, 40.0))
    a = r.camera_to_map(NADIR)
    view = r._view.maps(a, H, CAM)
    u, v = np.meshgrid(np.arange(CAM.width_px, dtype=np.float64), np.arange(CAM.height_px, dtype=np.float64))
    affine_xy = np.dstack([a[0, 0] * u + a[0, 1] * v + a[0, 2], a[1, 0] * u + a[1, 1] * v + a[1, 2]])
    west = slice(0, CAM.width_px // 2 - 10)     # the building is east of nadir: the west half is open ground
    assert np.abs(view.xy[:, west] - affine_xy[:, west]).max() < 1e-3
    roof = (slice(190, 210), slice(CAM.width_px // 2 + 200, CAM.width_px // 2 + 240))   # ~50-60 m east: roof
    assert np.abs(view.xy[roof] - affine_xy[roof]).max() > 1.0


@pytest.mark.parametrize(("tilt_rad", "size"), [((0.0, 0.0), (600, 400)), ((0.004, -0.003), (600, 400)),
                                                 ((0.004, -0.003), (301, 203))])   # partial 4 x 4 blocks
@pytest.mark.slow
def test_visible_point_is_the_first_hit_of_a_fine_ray_cast_away_from_edges(tilt_rad, size):
    """Against a brute-force ray cast (every ray probed every 10 cm from the top down: its point within 0.25 px):
    the coarse march (one ray per 4 x 4 block, 10 heights) plus the fixed-point steps give each non-facade pixel
    the first surface its ray hits, to within 1 px on the map, everywhere farther than one march cell (4 px, + 1
    for the dilation) from a change of the visible height; near such edges a few pixels may take the other
    side's surface."""
    import cv2

    om = box_map(30.0, 50.0, 40.0)
    dsm = om.dsm_m.copy()
    for u0, v0, side, h in [(560, 700, 60, 12.0), (900, 620, 90, 25.0), (700, 900, 40, 6.0), (1000, 860, 70, 33.0)]:
        dsm[v0:v0 + side, u0:u0 + side] = h
    om = Orthomap(rgb=om.rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=om.georef, dsm_m=dsm, name="boxes")
    cam = CameraModel(width_px=size[0], height_px=size[1])
    r = CameraRenderer(om, cam, Photometry.ideal(), perspective=PerspectiveConfig(enabled=True))
    a = r.camera_to_map(NADIR)
    tilt = tilt_homography(cam, *tilt_rad) if any(tilt_rad) else None
    view = r._view.maps(a, H, cam, tilt)
    rays = np.stack(np.meshgrid(np.arange(cam.width_px, dtype=np.float64), np.arange(cam.height_px, dtype=np.float64)),
                    axis=-1).reshape(-1, 1, 2)
    if tilt is not None:
        rays = cv2.perspectiveTransform(rays, tilt)
    ground = (rays.reshape(-1, 2) @ a[:, :2].T + a[:, 2]).reshape(cam.height_px, cam.width_px, 2)
    nadir = a[:, :2] @ np.array(cam.center_px) + a[:, 2]
    first = np.full(ground.shape[:2], -1.0)
    for z in np.arange(dsm.max(), -1e-9, -0.1):
        pts = (nadir + (ground - nadir) * (1.0 - z / H)).astype(np.float32)
        hit = (first < 0) & (cv2.remap(dsm, pts[..., 0], pts[..., 1], cv2.INTER_NEAREST) >= z - 1e-6)
        first[hit] = z
    first = np.maximum(first, 0.0)
    exact = nadir + (ground - nadir) * (1.0 - first / H)[..., None]
    err = np.hypot(view.x - exact[..., 0], view.y - exact[..., 1])
    edge = np.zeros(first.shape, np.uint8)
    edge[:, 1:] |= np.abs(np.diff(first, axis=1)) > 0.3
    edge[1:, :] |= np.abs(np.diff(first, axis=0)) > 0.3
    near_edge = cv2.dilate(edge, np.ones((11, 11), np.uint8)) > 0
    facade = np.zeros(first.size, bool)
    facade[view.facade] = True
    far = ~near_edge & ~facade.reshape(first.shape)
    assert far.mean() > 0.8 and (first[far] > 0).mean() > 0.05          # roofs away from their edges count
    assert err[far].max() <= 1.0
    assert (err[~facade.reshape(first.shape)] > 1.0).mean() < 0.02       # a band a few pixels wide at edges


def test_a_held_views_facades_are_never_overwritten():
    """The facade lists are views of buffers reused from frame to frame only once no view of them is alive: a view
    the caller keeps keeps its facades while later frames are made."""
    r = renderer(box_map(40.0, 55.0, 50.0))
    first = r._view.maps(r.camera_to_map(NADIR), H, CAM)
    assert first.facade is not None and first.facade.size > 100
    kept = first.facade.copy(), first.facing.copy()
    moved = Pose(NADIR.x_m + 8.0, NADIR.y_m - 5.0, NADIR.yaw_rad + 0.2, H)
    second = r._view.maps(r.camera_to_map(moved), H, CAM)
    assert second.facade is not None and not np.shares_memory(first.facade, second.facade)
    assert not np.shares_memory(first.facing, second.facing)
    assert np.array_equal(first.facade, kept[0]) and np.array_equal(first.facing, kept[1])
    assert not np.array_equal(second.facade[:kept[0].size], kept[0])     # the second frame's walls differ
    facade = first.facade
    del first
    third = r._view.maps(r.camera_to_map(moved), H, CAM)
    assert not np.shares_memory(facade, third.facade)     # a facade list still held on its own is not reused
    assert np.array_equal(facade, kept[0]) and np.array_equal(third.facade, second.facade)
