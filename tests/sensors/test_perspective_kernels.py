"""The compiled perspective kernels against the OpenCV/NumPy implementation they replaced (perspective v5, kept in
``perspective_reference.py``): the same maps, facades and facing directions bit for bit, the same shaded facades,
over random cities, headings, heights (also above the 0.95 H cap), tilts, box origins, partial march blocks and a
map beyond remap's size limit."""

from __future__ import annotations

import math
import platform

import cv2
import numpy as np
import pytest
from perspective_reference import (
    _NEAREST,
    facade_gains_numpy,
    reference_maps,
    reference_shade_facades,
    reference_tilt,
    reference_tilted_corners,
)

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.sensors.camera import CameraModel, Pose
from aerial_loc_env.sensors.perspective import PerspectiveConfig, ReliefView, tilt_homography
from aerial_loc_env.sensors.render import CameraRenderer, Photometry
from aerial_loc_env.world.maps.geo import LocalTangentGeoref
from aerial_loc_env.world.maps.orthomap import Orthomap

GSD = 0.25
# the kernels reproduce OpenCV 5's nearest-neighbour warp arithmetic (float32 coefficients, FMA); OpenCV 4 rounds
# its probes in fixed point, so a probe within ~1e-4 px of a pixel boundary may round the other way there
EXACT = int(cv2.__version__.split(".")[0]) >= 5


