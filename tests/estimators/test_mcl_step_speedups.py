"""The MCL step's fixed costs made cheaper (issue 12) against the code they replaced, kept here as references.

Every change here keeps the arithmetic (the same float operations on the same operands, or exact integer sums),
so the outputs must be bit-identical; the one exception, the closed-form largest eigenvalue of the estimate's
2x2 covariance, has its tolerance derived in its test.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.estimate import max_std_m
from aerial_loc_env.estimators.mcl.motion import OdometryMotionModel, mid_heading, wrap
from aerial_loc_env.estimators.protocol import Observation
from aerial_loc_env.estimators.shadow_detection import (
    ShadowDetector,
    ShadowDetectorConfig,
    ShadowMask,
    _disc,
    _masked_channel_means,
    _OpenClose,
    shadow_index,
)
from aerial_loc_env.estimators.shadow_detection_kernels import _pairwise_sum
from aerial_loc_env.sensors.camera import CameraModel, world_to_map_affine


# ---------------------------------------------------------------------- references: the replaced code
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


def _propagate_reference(m: OdometryMotionModel, states: np.ndarray, obs: Observation,
                         rng: np.random.Generator) -> np.ndarray:
    """One ``rng.normal`` call per noise term (the code before the single draw)."""
    n = states.shape[0]
    k, dt = m.noise_scale, m.dt_s
    v = obs.speed_mps + rng.normal(0.0, m.noise.speed_std_mps * k, n)
    if m.state == "xy":
        heading = mid_heading(m.prev_yaw_rad, obs.yaw_rad, obs.yaw_rate_radps, dt)
        psi = heading + rng.normal(0.0, m.noise.heading_std_rad * k / math.sqrt(2.0), n)
        states[:, 0] += v * dt * np.cos(psi)
        states[:, 1] += v * dt * np.sin(psi)
        states[:, 2] = wrap(obs.yaw_rad + rng.normal(0.0, m.noise.heading_std_rad * k, n))
    else:
        omega = obs.yaw_rate_radps + rng.normal(0.0, m.noise.yaw_rate_std_radps * k, n)
        psi = states[:, 2] + 0.5 * omega * dt
        states[:, 0] += v * dt * np.cos(psi)
        states[:, 1] += v * dt * np.sin(psi)
        states[:, 2] = wrap(states[:, 2] + omega * dt)
    if m.jitter_std_m > 0:
        states[:, :2] += rng.normal(0.0, m.jitter_std_m, (n, 2))
    m.prev_yaw_rad = obs.yaw_rad
    return states


# ---------------------------------------------------------------------- camera
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



@pytest.mark.parametrize("gsd_xy", [(0.25, 0.25), (0.3, 0.21), (1.0, 0.5)])
def test_pair_kernels_affine_is_camera_to_map_bit_for_bit(gsd_xy):
    """``intensity_pairs_kernels.pose_affine`` (the pair kernel's per-particle affine, from NumPy's cos and sin of the
    yaw column) gives ``camera_to_map``'s floats: on- and off-map poses, any yaw, several altitudes and cameras."""
    from aerial_loc_env.estimators.mcl.intensity_pairs_kernels import pose_affines

    grid = SimpleNamespace(gsd_x_m=gsd_xy[0], gsd_y_m=gsd_xy[1], height_px=1234)
    g = np.random.default_rng(8)
    n = 5000
    states = np.column_stack([g.uniform(-50, 900, n), g.uniform(-50, 900, n), g.uniform(-7, 7, n)])
    states[:3] = [[np.nan, 1.0, 0.0], [1.0, np.inf, 0.3], [2.0, 3.0, np.nan]]
    for cam in (CameraModel(), CameraModel(width_px=640, height_px=360, hfov_deg=50.0, pixel_aspect=1.1)):
        for alt in (200.0, 173, np.float64(88.8), np.float32(123.4)):
            ref = cam.camera_to_map(grid, states[:, 0], states[:, 1], states[:, 2], alt)
            yaw = states[:, 2]
            out = pose_affines(cam.affine_terms(grid, alt), states, np.cos(yaw), np.sin(yaw), np.empty((n, 2, 3)))
            np.testing.assert_array_equal(out, ref)
    with pytest.raises(ConfigError, match="altitude_m"):
        CameraModel().affine_terms(grid, float("nan"))

