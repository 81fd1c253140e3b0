"""Shadow detection from the camera image alone, restoration look-up tables, the oracle, and mask quality."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.shadow_detection import (
    INDICES,
    ShadowDetector,
    ShadowDetectorConfig,
    ShadowMask,
    _disc,
    _masked_channel_means,
    _OpenClose,
    mask_quality,
    oracle_mask,
    restoration_lut,
    restoration_lut_reference,
    restore,
    shadow_index,
)
from aerial_loc_env.estimators.shadow_detection_kernels import _pairwise_sum
from aerial_loc_env.world.shadows import apply_shading


def ground(seed: int, shape: tuple[int, int] = (200, 300)) -> np.ndarray:
    """A moderately textured sunlit surface (mean ~150, std ~15 DN, slowly varying hue), RGB uint8."""
    g = np.random.default_rng(seed)
    base = [cv2.GaussianBlur(g.standard_normal(shape).astype(np.float32), (0, 0), s) for s in (2.0, 8.0, 8.0)]
    lum = 150 + 15 * base[0] / base[0].std()
    rgb = np.stack([lum + 10 * base[1] / base[1].std(), lum, lum + 10 * base[2] / base[2].std()], axis=-1)
    return np.clip(rgb, 0, 255).astype(np.uint8)


def shadow_scene(seed: int, strength: float = 0.9) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lit frame, shadowed frame, true mask): a few building-like shadow polygons, shaded by the simulator's
    own model (darker and bluer)."""
    lit = ground(seed)
    g = np.random.default_rng(seed + 100)
    occ = np.zeros(lit.shape[:2], np.uint8)
    for _ in range(3):
        c = g.uniform([30, 30], [270, 170])
        w, h, a = g.uniform(30, 90), g.uniform(20, 60), g.uniform(0, 180)
        box = cv2.boxPoints(((float(c[0]), float(c[1])), (w, h), a)).astype(np.int32)
        cv2.fillPoly(occ, [box], 255)
    return lit, apply_shading(lit, occ, strength), occ > 127


@pytest.mark.parametrize("index", ["c3_luminance", "luminance"])
def test_detector_finds_cast_shadows(index: str) -> None:
    det = ShadowDetector(ShadowDetectorConfig(index=index))
    ious = []
    for seed in range(4):
        _, shadowed, truth = shadow_scene(seed)
        q = mask_quality(det.detect(shadowed).full(), truth)
        ious.append(q["iou"])
        assert q["precision"] > 0.8 and q["recall"] > 0.8, q
    assert np.mean(ious) > 0.8, ious


@pytest.mark.parametrize("index", INDICES)
def test_detector_reports_no_shadow_on_a_lit_frame(index: str) -> None:
    """Otsu always splits in two; the luminance-ratio guard must turn that split down on a sunlit frame."""
    det = ShadowDetector(ShadowDetectorConfig(index=index))
    for seed in range(3):
        lit, _, _ = shadow_scene(seed)
        assert det.detect(lit).fraction < 0.02


def test_mask_lookup_matches_full_mask() -> None:
    _, shadowed, _ = shadow_scene(1)
    m = ShadowDetector().detect(shadowed)
    full = m.full()
    g = np.random.default_rng(0)
    u, v = g.integers(0, 300, 500), g.integers(0, 200, 500)
    np.testing.assert_array_equal(m.at(u, v), full[v, u])


def test_gain_restoration_brings_shadows_back() -> None:
    lit, shadowed, truth = shadow_scene(2)
    m = ShadowDetector().detect(shadowed)
    err_before = np.abs(shadowed[truth].astype(float) - lit[truth]).mean()
    err_gain = np.abs(restore(shadowed, m, "gain").astype(float)[truth] - lit[truth]).mean()
    err_eq = np.abs(restore(shadowed, m, "equalize").astype(float)[truth] - lit[truth]).mean()
    assert err_gain < 0.3 * err_before
    assert err_gain < 0.5 * err_eq      # equalization over-restores (the paper's finding, V.A)


def test_restoration_lut_is_identity_without_shadow() -> None:
    lit, _, _ = shadow_scene(0)
    for method in ("gain", "equalize"):
        lut = restoration_lut(lit, np.zeros(lit.shape[:2], bool), method)
        np.testing.assert_array_equal(lut, np.tile(np.arange(256, dtype=np.float32), (3, 1)))
    with pytest.raises(ConfigError, match="equalize"):
        restoration_lut(lit, np.zeros(lit.shape[:2], bool), "magic")


def test_mask_quality_counts() -> None:
    truth = np.zeros((10, 10), bool)
    truth[:5] = True                         # 50 px
    pred = np.zeros((10, 10), bool)
    pred[3:8] = True                         # 50 px, 20 overlap
    q = mask_quality(pred, truth)
    assert q["iou"] == pytest.approx(20 / 80)
    assert q["precision"] == pytest.approx(20 / 50) and q["recall"] == pytest.approx(20 / 50)
    empty = np.zeros((10, 10), bool)
    assert mask_quality(empty, empty)["iou"] == 1.0
    with pytest.raises(ConfigError, match="shape"):
        mask_quality(pred, truth[:5])


