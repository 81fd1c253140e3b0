"""The intensity-pair model (``estimators/mcl/intensity_pairs.py`` and its kernels) against the straightforward
forms: the pair kernel's affine, eq. (4)'s XNOR count, eq. (8) for one frame, the database words."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from test_dense_models import briefing_standin, textured_map

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.intensity_pairs import IntensityPairsConfig, IntensityPairsModel, xnor_similarity
from aerial_loc_env.sensors.camera import CameraModel


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


def test_pair_pixels_are_numpys_integers_and_leave_the_generator_as_they_do(monkeypatch):
    """``pair_pixels`` against two ``rng.integers`` calls: the same values and the same generator afterwards (its
    next draws of every kind equal), over many seeds and frame sizes; with a 32-bit half kept from an earlier odd
    draw, an odd count, another bit generator, and where the compiled pass meets a rejected half (forced), NumPy
    draws itself."""
    from aerial_loc_env.estimators.mcl import intensity_pairs
    from aerial_loc_env.estimators.mcl.intensity_pairs import pair_pixels
    from aerial_loc_env.estimators.mcl.intensity_pairs_kernels import bounded_pairs

    def same(a: np.random.Generator, b: np.random.Generator, w: int, h: int, n: int) -> None:
        u, v = pair_pixels(a, w, h, n)
        np.testing.assert_array_equal(u, b.integers(0, w, n))
        np.testing.assert_array_equal(v, b.integers(0, h, n))
        assert u.dtype == v.dtype == np.int64
        assert a.integers(0, 7, 3).tolist() == b.integers(0, 7, 3).tolist() and a.random() == b.random()

    for seed in range(300):
        w, h = [(600, 400), (64, 64), (2, 3), (4000, 3000), (2 ** 31 + 5, 7)][seed % 5]
        same(np.random.default_rng(seed), np.random.default_rng(seed), w, h, 2 * (1 + seed % 90))
    a, b = np.random.default_rng(5), np.random.default_rng(5)
    a.integers(0, 600, 1), b.integers(0, 600, 1)                  # a half kept in the generator
    same(a, b, 600, 400, 140)
    same(np.random.default_rng(6), np.random.default_rng(6), 600, 400, 141)
    same(np.random.Generator(np.random.MT19937(7)), np.random.Generator(np.random.MT19937(7)), 600, 400, 140)
    monkeypatch.setattr(intensity_pairs, "bounded_pairs", lambda *args: False)
    same(np.random.default_rng(8), np.random.default_rng(8), 600, 400, 140)
    raw = np.array([0, 1 << 40], np.uint64)                      # a zero half: a rejection for bound 600
    assert not bounded_pairs(raw, 600, 400, np.empty(2, np.int64), np.empty(2, np.int64))