# ---------------------------------------------------------------------- motion
@pytest.mark.parametrize("state", ["xy", "xyyaw"])
@pytest.mark.parametrize("jitter", [0.0, 0.5])
@pytest.mark.parametrize("scale", [1.0, 2.5])
def test_one_normal_draw_moves_the_particles_as_one_call_per_term(state, jitter, scale):
    noise = SimpleNamespace(speed_std_mps=0.3, yaw_rate_std_radps=0.05, heading_std_rad=0.035)
    new = OdometryMotionModel(noise, 0.25, state=state, noise_scale=scale, jitter_std_m=jitter)
    ref = OdometryMotionModel(noise, 0.25, state=state, noise_scale=scale, jitter_std_m=jitter)
    g = np.random.default_rng(2)
    s0 = np.column_stack([g.uniform(0, 500, 700), g.uniform(0, 500, 700), g.uniform(-np.pi, np.pi, 700)])
    a, b = s0.copy(), s0.copy()
    ra, rb = np.random.default_rng(11), np.random.default_rng(11)
    for t, yaw in enumerate((0.4, 3.13, -3.1405, 1e-17, -np.pi, 2.0)):   # headings across the wrap too
        obs = Observation(np.zeros((4, 4, 3), np.uint8), 12.0 + t, 0.02 * t - 0.05, yaw, 200.0)
        new.propagate(a, obs, ra)
        _propagate_reference(ref, b, obs, rb)
        np.testing.assert_array_equal(a, b)
    assert ra.random() == rb.random()        # the same number of draws: later draws are unchanged too



def _normalize_reference(log_w: np.ndarray) -> tuple[np.ndarray, float]:
    """``normalize_log_weights`` as it was: the non-finite values masked to -inf first, always."""
    lw = np.where(np.isfinite(log_w), log_w, -np.inf)
    m = float(np.max(lw))
    if not np.isfinite(m):
        return np.full(lw.shape[0], 1.0 / lw.shape[0]), -np.inf
    w = np.exp(lw - m)
    s = float(w.sum())
    return w / s, m + float(np.log(s / lw.shape[0]))


def test_normalization_skips_the_mask_only_where_it_changes_nothing():
    """Weights and log-mean (also ``log_mean_weight`` alone) equal the always-masking form bit for bit: finite
    log-weights of many scales, with -inf, +inf and NaN among them, and none finite."""
    from aerial_loc_env.estimators.mcl.resampling import log_mean_weight, normalize_log_weights

    g = np.random.default_rng(4)
    for t in range(300):
        n = int(g.integers(1, 900))
        lw = g.normal(g.uniform(-1e3, 1e3), 10 ** g.uniform(-3, 3), n)
        for bad, p in ((-np.inf, 0.2), (np.inf, 0.01), (np.nan, 0.01)):
            if t % 4 == 1 or (t % 4 == 2 and bad != -np.inf):
                lw[g.random(n) < p] = bad
        if t % 50 == 3:
            lw[:] = [-np.inf, np.nan][t % 2]
        W, lm = normalize_log_weights(lw)
        ref_W, ref_lm = _normalize_reference(lw)
        np.testing.assert_array_equal(W, ref_W)
        assert lm == ref_lm or (np.isnan(lm) and np.isnan(ref_lm))
        assert log_mean_weight(lw) == lm or (np.isnan(lm) and np.isnan(log_mean_weight(lw)))


def test_one_frames_activation_is_the_array_forms_float():
    """Eq. (8) for one frame (int K and lc, float gain) in Python floats, against its array form."""
    from aerial_loc_env.estimators.mcl.intensity_pairs import activation

    g = np.random.default_rng(6)
    for K in (1, 7, 30, 70, 333, 10_000):
        for lc in sorted({0, 1, K // 2, K - 1, K, *(int(v) for v in g.integers(0, K + 1, 20))}):
            for gain in (0.0, 1.0, 10.0, 47.3, 1000.0):
                a = gain / K
                fast = activation(K, lc, a)
                assert isinstance(fast, float)
                assert fast == float(activation(np.array([K]), np.array([lc]), np.array([a]))[0])

# ---------------------------------------------------------------------- estimate
def test_closed_form_spread_matches_eigvalsh():
    """``(a + c)/2 + hypot((a - c)/2, b)`` adds two non-negative terms (no cancellation), each within 1-2 ulp;
    LAPACK's symmetric solver is backward stable (a few ulp of ||cov||, and the largest eigenvalue is
    ||cov||): so relative agreement to 8 ulp (2e-15) of the eigenvalue, half that on its square root."""
    g = np.random.default_rng(5)
    covs = [np.zeros((2, 2)), np.diag([4.0, 4.0]), np.diag([1e-9, 1e6]), np.array([[1.0, 1.0], [1.0, 1.0]])]
    for _ in range(2000):
        m = g.normal(size=(2, 2)) * 10 ** g.uniform(-3, 4)
        covs.append(m @ m.T)
    for cov in covs:
        ref = float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))
        assert max_std_m(cov) == pytest.approx(ref, rel=1e-15 * 8 / 2, abs=1e-300)