def test_oracle_reads_info_and_fails_clearly_without_it() -> None:
    truth = np.zeros((4, 6), bool)
    truth[1, 2] = True
    np.testing.assert_array_equal(oracle_mask({"shadow_mask": truth}, (4, 6)).full(), truth)
    with pytest.raises(ConfigError, match="uses_ground_truth"):
        oracle_mask(None, (4, 6))
    with pytest.raises(ConfigError, match="shape"):
        oracle_mask({"shadow_mask": truth}, (5, 6))


def test_bad_inputs_are_clear_errors() -> None:
    with pytest.raises(ConfigError, match="uint8"):
        ShadowDetector().detect(np.zeros((10, 10), np.float32))
    with pytest.raises(ConfigError, match="scale"):
        build_config(ShadowDetectorConfig, {"scale": 0.0})
    with pytest.raises(ConfigError, match="index"):
        build_config(ShadowDetectorConfig, {"index": "ndvi"})


@pytest.mark.parametrize("shape", [(0, 0, 3), (0, 10, 3), (10, 0, 3)])
def test_an_empty_frame_is_a_clear_error(shape: tuple[int, int, int]) -> None:
    with pytest.raises(ConfigError, match=r"the frame is empty .*at least 1 x 1 px"):
        ShadowDetector().detect(np.zeros(shape, np.uint8))
    with pytest.raises(ConfigError, match=r"the reduced frame is empty"):
        ShadowDetector().detect(np.zeros((8, 8, 3), np.uint8), small=np.zeros(shape, np.uint8))
    assert ShadowDetector().detect(np.zeros((1, 1, 3), np.uint8)).mask.shape == (1, 1)   # the smallest frame


def test_map_ratio_detector_sees_shadows_the_image_detector_cannot() -> None:
    """On a high-contrast map (dark texture as dark as the shadows) the image alone is ambiguous; the ratio to
    the shadow-free database at the (slightly wrong) pose is not."""
    from test_dense_models import ALT_M, briefing_standin, render_frame, textured_map

    from aerial_loc_env.estimators.shadow_detection import MapRatioShadowDetector

    m = textured_map(400, seed=1)
    br = briefing_standin(m)
    det = MapRatioShadowDetector()
    det.reset(br)
    ious, ious_image = [], []
    for k in range(4):
        x, y, yaw = 80.0 + 10 * k, 100.0, 0.4 * k
        frame = render_frame(m, x, y, yaw)
        occ = np.zeros(frame.shape[:2], np.uint8)
        occ[10 + 5 * k:50, 15:60 + 10 * k] = 255
        shadowed, truth = apply_shading(frame, occ, 1.0), occ > 127     # weak ones (0.7) can fall under the guard
        ious.append(mask_quality(det.detect(shadowed, x + 0.4, y - 0.3, yaw, ALT_M).full(), truth)["iou"])
        ious_image.append(mask_quality(ShadowDetector().detect(shadowed).full(), truth)["iou"])
        assert det.detect(frame, x, y, yaw, ALT_M).fraction < 0.02            # sunlit: no shadow
    assert np.mean(ious) > 0.7 and np.mean(ious) > np.mean(ious_image) + 0.2, (ious, ious_image)


def test_mask_quality_scores_an_empty_prediction_of_a_shadowed_frame_as_imprecise():
    from aerial_loc_env.estimators.shadow_detection import mask_quality

    truth = np.zeros((10, 10), bool)
    truth[:4] = True
    empty = np.zeros((10, 10), bool)
    q = mask_quality(empty, truth)
    assert q["precision"] == 0.0 and q["recall"] == 0.0 and q["iou"] == 0.0
    assert mask_quality(empty, empty)["precision"] == 1.0
    assert mask_quality(truth, empty)["precision"] == 0.0 and mask_quality(truth, empty)["recall"] == 1.0


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


@pytest.mark.slow
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


@pytest.mark.parametrize("method", ["gain", "equalize"])
def test_restoration_lut_is_bit_identical_to_the_reference(method):
    """Exact integer sums and counts (8-bit values, fewer than 2^24 / 255 pixels) divided as NumPy divides."""
    g = np.random.default_rng(8)
    for trial in range(200):
        h, w = g.integers(3, 110, 2)
        img = g.integers(0, 256, (h, w, 3)).astype(np.uint8)
        if trial % 2:
            img //= np.uint8(g.integers(2, 40))            # dark, narrow histograms
        mask = g.random((h, w)) < g.random()
        np.testing.assert_array_equal(restoration_lut(img, mask, method), restoration_lut_reference(img, mask, method))


