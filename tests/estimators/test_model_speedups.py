"""The faster measurement-model code paths (issue 12) against the straightforward forms they replaced.

Where the arithmetic is unchanged (integer bit counts, the same samples) the outputs must be bit-identical; where
it changes (MI's entropies from integer counts with
a ``c log c`` table instead of probabilities and their logs) the tolerance is derived in the test.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from reference_models import mutual_information, mutual_information_reference
from test_dense_models import ALT_M, briefing_standin, observation, render_frame, textured_map

from aerial_loc_env.estimators.mcl.abbrief import ABBriefConfig, ABBriefModel, lab_channels, reduced_lab
from aerial_loc_env.estimators.mcl.dense import MIModel
from aerial_loc_env.estimators.mcl.intensity_pairs import IntensityPairsConfig, IntensityPairsModel, xnor_similarity
from aerial_loc_env.estimators.patches import reduce_image
from aerial_loc_env.estimators.shadow_detection import restoration_lut, restoration_lut_reference


def _states(m, n: int = 150, seed: int = 4) -> np.ndarray:
    """Particles around the map centre plus some whose footprint leaves the map."""
    g = np.random.default_rng(seed)
    cx, cy = m.width_m / 2, m.height_m / 2
    near = np.column_stack([cx + g.normal(0, 15, n), cy + g.normal(0, 15, n), g.uniform(-np.pi, np.pi, n)])
    far = np.array([[-40.0, cy, 0.3], [m.width_m + 5, cy, 1.0], [cx, 3.0, -2.0]])
    return np.concatenate([near, far])


# ---------------------------------------------------------------------- intensity pairs
def _xnor_reference(cam_bits: np.ndarray, db_bits: np.ndarray, channels: int) -> np.ndarray:
    """Eq. (4) counted the direct way: agreements over all C (padding agreeing) minus the padding."""
    n, k, c_all = db_bits.shape
    agree = db_bits == cam_bits[None]
    return (agree.reshape(n, -1).sum(axis=1) - k * (c_all - channels)) / (k * channels)


@pytest.mark.parametrize("k, c_all, c", [(70, 4, 3), (255, 4, 3), (300, 4, 3), (30, 1, 1), (12, 3, 3)])
def test_xnor_count_is_exact(k, c_all, c):
    g = np.random.default_rng(k)
    cam = g.random((k, c_all)) < 0.5
    db = g.random((200, k, c_all)) < 0.5
    cam[:, c:] = False
    db[..., c:] = False                                    # padding agrees, as the packed RGBA alpha byte
    out = xnor_similarity(cam, db, channels=c)
    np.testing.assert_array_equal(out, _xnor_reference(cam, db, c))   # the same integers / the same divisor
    keep = g.random(k) < 0.7
    np.testing.assert_array_equal(xnor_similarity(cam, db, keep, channels=c),
                                  _xnor_reference(cam[keep], db[:, keep], c))


# ---------------------------------------------------------------------- MI
def test_mi_from_counts_matches_the_probability_form():
    """Tolerance: each entropy is a float64 sum of at most B^2 = 256 terms; in the count form the terms are
    c log c <= K log K and the sum is divided by K, so the rounding is <= 256 K log K eps / K = 256 log K eps
    (~2.3e-13 nats at K = 2400); the probability form errs alike. 1e-12 nats covers both, 4x over."""
    g = np.random.default_rng(3)
    k = 2400
    ref = cv2.GaussianBlur(g.uniform(0, 255, (40, 60)).astype(np.float32), (0, 0), 1.5).ravel()
    rows = np.concatenate([ref[None] + g.normal(0, s, (20, k)) for s in (0.0, 5.0, 30.0, 200.0)])
    rows = np.clip(rows, 0, 255).astype(np.float32)
    rows[-1] = 0.0                                          # a constant row (an invalid particle's zeros)
    for bins in (2, 16, 17, 64):
        np.testing.assert_allclose(mutual_information(rows, ref, bins), mutual_information_reference(rows, ref, bins),
                                   rtol=0, atol=1e-12)
    # beyond the gray range: quantization clips to the edge bins alike
    wild = np.concatenate([rows[:5], rows[:5] * 3 - 300])
    np.testing.assert_allclose(mutual_information(wild, ref), mutual_information_reference(wild, ref),
                               rtol=0, atol=1e-12)


def test_mi_model_log_likelihoods_match_the_reference_on_the_same_samples():
    """log L = -(1 - xi)^2 / (2 sigma^2) with xi = MI / H: |d log L| <= |1 - xi| / sigma^2 * dMI / H
    <= 100 * 1e-12 / H (sigma = 0.1, H ~ 2 nats here): 1e-9 is generous."""
    m = textured_map(300, seed=2)
    model = MIModel()
    model.reset(briefing_standin(m), np.random.default_rng(0))
    x, y, yaw = m.width_m / 2, m.height_m / 2, 0.4
    prep = model.prepare(observation(render_frame(m, x, y, yaw), yaw), np.random.default_rng(0))
    states = _states(m)
    ll = model.log_likelihood(prep, states, ALT_M)
    patches, valid = model.sampler.sample(states, ALT_M)
    flat = patches.reshape(len(states), -1)
    flat[~valid] = 0.0
    xi = np.where(valid, mutual_information_reference(flat, prep.ref, model.config.bins) / prep.extra[0], 0.0)
    np.testing.assert_allclose(ll, -np.square(1.0 - xi) / (2.0 * model.config.sigma ** 2), rtol=0, atol=1e-9)
    assert int(np.argmax(ll)) != len(states) - 1 and np.isfinite(ll).all()


# ---------------------------------------------------------------------- abBRIEF
@pytest.mark.parametrize("channels", ["ab", "L", "Lab"])
@pytest.mark.parametrize("with_nodata", [False, True])
def test_abbrief_kernel_count_is_bit_identical_to_the_bool_descriptor(channels, with_nodata):
    """The kernel's count at the pattern's nodes against the whole patch's bool descriptor (the same samples:
    exact integer counts)."""
    m = textured_map(300, seed=5)
    if with_nodata:
        m.nodata = np.zeros((m.height_px, m.width_px), bool)
        m.nodata[20:60, 30:90] = True            # near the corner: the true pose keeps its data
    model = ABBriefModel(ABBriefConfig(channels=channels, grid_width_px=30, grid_height_px=20))
    model.reset(briefing_standin(m), np.random.default_rng(1))
    x, y, yaw = m.width_m / 2, m.height_m / 2, -0.7
    prep = model.prepare(observation(render_frame(m, x, y, yaw), yaw), np.random.default_rng(0))
    states = np.concatenate([[[x, y, yaw]], _states(m)])
    xi = model.similarity(prep, states, ALT_M)
    ref = model.similarity_reference(prep, states, ALT_M)
    np.testing.assert_array_equal(xi, ref)                 # exact integer counts over the same bits
    assert np.any(xi == 0.5) and xi[0] > 0.8 and int(np.argmax(xi)) == 0


# ---------------------------------------------------------------------- shadow restoration, database words
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


def test_database_words_are_converted_once_per_map_and_read_only():
    m = textured_map(120, seed=9)
    a, b = IntensityPairsModel(IntensityPairsConfig(channels=1)), IntensityPairsModel(IntensityPairsConfig())
    briefing = briefing_standin(m)
    a.reset(briefing, np.random.default_rng(0))
    a2 = IntensityPairsModel(IntensityPairsConfig(channels=1))
    a2.reset(briefing, np.random.default_rng(0))
    b.reset(briefing, np.random.default_rng(0))
    assert a2._db is a._db and b._db is not a._db and not a._db.flags.writeable
    np.testing.assert_array_equal(a._db, cv2.cvtColor(m.rgb, cv2.COLOR_RGB2GRAY).ravel())
    assert np.shares_memory(b._db, m.rgb) and b._db.dtype == np.uint8      # c = 3: the map's own bytes, no copy
    np.testing.assert_array_equal(b._db, m.rgb.ravel())
    # another map layer (or the same pixels with no-data added) is converted anew
    other = textured_map(120, seed=9)
    other.nodata = np.zeros((120, 120), bool)
    other.nodata[:10] = True
    c = IntensityPairsModel(IntensityPairsConfig(channels=1))
    c.reset(briefing_standin(other), np.random.default_rng(0))
    assert c._db is not a._db and c._nodata is not None and c._nodata[:1200].all() and not c._nodata[1200:].any()


@pytest.mark.parametrize("channels", ["ab", "L", "Lab"])
@pytest.mark.parametrize("size", [(60, 40), (37, 23), (120, 80)])
def test_reduced_lab_is_bit_identical_to_reducing_the_selected_channels(channels, size):
    img = render_frame(textured_map(200, seed=6), 50.0, 50.0, 0.2)
    ref = reduce_image(lab_channels(img, channels), *size)          # (h, w) for one channel: cv2 drops it
    np.testing.assert_array_equal(reduced_lab(img, channels, *size), ref.reshape(size[1], size[0], -1))