# ---------------------------------------------------------------------- shadow detector
def test_luminance_means_from_exact_sums_equal_the_masked_means():
    g = np.random.default_rng(3)
    for shape in [(100, 150), (7, 9), (1, 300)]:
        lum = g.integers(0, 256, shape).astype(np.float32)
        for p in (0.01, 0.3, 0.9):
            mask = g.random(shape) < p
            if not mask.any() or mask.all():
                continue
            out_mean, in_mean = _masked_channel_means(lum, mask)
            assert float(in_mean[0]) == float(lum[mask].mean())
            assert float(out_mean[0]) == float(lum[~mask].mean())
            assert ShadowMask(mask, shape).fraction == float(mask.mean())


def test_pairwise_sum_is_numpys_float32_sum():
    """The detector's compiled sum against NumPy's float32 ``mean`` (its pairwise ``add.reduce``), sizes from
    short runs to above 16 384 (three levels of halving), bit for bit."""
    g = np.random.default_rng(0)
    for t in range(600):
        n = int(g.integers(1, 40000)) if t % 3 else int(g.integers(1, 300))
        a = (g.random(n) * g.uniform(0.1, 300)).astype(np.float32)
        assert np.float32(_pairwise_sum(a, 0, n)) / np.float32(n) == a.mean()


def _detect_reference(det: ShadowDetector, image: np.ndarray) -> np.ndarray:
    """The detector as it was (before its compiled passes): the float32 index image from ``shadow_index``,
    NumPy's masked (``compress``) float32 means; the mask (h, w) bool."""
    small = det.reduce(image)
    idx, lum, c3 = shadow_index(small, det.config.index)
    idx8 = np.clip(idx * 255.0, 0, 255).astype(np.uint8)
    _, binary = cv2.threshold(idx8, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    mask = binary.astype(bool)
    if not mask.any() or mask.all():
        return np.zeros(mask.shape, bool)
    inside, outside = mask.ravel(), ~mask.ravel()
    ratio = float(np.compress(inside, lum).mean()) / max(float(np.compress(outside, lum).mean()), 1e-6)
    bluer = c3 is None or (float(np.compress(inside, c3).mean()) - float(np.compress(outside, c3).mean())
                           >= det.config.min_blue_shift)
    if ratio > det.config.max_luminance_ratio or not bluer:
        return np.zeros(mask.shape, bool)
    return _open_close_reference(binary, det.config.open_px, det.config.close_px)


def _open_close_reference(binary: np.ndarray, open_px: int, close_px: int) -> np.ndarray:
    """The detectors' morphology as it was: OpenCV's opening, then closing, by discs; the mask as bool."""
    if open_px > 0:
        binary = cv2.morphologyEx(binary, cv2.MORPH_OPEN, _disc(open_px))
    if close_px > 0:
        binary = cv2.morphologyEx(binary, cv2.MORPH_CLOSE, _disc(close_px))
    return binary.astype(bool)


@pytest.mark.parametrize("radii", [(1, 1), (0, 1), (1, 0), (0, 0), (2, 3), (5, 1), (12, 7)])
def test_compiled_opening_and_closing_are_opencvs(radii):
    """``_OpenClose`` against ``cv2.morphologyEx`` with the same discs: masks of many sizes (down to one pixel,
    one row, one column, smaller than the disc), densities and blob sizes, specks and holes at the borders."""
    op = _OpenClose(*radii)
    g = np.random.default_rng(sum(radii) + 10 * radii[0])
    for t in range(60):
        h, w = (int(v) for v in g.integers(1, 160, 2)) if t % 4 else [(1, 1), (1, 57), (43, 1), (3, 4)][t // 4 % 4]
        mask = g.random((h, w)) < g.uniform(0.02, 0.98)
        if t % 2:                                    # blobs: a blurred field thresholded
            mask = cv2.GaussianBlur(g.random((h, w)).astype(np.float32), (0, 0), 1 + t % 5) > 0.5
        binary = mask.astype(np.uint8)
        out = op(binary)
        assert out.dtype == np.bool_ and out.shape == (h, w)
        np.testing.assert_array_equal(out, _open_close_reference(binary, *radii))
        np.testing.assert_array_equal(binary, mask)          # the input is left as it was


@pytest.mark.parametrize("index", ["c3_luminance", "c3", "luminance", "tsai"])
@pytest.mark.parametrize("scale", [0.25, 0.7])
def test_detector_kernels_keep_the_masks_of_the_numpy_path(index, scale):
    """The compiled index/quantization and class statistics against the NumPy path (masked means; exact for
    8-bit luminance sums below 2^24, pairwise float32 above: scale 0.7 of a 600 x 400 frame is 117 600 px),
    over frames with darkened, blued shadows of many sizes and strengths, and frames without."""
    g = np.random.default_rng(9)
    det = ShadowDetector(ShadowDetectorConfig(index=index, scale=scale))
    decided = 0
    for k in range(24):
        img = cv2.GaussianBlur(g.normal(120, 40, (400, 600, 3)), (0, 0), 1 + k % 4)
        img = np.clip(img, 0, 255).astype(np.uint8)
        if k % 6:
            y0, x0 = g.integers(0, 300, 2)
            gain = np.array([0.3, 0.35, 0.5]) + g.uniform(0, 0.4)
            img[y0:y0 + 40 + 8 * k, x0:x0 + 300] = (img[y0:y0 + 40 + 8 * k, x0:x0 + 300] * gain).astype(np.uint8)
        mask = det.detect(img).mask
        np.testing.assert_array_equal(mask, _detect_reference(det, img))
        decided += bool(mask.any())
    assert (1 if index == "tsai" else 6) <= decided <= 22   # shadows found on shadowed frames, not on all frames


def test_quarter_reduction_is_cv2_resize():
    """The default scale's reduction (1/4 of a frame whose sides are multiples of 4) against ``cv2.resize``'s
    bilinear result: random bytes over every value, frames from 4 x 4 up, and the detector's ``reduce`` still
    OpenCV's at other scales and sizes."""
    from aerial_loc_env.estimators.shadow_detection_kernels import _quarter

    g = np.random.default_rng(12)
    for h, w in [(400, 600), (4, 4), (8, 12), (404, 604), (1200, 1600), (36, 4), (4, 88)]:
        img = g.integers(0, 256, (h, w, 3)).astype(np.uint8)
        ref = cv2.resize(img, (w // 4, h // 4), interpolation=cv2.INTER_LINEAR)
        np.testing.assert_array_equal(_quarter(img), ref)
        np.testing.assert_array_equal(ShadowDetector(ShadowDetectorConfig(scale=0.25)).reduce(img), ref)
    img = g.integers(0, 256, (402, 600, 3)).astype(np.uint8)
    for scale in (0.25, 0.3, 0.5):
        size = (round(600 * scale), round(402 * scale))
        np.testing.assert_array_equal(ShadowDetector(ShadowDetectorConfig(scale=scale)).reduce(img),
                                      cv2.resize(img, size, interpolation=cv2.INTER_LINEAR))

def test_c3_table_holds_the_invariant_of_every_pixel():
    """The detector looks c3 up by (B, max(R, G)); NumPy's ``arctan2`` gives those floats wherever the pixel
    sits in the frame (frames of many sizes, every 8-bit value)."""
    from aerial_loc_env.estimators.shadow_detection import _c3_table, c3_invariant

    table = _c3_table()
    g = np.random.default_rng(1)
    for _ in range(100):
        h, w = g.integers(1, 130, 2)
        rgb = g.integers(0, 256, (h, w, 3)).astype(np.uint8)
        np.testing.assert_array_equal(table[rgb[..., 2], np.maximum(rgb[..., 0], rgb[..., 1])], c3_invariant(rgb))


def test_detector_refuses_a_reduced_frame_the_c3_table_cannot_index():
    """The kernel looks c3 up by byte values, unchecked: a reduced frame passed in must be (h, w, 3) uint8 too."""
    det = ShadowDetector(ShadowDetectorConfig())
    img = np.full((40, 60, 3), 100, np.uint8)
    for small in (np.full((10, 15, 3), 300, np.int32), np.zeros((10, 15, 3), np.float32), np.zeros((10, 15), np.uint8)):
        with pytest.raises(ConfigError, match="reduced frame"):
            det.detect(img, small=small)