def city(size_px: int, seed: int, buildings: int, tall_m: float = 40.0) -> Orthomap:
    """Random box buildings (2-``tall_m`` m, some with a ridge) on textured ground."""
    rng = np.random.default_rng(seed)
    rgb = cv2.resize(rng.integers(30, 230, (size_px // 8, size_px // 8, 3), dtype=np.uint8), (size_px, size_px),
                     interpolation=cv2.INTER_NEAREST)
    dsm = np.zeros((size_px, size_px), np.float32)
    for _ in range(buildings):
        u, v = rng.integers(0, size_px - 60, 2)
        w, h = rng.integers(8, 60, 2)
        dsm[v:v + h, u:u + w] = rng.uniform(2.0, tall_m)
        if rng.random() < 0.3:   # a ridged roof: heights varying across it
            dsm[v:v + h, u:u + w] += np.abs(np.arange(w, dtype=np.float32) - w / 2) * -0.2 + 2.0
        rgb[v:v + h, u:u + w] = rng.integers(60, 220, 3)
    georef = LocalTangentGeoref(origin_lat_deg=47.0, origin_lon_deg=8.0, gsd_x_m=GSD, gsd_y_m=GSD)
    return Orthomap(rgb=rgb, gsd_x_m=GSD, gsd_y_m=GSD, georef=georef, dsm_m=np.maximum(dsm, 0.0), name="city")


def assert_same_view(new, ref) -> None:
    assert (new is None) == (ref is None)
    if new is None:
        return
    assert new.bbox == ref.bbox and new.origin_px == ref.origin_px
    if not EXACT:
        assert np.mean((new.x != ref.x) | (new.y != ref.y)) < 1e-3
        return
    assert np.array_equal(new.x.view(np.int32), ref.x.view(np.int32))     # bit for bit (-0.0 too)
    assert np.array_equal(new.y.view(np.int32), ref.y.view(np.int32))
    assert (new.facade is None) == (ref.facade is None)
    if new.facade is not None:     # the same facades, listed in flat-index order (the reference: cell by cell)
        order = np.argsort(ref.facade, kind="stable")
        assert np.all(np.diff(new.facade) > 0)
        assert np.array_equal(new.facade, ref.facade[order]) and np.array_equal(new.facing, ref.facing[order])


@pytest.mark.parametrize(("seed", "size", "tilt_rad"), [
    (0, (600, 400), (0.0, 0.0)), (1, (600, 400), (0.004, -0.003)), (2, (301, 203), (0.0, 0.0)),
    (3, (301, 203), (-0.02, 0.015)), (4, (64, 48), (0.0, 0.0))])
def test_maps_equal_the_opencv_reference_bit_for_bit(seed, size, tilt_rad):
    om = city(1600, seed, 500)
    cam = CameraModel(width_px=size[0], height_px=size[1])
    r = CameraRenderer(om, cam, Photometry.ideal(), perspective=PerspectiveConfig(enabled=True))
    rng = np.random.default_rng(seed)
    tilt = tilt_homography(cam, *tilt_rad) if any(tilt_rad) else None
    facades = 0
    for altitude in (200.0, 120.0, 60.0, 40.0):      # 40 m: roofs above 0.95 H are capped
        for _ in range(3):
            pose = Pose(*rng.uniform(150.0, 250.0, 2), rng.uniform(-math.pi, math.pi), altitude)
            a = r.camera_to_map(pose)
            origin = tuple(int(o) for o in rng.integers(0, 400, 2)) if rng.random() < 0.5 else (0, 0)
            new = r._view.maps(a, altitude, cam, tilt, origin)
            assert_same_view(new, reference_maps(r._view, a, altitude, cam, tilt, origin))
            facades += 0 if new is None or new.facade is None else new.facade.size
    assert facades > 100      # the walls' branch ran


def test_flat_and_tilt_only_views_equal_the_reference():
    """No relief under the footprint (None: the affine warp), and a map without a height model, tilted."""
    om = city(1600, 5, 0)
    cam = CameraModel()
    view = ReliefView(om.dsm_m)
    flat = ReliefView(None)
    tilt = tilt_homography(cam, 0.01, -0.004)
    r = CameraRenderer(om, cam, Photometry.ideal())
    a = r.camera_to_map(Pose(200.0, 200.0, 0.4, 200.0))
    assert view.maps(a, 200.0, cam) is None
    assert_same_view(view.maps(a, 200.0, cam, tilt), reference_maps(view, a, 200.0, cam, tilt))
    assert_same_view(flat.maps(a, 200.0, cam, tilt, (30, 40)), reference_maps(flat, a, 200.0, cam, tilt, (30, 40)))


def test_a_map_beyond_remaps_size_limit_is_read_in_a_window_as_before():
    """A 32800 px wide height model: remap reads it in a window with the border replicated; so does the kernel."""
    rng = np.random.default_rng(7)
    dsm = np.zeros((1200, 32800), np.float32)
    for _ in range(300):
        u, v = rng.integers(31000, 32700), rng.integers(0, 1150)
        dsm[v:v + rng.integers(8, 50), u:u + rng.integers(8, 50)] = rng.uniform(2.0, 40.0)
    cam = CameraModel()
    view = ReliefView(dsm)
    for tilt in (None, tilt_homography(cam, 0.003, 0.002)):
        for yaw in (0.3, 2.0):
            c, s = math.cos(yaw), math.sin(yaw)
            a = np.array([[c, -s, 31900.0 - 299.5 * c + 199.5 * s], [s, c, 600.0 - 299.5 * s - 199.5 * c]])
            new = view.maps(a, 150.0, cam, tilt)
            assert new is not None and new.facade is not None
            assert_same_view(new, reference_maps(view, a, 150.0, cam, tilt))


@pytest.mark.parametrize("sun_deg", [None, (250.0, 35.0), (80.0, 12.0)])
def test_facade_shading_equals_the_reference(sun_deg):
    om = city(1600, 8, 500)
    r = CameraRenderer(om, CameraModel(), Photometry.ideal(), perspective=PerspectiveConfig(enabled=True))
    pose = Pose(200.0, 200.0, 0.7, 80.0)
    view = r._view.maps(r.camera_to_map(pose), 80.0, r.camera)
    assert view.facade is not None and view.facade.size > 100
    image = np.random.default_rng(1).integers(0, 256, (400, 600, 3), dtype=np.uint8)
    expected = reference_shade_facades(r._view, image.copy(), view, sun_deg, 2.2)
    got = r._view.shade_facades(image.copy(), view, sun_deg, 2.2)
    assert np.array_equal(got, expected)
    assert not np.array_equal(got, image)


@pytest.mark.parametrize("tilted", [False, True])
def test_top_height_is_the_maximum_of_opencvs_nearest_warp(tilted):
    """``perspective_kernels.top_height`` (the march's first height) equals ``cv2.minMaxLoc``'s maximum of OpenCV's
    nearest ``warpAffine`` / ``warpPerspective`` of the pooled window (zero border) over random warps, windows and
    grid sizes (rows that end inside the vector body and in the scalar tail), points inside, across and outside the
    window; negative heights too (the border's zeros then count). (OpenCV 4 rounds its probes in fixed point: there
    a probe near a pixel boundary may read its neighbour, and so may the maximum.)"""

    from aerial_loc_env.sensors import perspective_kernels as kernels

    rng = np.random.default_rng(3 + tilted)
    pooled = (rng.random((300, 300)) * 30.0 * (rng.random((300, 300)) < 0.2)).astype(np.float32)
    pooled[:40] -= 5.0
    seen_zero = seen_top = False
    differ = 0
    for _ in range(600):
        angle, scale = rng.uniform(-np.pi, np.pi), rng.uniform(0.2, 2.0)
        m = np.array([[scale * np.cos(angle), -scale * np.sin(angle), rng.uniform(-50.0, 200.0)],
                      [scale * np.sin(angle), scale * np.cos(angle), rng.uniform(-50.0, 200.0)],
                      [*(rng.normal(0.0, 1e-3, 2) if tilted else (0.0, 0.0)), 1.0]])
        r0, c0 = rng.integers(0, 150, 2)
        window = pooled[r0:r0 + rng.integers(1, 150), c0:c0 + rng.integers(1, 150)]
        hc, wc = int(rng.integers(1, 60)), int(rng.integers(1, 90))
        if tilted:
            warped = cv2.warpPerspective(window, m, (wc, hc), flags=_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        else:
            warped = cv2.warpAffine(window, m[:2], (wc, hc), flags=_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        expected = float(cv2.minMaxLoc(warped)[1])
        got = kernels.top_height[tilted](pooled, m.astype(np.float32).reshape(1, 9),
                                         np.array([r0, c0, *window.shape]), hc, wc)
        differ += got != expected
        seen_zero |= expected == 0.0
        seen_top |= expected > 10.0
    assert differ == 0 if EXACT else differ < 30
    assert seen_zero and seen_top


def test_facade_gains_kernel_equals_numpys_float32_arithmetic():
    """The sunlit facade gains (``perspective_kernels.facade_gains``, also inlined in ``view_finish``) equal NumPy's
    float32 formula bit for bit over random facings (the unit circle, its axes and diagonals, where the sun's
    direction term is 0 or negative), suns from grazing to overhead, gammas and facade albedos; without a sun both
    give the float64 constant."""
    from aerial_loc_env.sensors.perspective import ViewMaps

    rng = np.random.default_rng(8)
    angles = np.concatenate([rng.uniform(-np.pi, np.pi, 5000), np.arange(-4, 5) * (np.pi / 4)])
    facing = np.stack([np.cos(angles), np.sin(angles)], axis=1).astype(np.float32)
    plane = np.zeros((1, 1), np.float32)
    view = ViewMaps(plane, plane, np.arange(facing.shape[0]), (0.0, 0.0, 1.0, 1.0), facing)
    for _ in range(40):
        config = PerspectiveConfig(enabled=True, facade_gain=float(rng.uniform(0.05, 1.0)),
                                   ambient=float(rng.uniform(0.01, 1.0)))
        rv = ReliefView(None, config)
        sun = (float(rng.uniform(0.0, 360.0)), float(rng.choice([rng.uniform(0.5, 5.0), rng.uniform(5.0, 90.0)])))
        gamma = float(rng.uniform(0.5, 3.0))
        got, expected = rv.facade_gains(view, sun, gamma), facade_gains_numpy(rv, view, sun, gamma)
        assert got.dtype == expected.dtype == np.float32
        np.testing.assert_array_equal(got, expected)
        dark = got[np.argmin(facing @ np.array([math.sin(math.radians(sun[0])), math.cos(math.radians(sun[0]))]))]
        assert dark < got.max()     # walls facing away from the sun are darker than those facing it
        unlit = rv.facade_gains(view, None, gamma)
        assert unlit.dtype == np.float64 and np.all(unlit == config.facade_gain)


def test_a_view_the_caller_holds_is_never_overwritten():
    """The maps' planes are reused from frame to frame only once nothing holds the last frame's view."""
    om = city(1600, 9, 500)
    r = CameraRenderer(om, CameraModel(), Photometry.ideal(), perspective=PerspectiveConfig(enabled=True))
    poses = [Pose(200.0, 200.0, 0.3, 120.0), Pose(190.0, 210.0, 1.3, 120.0)]
    first = r._view.maps(r.camera_to_map(poses[0]), 120.0, r.camera)
    kept = first.x.copy(), first.y.copy()
    second = r._view.maps(r.camera_to_map(poses[1]), 120.0, r.camera)
    assert not np.shares_memory(first.x, second.x) and not np.shares_memory(first.y, second.y)
    assert np.array_equal(first.x, kept[0]) and np.array_equal(first.y, kept[1])
    x_plane = first.x
    del first
    third = r._view.maps(r.camera_to_map(poses[1]), 120.0, r.camera)
    assert not np.shares_memory(x_plane, third.x)          # a plane still held on its own is not reused either
    assert np.array_equal(third.x, second.x) and not np.shares_memory(third.x, second.x)
    del second, x_plane
    fourth = r._view.maps(r.camera_to_map(poses[0]), 120.0, r.camera)
    assert np.array_equal(fourth.x, kept[0])


def test_facade_shading_refuses_a_frame_the_kernel_cannot_write():
    """The kernel writes unchecked at the facade indices: a frame of another size, dtype or layout is refused."""
    om = city(1600, 8, 500)
    r = CameraRenderer(om, CameraModel(), Photometry.ideal(), perspective=PerspectiveConfig(enabled=True))
    view = r._view.maps(r.camera_to_map(Pose(200.0, 200.0, 0.7, 80.0)), 80.0, r.camera)
    assert view.facade is not None
    image = np.zeros((400, 600, 3), np.uint8)
    for bad in (image[:200], image.astype(np.float32), image[:, ::-1], image[..., 0]):
        with pytest.raises(ConfigError, match="shade_facades"):
            r._view.shade_facades(bad, view)


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"),
                    reason="the plan reproduces NumPy's products as OpenBLAS computes them on x86-64")
def test_the_plans_float64_products_are_numpys():
    """``plan_view``'s 3 x 3 products (``_mm3``) and its nadir point equal NumPy's ``@`` (OpenBLAS) bit for bit over
    random matrices of mixed magnitudes, both for plain 3 x 3 products and for a matrix times a stack (``probes``'
    broadcast); a plain sum of products differs from it in many entries (the test can fail)."""
    import numba

    from aerial_loc_env.sensors import perspective_kernels as kernels

    @numba.njit
    def products(p, q, out, a, cu, cv, nadir):
        for i in range(p.shape[0]):
            kernels._mm3(p[i], q[i], out[i])
        for i in range(a.shape[0]):
            nadir[i, 0] = kernels._fma64(a[i, 0, 0], cu, a[i, 0, 1] * cv) + a[i, 0, 2]
            nadir[i, 1] = kernels._fma64(a[i, 1, 0], cu, a[i, 1, 1] * cv) + a[i, 1, 2]

    rng = np.random.default_rng(11)
    n = 4000
    p = rng.normal(size=(n, 3, 3)) * 10.0 ** rng.uniform(-3, 3, (n, 3, 3))
    q = rng.normal(size=(n, 3, 3)) * 10.0 ** rng.uniform(-3, 3, (n, 3, 3))
    a = rng.normal(size=(n, 2, 3)) * 100.0
    out, nadir = np.empty_like(p), np.empty((n, 2))
    products(p, q, out, a, 299.5, 199.5, nadir)
    expected = np.array([p[i] @ q[i] for i in range(n)])
    assert np.array_equal(out, expected)
    stacked = p[0] @ q[:200]                      # a matrix times a stack, as ``probes`` broadcasts it
    products(np.broadcast_to(p[0], (200, 3, 3)).copy(), q[:200], out[:200], a[:0], 0.0, 0.0, nadir[:0])
    assert np.array_equal(out[:200], stacked)
    assert np.array_equal(nadir, np.array([a[i][:, :2] @ np.array([299.5, 199.5]) + a[i][:, 2] for i in range(n)]))
    plain = np.einsum("nij,njk->nik", p, q, optimize=False)
    assert np.mean(plain != expected) > 0.01


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"),
                    reason="the kernels reproduce NumPy's and OpenCV's arithmetic as they run on x86-64")
def test_the_tilt_and_the_footprint_are_numpys_and_opencvs():
    """``tilt_homography``, ``tilted_corners`` and ``footprint_px`` (compiled: ``tilt_matrix``, ``map_corners``)
    equal the NumPy products and ``cv2.perspectiveTransform`` + ``apply_affine`` they replaced, bit for bit, over
    random cameras, gimbal errors and poses (x86-64's arithmetic: see the plan's products above)."""
    from aerial_loc_env.sensors.camera import apply_affine
    from aerial_loc_env.sensors.perspective import footprint_px, tilted_corners

    rng = np.random.default_rng(12)
    for i in range(300):
        cam = CameraModel(width_px=int(rng.integers(40, 1200)), height_px=int(rng.integers(30, 900)),
                          hfov_deg=float(rng.uniform(20.0, 110.0)))
        roll, pitch = rng.normal(0.0, 0.05, 2) * (i % 3 != 0)      # every third untilted
        tilt = tilt_homography(cam, float(roll), float(pitch))
        if i % 3 == 0:
            assert tilt is None
        else:
            assert np.array_equal(tilt, reference_tilt(cam, float(roll), float(pitch)))
        assert np.array_equal(tilted_corners(cam, tilt), reference_tilted_corners(cam, tilt))
        yaw = rng.uniform(-np.pi, np.pi)
        a = np.array([[np.cos(yaw), -np.sin(yaw), rng.uniform(-1e4, 1e4)],
                      [np.sin(yaw), np.cos(yaw), rng.uniform(-1e4, 1e4)]]) * rng.uniform(0.1, 5.0, (2, 1))
        assert np.array_equal(footprint_px(a, cam, tilt), apply_affine(a, reference_tilted_corners(cam, tilt)))
