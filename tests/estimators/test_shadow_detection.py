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
    mask_quality,
    oracle_mask,
    restoration_lut,
    restore,
)
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