def test_luminance_formula_is_cvtcolors_on_every_colour():
    """The fused pass's fixed-point luminance ``(9798 R + 19235 G + 3735 B + 2^14) >> 15`` against
    ``cv2.cvtColor(COLOR_RGB2GRAY)`` on all 2^24 8-bit colours (and the compiled pass's own bytes on a frame of
    them)."""
    from aerial_loc_env.estimators.shadow_detection_kernels import _reduce_index8

    c = np.arange(2 ** 24, dtype=np.uint32)
    img = np.stack([(c >> 16) & 255, (c >> 8) & 255, c & 255], axis=-1).astype(np.uint8).reshape(4096, 4096, 3)
    rgb = img.astype(np.int64)
    formula = (9798 * rgb[..., 0] + 19235 * rgb[..., 1] + 3735 * rgb[..., 2] + (1 << 14)) >> 15
    np.testing.assert_array_equal(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), formula)
    small, lum8, _, _ = _reduce_index8(img[:2048], _c3_table_for_tests(), 2)
    np.testing.assert_array_equal(lum8, cv2.cvtColor(small, cv2.COLOR_RGB2GRAY))


def _c3_table_for_tests() -> np.ndarray:
    from aerial_loc_env.estimators.shadow_detection import _c3_table

    return _c3_table()


@pytest.mark.parametrize("index", ["c3_luminance", "c3", "luminance"])
def test_fused_reduction_and_index_are_the_separate_passes(index):
    """``_reduce_index8`` (one pass) against ``_quarter``, ``cvtColor`` and ``_index8`` over random and smooth
    frames of several sizes, and the detector's mask with and without a reduced frame passed in (the two paths)."""
    from aerial_loc_env.estimators.shadow_detection import _INDEX_MODES, _c3_table
    from aerial_loc_env.estimators.shadow_detection_kernels import _index8, _quarter, _reduce_index8

    g = np.random.default_rng(21)
    mode = _INDEX_MODES[index]
    det = ShadowDetector(ShadowDetectorConfig(index=index))
    for k, (h, w) in enumerate([(400, 600), (4, 4), (8, 12), (36, 4), (400, 600), (120, 160)]):
        img = g.integers(0, 256, (h, w, 3)).astype(np.uint8)
        if k % 2:
            img = np.clip(cv2.GaussianBlur(img.astype(np.float32), (0, 0), 3) * 1.5 - 60, 0, 255).astype(np.uint8)
            img[: h // 2, : w // 3] = (img[: h // 2, : w // 3] * np.array([0.4, 0.45, 0.6])).astype(np.uint8)
        small, lum8, c3, idx8 = _reduce_index8(img, _c3_table(), mode)
        ref_small = _quarter(img)
        ref_lum = cv2.cvtColor(ref_small, cv2.COLOR_RGB2GRAY)
        ref_c3 = np.empty(ref_lum.shape, np.float32)
        np.testing.assert_array_equal(small, ref_small)
        np.testing.assert_array_equal(lum8, ref_lum)
        np.testing.assert_array_equal(idx8, _index8(ref_small, ref_lum, _c3_table(), mode, ref_c3))
        if mode != 2:
            np.testing.assert_array_equal(c3, ref_c3)
        got_small, mask = det.detect_reduced(img)
        np.testing.assert_array_equal(got_small, ref_small)
        np.testing.assert_array_equal(mask.mask, det.detect(img, small=ref_small).mask)
        np.testing.assert_array_equal(mask.mask, _detect_reference(det, img))


def test_compiled_otsu_threshold_is_opencvs():
    """``_otsu`` against ``cv2.threshold(.., THRESH_OTSU)``'s threshold on 8-bit images of many sizes and
    histograms: uniform noise, one or two Gaussian modes, a few levels, nearly constant images (a class under
    FLT_EPSILON), and the detector's own index images."""
    from aerial_loc_env.estimators.shadow_detection import _INDEX_MODES, _c3_table
    from aerial_loc_env.estimators.shadow_detection_kernels import _otsu, _reduce_index8

    g = np.random.default_rng(17)
    for t in range(3000):
        h, w = (100, 150) if t % 3 else (int(v) for v in g.integers(1, 200, 2))
        kind = t % 6
        if kind == 0:
            img = g.integers(0, 256, (h, w)).astype(np.uint8)
        elif kind == 1:
            img = np.clip(g.normal(g.uniform(50, 200), g.uniform(1, 60), (h, w)), 0, 255).astype(np.uint8)
        elif kind == 2:
            img = np.clip(g.normal(g.uniform(50, 120), 10, (h, w)), 0, 255).astype(np.uint8)
            img[: h // 2] += np.uint8(g.integers(0, 100))
        elif kind == 3:
            img = g.choice(g.integers(0, 256, int(g.integers(1, 5))).astype(np.uint8), (h, w))
        elif kind == 4:
            img = np.full((h, w), g.integers(0, 256), np.uint8)
            img[g.random((h, w)) < g.uniform(0, 1e-3)] = g.integers(0, 256)
        else:
            frame = np.clip(cv2.GaussianBlur(g.normal(120, 40, (400, 600, 3)), (0, 0), 2), 0, 255).astype(np.uint8)
            frame[100:260, 50:400] = (frame[100:260, 50:400] * np.array([0.4, 0.45, 0.6])).astype(np.uint8)
            img = _reduce_index8(frame, _c3_table(), _INDEX_MODES["c3_luminance"])[3]
        assert _otsu(img) == cv2.threshold(img, 0, 1, cv2.THRESH_BINARY + cv2.THRESH_OTSU)[0], (t, kind)
