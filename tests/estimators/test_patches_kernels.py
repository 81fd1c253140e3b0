"""The compiled patch kernels (issue 12) against today's code kept as the reference (tests/reference_models.py):
``cv2.remap`` over float32 coordinate maps, then the models' similarities in NumPy.

Tolerances, derived (``delta`` = the largest sample difference):

- Samples. The kernel's bilinear is OpenCV's sequence (floor, fractions a, b; ``v0 = fma(a, p01 - p00, p00)``,
  ``v1`` alike, ``fma(b, v1 - v0, v0)``) at the same float32 coordinates. Where OpenCV also fuses (its vector
  path on FMA hardware: measured here, every sample equal) the difference is 0; where it multiplies and adds
  unfused, each of the three steps differs by at most half an ulp of a value below 256 (2^-17) and the last
  step's inputs carry the first two's: |d| <= 2^-17 (1 - b) + 2^-17 b + 2^-17 + 2^-17 <= 2^-15 = 3.1e-5 gray levels
  (the measured unfused maximum is exactly 2^-15).
- SSD: ``| RMS(q - r) - RMS(p - r) | <= RMS(q - p) <= delta`` (triangle inequality), so
  ``|d xi| <= delta / 255`` and ``|d log L| <= (|1 - xi| + |d xi|) |d xi| / sigma^2``; plus the old float32 sums'
  rounding, replaced here by float64 (the reference is evaluated in float64).
- NCC: the centred view's unit vector moves by at most ``2 |d p~| / |p~| <= 2 delta sqrt(K) / |p~|``, and so does
  the correlation with a unit reference.
- MI: integer counts; a sample moved to another bin changes two joint cells and two marginal cells by one, each
  ``c log c`` by at most ``1 + log K``: ``|d MI| <= 4 (1 + log K) / K`` per moved sample (none here), plus the
  float64 sums (1e-12).
- abBRIEF: a bit can only flip where the reference's two values are within ``2 delta``.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from reference_models import mutual_information, pair_similarity_reference, remap_patches
from test_dense_models import ALT_M, briefing_standin, observation, render_frame, textured_map

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.abbrief import ABBriefConfig, ABBriefModel
from aerial_loc_env.estimators.mcl.dense import DenseConfig, MIModel, NCCModel, SSDModel, quantize
from aerial_loc_env.estimators.mcl.intensity_pairs import IntensityPairsConfig, IntensityPairsModel
from aerial_loc_env.estimators.patches import BRIEF, HISTOGRAM, MOMENTS, SAMPLE, PatchGeometry, PatchSampler

DELTA = 2.0 ** -15


def _map(seed: int, with_nodata: bool):
    m = textured_map(300, seed=seed)
    if with_nodata:
        m.nodata = np.zeros((m.height_px, m.width_px), bool)
        m.nodata[20:60, 200:260] = True              # off the centre, where the true pose is
        m.nodata[:, :6] = True                       # along a border too
    return m


def _states(m, n: int = 400, seed: int = 4) -> np.ndarray:
    """Particles all over the map (many footprints crossing its borders or the no-data), some far off it or not
    finite, and a few at the centre."""
    g = np.random.default_rng(seed)
    w, h = m.width_m, m.height_m
    spread = np.column_stack([g.uniform(-20, w + 20, n), g.uniform(-20, h + 20, n), g.uniform(-np.pi, np.pi, n)])
    centre = np.column_stack([w / 2 + g.normal(0, 5, 20), h / 2 + g.normal(0, 5, 20), g.normal(0.4, 0.1, 20)])
    odd = np.array([[1e9, h / 2, 0.3], [-1e9, -1e9, 2.0], [np.nan, h / 2, 0.0], [w / 2, h / 2, np.inf]])
    return np.concatenate([centre, spread, odd])


@pytest.mark.parametrize("channels", [1, 2, 3, 4])
@pytest.mark.parametrize("with_nodata", [False, True])
def test_kernel_samples_equal_remap_within_the_fma_bound(channels, with_nodata):
    m = _map(1, with_nodata)
    rgb = m.rgb.astype(np.float32)
    layer = rgb[..., 0] if channels == 1 else np.concatenate([rgb, rgb[..., :1] * 0.5], axis=2)[..., :channels]
    sampler = PatchSampler(m, briefing_standin(m).camera, PatchGeometry(24, 16), layer, ALT_M, nodata=m.nodata)
    states = _states(m)
    with np.errstate(invalid="ignore"):
        patches, valid = sampler.sample(states, ALT_M)
        ref, ref_valid = remap_patches(sampler, states, ALT_M)
    assert patches.shape == ref.shape and patches.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(patches), np.isnan(ref))      # the border and the no-data alike
    both = np.isfinite(ref)
    assert np.abs(patches[both] - ref[both]).max() <= DELTA
    np.testing.assert_array_equal(valid, ref_valid)
    assert 20 <= valid.sum() < len(states) - 100                          # both kinds, many of each


def _dense_case(cls, with_nodata: bool):
    m = _map(3, with_nodata)
    model = cls(DenseConfig(patch_width_px=30, patch_height_px=20, sigma=0.2 if cls is NCCModel else 0.1))
    model.reset(briefing_standin(m), np.random.default_rng(0))
    x, y, yaw = m.width_m / 2, m.height_m / 2, 0.4
    prep = model.prepare(observation(render_frame(m, x, y, yaw), yaw), np.random.default_rng(0))
    states = _states(m, seed=7)
    with np.errstate(invalid="ignore"):
        ll = model.log_likelihood(prep, states, ALT_M)
        kernel, _ = model.sampler.sample(states, ALT_M)
        patches, valid = remap_patches(model.sampler, states, ALT_M)
    flat = patches.reshape(len(states), -1).astype(np.float64)
    flat[~valid] = 0.0
    delta = np.abs(kernel - patches).reshape(len(states), -1)
    delta = np.where(valid, np.nanmax(np.where(np.isnan(delta), 0.0, delta), axis=1), 0.0)
    assert delta.max() <= DELTA
    return model, prep, states, ll, flat, valid, kernel.reshape(len(states), -1)


def _ll(xi, sigma):
    return -np.square(1.0 - xi) / (2.0 * sigma ** 2)


@pytest.mark.parametrize("with_nodata", [False, True])
def test_ssd_model_matches_the_remap_reference(with_nodata):
    model, prep, states, ll, flat, valid, _ = _dense_case(SSDModel, with_nodata)
    sigma = model.config.sigma
    xi = np.where(valid, 1.0 - np.sqrt(np.square(flat - prep.ref).mean(axis=1)) / 255.0, 0.0)
    d_xi = DELTA / 255.0 + 1e-12
    bound = (np.abs(1.0 - xi) + d_xi) * d_xi / sigma ** 2 + 1e-9
    assert np.all(np.abs(ll - _ll(xi, sigma)) <= bound)
    assert np.isfinite(ll).all() and int(np.argmax(ll)) < 20 and (~valid).sum() > 100


@pytest.mark.parametrize("with_nodata", [False, True])
def test_ncc_model_matches_the_remap_reference(with_nodata):
    model, prep, states, ll, flat, valid, _ = _dense_case(NCCModel, with_nodata)
    sigma, k = model.config.sigma, flat.shape[1]
    pc = flat - flat.mean(axis=1, keepdims=True)
    rc = prep.ref.astype(np.float64) - prep.ref.mean(dtype=np.float64)
    norm = np.sqrt((pc * pc).sum(axis=1))
    ok = valid & (norm * norm > 1e-6 * k)
    xi = np.full(len(states), -1.0)
    xi[valid] = 0.0
    xi[ok] = np.clip(pc[ok] @ rc / (norm[ok] * np.sqrt(rc @ rc)), -1, 1)
    d_xi = np.where(ok, 2.0 * DELTA * math.sqrt(k) / np.where(ok, norm, 1.0), 0.0) + 1e-9
    bound = (np.abs(1.0 - xi) + d_xi) * d_xi / sigma ** 2 + 1e-9
    assert np.all(np.abs(ll - _ll(xi, sigma)) <= bound)
    assert np.isfinite(ll).all() and int(np.argmax(ll)) < 20


@pytest.mark.parametrize("with_nodata", [False, True])
def test_mi_model_matches_the_remap_reference(with_nodata):
    model, prep, states, ll, flat, valid, kernel = _dense_case(MIModel, with_nodata)
    bins, k = model.config.bins, flat.shape[1]
    h_ref = prep.extra[0]
    xi = np.where(valid, mutual_information(flat.astype(np.float32), prep.ref, bins) / h_ref, 0.0)
    with np.errstate(invalid="ignore"):
        moved = (quantize(np.nan_to_num(kernel), bins) != quantize(flat, bins)).sum(axis=1)
    d_xi = np.where(valid, moved, 0) * 4 * (1 + math.log(k)) / k / h_ref + 1e-12
    bound = (np.abs(1.0 - xi) + d_xi) * d_xi / model.config.sigma ** 2 + 1e-9
    assert np.all(np.abs(ll - _ll(xi, model.config.sigma)) <= bound)
    assert np.isfinite(ll).all() and int(np.argmax(ll)) < 20


@pytest.mark.parametrize("channels", ["ab", "L", "Lab"])
@pytest.mark.parametrize("with_nodata", [False, True])
def test_abbrief_kernel_matches_the_remap_reference(channels, with_nodata):
    m = _map(5, with_nodata)
    model = ABBriefModel(ABBriefConfig(channels=channels, grid_width_px=30, grid_height_px=20))
    model.reset(briefing_standin(m), np.random.default_rng(1))
    x, y, yaw = m.width_m / 2, m.height_m / 2, -0.7
    prep = model.prepare(observation(render_frame(m, x, y, yaw), yaw), np.random.default_rng(0))
    states = np.concatenate([[[x, y, yaw]], _states(m, seed=9)])
    with np.errstate(invalid="ignore"):
        xi = model.similarity(prep, states, ALT_M)
        patches, valid = remap_patches(model.sampler, states, ALT_M)
    values = patches.reshape(len(states), -1)
    first, second = values[:, model._i1], values[:, model._i2]
    ref_xi = np.where(valid, np.count_nonzero((first > second) == prep.bits, axis=1) / prep.bits.size, 0.5)
    near_ties = np.where(valid, (np.abs(first - second) <= 2 * DELTA).sum(axis=1), 0)
    assert np.all(np.abs(xi - ref_xi) * prep.bits.size <= near_ties + 1e-9)
    assert np.any(xi == 0.5) and xi[0] > 0.7 and int(np.argmax(xi)) == 0


def test_kernel_compiles_once_for_every_mode():
    """The unused inputs of a mode are empty arrays of the used ones' types: one compiled specialization."""
    from aerial_loc_env.estimators import patches_kernels

    for model in (SSDModel(), MIModel(), ABBriefModel()):
        m = _map(2, False)
        model.reset(briefing_standin(m), np.random.default_rng(0))
        prep = model.prepare(observation(render_frame(m, 70.0, 80.0, 0.1), 0.1), np.random.default_rng(0))
        with np.errstate(invalid="ignore"):                    # the states' NaN and inf rows
            model.log_likelihood(prep, _states(m, 20), ALT_M)
            model.sampler.sample(_states(m, 5), ALT_M)
    assert len(patches_kernels.scan.signatures) == 1


def test_score_refuses_inputs_the_kernel_would_index_out_of_bounds():
    """``scan`` indexes unchecked (boundscheck=False): shapes and ranges are checked before it runs."""
    m = _map(1, False)
    sampler = PatchSampler(m, briefing_standin(m).camera, PatchGeometry(24, 16), m.rgb[..., 0], ALT_M)
    states = _states(m, 10)[:20]                       # the finite ones at the centre
    ok_bins, table = np.zeros((16, 24), np.int32), np.zeros(16 * 24 + 1)
    for mode, inputs in [(MOMENTS, {"ref": np.zeros((15, 24), np.float32)}), (MOMENTS, {}), (SAMPLE, {}),
                         (MOMENTS, {"ref": np.zeros((16, 24), np.float32), "channels": 2}),
                         (HISTOGRAM, {"ref_bins": ok_bins + 16, "bins": 16, "nlogn": table}),
                         (HISTOGRAM, {"ref_bins": ok_bins, "bins": 16, "nlogn": table[:10]}),
                         (BRIEF, {"tests": np.array([[0, 16 * 24, 0]]), "cam_bits": np.zeros(1, bool)}),
                         (BRIEF, {"tests": np.array([[0, 1, 1]]), "cam_bits": np.zeros(1, bool)}),
                         (BRIEF, {"tests": np.array([[0, 1, 0]]), "cam_bits": np.zeros(2, bool)})]:
        with pytest.raises(ConfigError, match="PatchSampler.score"):
            sampler.score(states, ALT_M, mode, **inputs)


# ---------------------------------------------------------------------- intensity pairs
@pytest.mark.parametrize("params", [{}, {"channels": 1}, {"shadow": "drop"}, {"shadow": "drop", "channels": 1},
                                    {"shadow": "drop", "shadow_pair_weight": 0.4}, {"shadow": "restore"}])
@pytest.mark.parametrize("with_nodata", [False, True])
def test_pair_kernel_is_bit_identical_to_the_numpy_path(params, with_nodata):
    """The kernel's projection, rounding, clipping, lookup and count against the gather path it replaced (Table
    5's models: every xi the same float, of the same dtype, on- and off-map, with and without no-data)."""
    m = _map(6, with_nodata)
    model = IntensityPairsModel(IntensityPairsConfig(**params))
    model.reset(briefing_standin(m), np.random.default_rng(0))
    x, y, yaw = m.width_m / 2, m.height_m / 2, 0.4
    frame = render_frame(m, x, y, yaw)
    frame[10:50, 20:70] //= 3                                  # a dark patch: the detector flags something
    g = np.random.default_rng(2)
    for trial in range(4):
        prep = model.prepare(observation(frame, yaw), g)
        states = np.concatenate([[[x, y, yaw]], _states(m, 300, seed=trial)[:-4]])   # finite states
        if trial == 3:
            states = states[:25]                                 # near the centre: every point on the map
        xi = model.similarity(prep, states, ALT_M)
        ref = pair_similarity_reference(model, prep, states, ALT_M)
        assert xi.dtype == ref.dtype
        np.testing.assert_array_equal(xi, ref)
        assert xi[0] > 0.6 and xi[0] > np.median(xi) + 0.1         # the true pose stands out


@pytest.mark.parametrize("with_mask", [False, True])
def test_camera_pairs_kernel_reads_the_pixels_and_the_mask_as_numpy_does(with_mask):
    """The frame's side of the pairs: the pixels by fancy indexing, the reduced mask by ``ShadowMask.at``, the
    pairs' bits as ``vals[:K] > vals[K:]`` and the kept pairs as ``np.flatnonzero(~(in[:K] ^ in[K:]))``."""
    from aerial_loc_env.estimators.mcl.intensity_pairs_kernels import camera_pairs
    from aerial_loc_env.estimators.shadow_detection import ShadowMask

    g = np.random.default_rng(3)
    for h_w in ((400, 600), (37, 53), (400, 600)):
        img = g.integers(0, 256, h_w + (3,)).astype(np.uint8)
        u, v = g.integers(0, h_w[1], 500), g.integers(0, h_w[0], 500)
        mask = ShadowMask(g.random((max(1, h_w[0] // 4), max(1, h_w[1] // 3))) < 0.4, h_w)
        vals, in_mask, uv = np.empty((500, 3), np.float32), np.zeros(500, bool), np.empty((500, 2))
        bits, kept = np.empty((250, 3), bool), np.empty(250, np.intp)
        n_kept = camera_pairs(img, u, v, mask.mask if with_mask else np.zeros((0, 0), bool), vals, in_mask, uv,
                              bits, kept)
        np.testing.assert_array_equal(vals, img[v, u].astype(np.float32))
        np.testing.assert_array_equal(bits, vals[:250] > vals[250:])
        np.testing.assert_array_equal(kept[:n_kept], np.flatnonzero(~(in_mask[:250] ^ in_mask[250:])))
        assert 0 < n_kept < 250 if with_mask else n_kept == 250
        np.testing.assert_array_equal(uv, np.column_stack([u, v]).astype(float))
        np.testing.assert_array_equal(in_mask, mask.at(u, v) if with_mask else np.zeros(500, bool))


def test_bilinear_f32x8_equals_the_scalar_chain():
    """``jit.bilinear_f32x8`` (the kernel's samples, 8 points a call, each neighbour pair one 64-bit load) gives the
    floats of the point-by-point chain at aligned and unaligned offsets, the plane's first and last pairs included,
    and copies non-finite neighbours' results as the chain makes them."""
    import numba

    from aerial_loc_env import jit
    from aerial_loc_env.estimators import patches_kernels

    @numba.njit
    def vector(plane, idx, below, fa, fb, out, starts):
        for j in starts:
            jit.bilinear_f32x8(plane, idx, below, fa, fb, out, j)

    rng = np.random.default_rng(21)
    below, n = 53, 48
    plane = (rng.random(53 * 40, dtype=np.float32) * 255).astype(np.float32)
    plane[[7, 8]] = np.nan, np.inf
    idx = rng.integers(0, plane.size - below - 1, n).astype(np.uint32)
    idx[:3] = 0, plane.size - below - 2, 7
    fa, fb = rng.random(n, dtype=np.float32), rng.random(n, dtype=np.float32)
    starts = np.array([0, 8, 16, 24, 32, 40, 5], np.int64)
    out_v, out_s = np.zeros(n, np.float32), np.zeros(n, np.float32)
    vector(plane, idx, np.uint32(below), fa, fb, out_v, starts)
    patches_kernels._sample(plane, idx, np.uint32(below), fa, fb, out_s, 0, 5)    # the scalar tail: 5 < 8
    patches_kernels._sample(plane, idx, np.uint32(below), fa, fb, out_s, 5, n)    # 8 at a time from 5, then 3
    np.testing.assert_array_equal(out_v, out_s)
    assert np.isnan(out_v[2]) and np.isfinite(out_v[3:]).all()


def test_index32_wraps_in_32_bits():
    """``jit.index32``: ``row * stride + col`` in int32 (the kernels' flat indices; a product beyond int32 wraps, as
    the uint32 index it becomes reads it)."""
    import numba

    from aerial_loc_env import jit

    @numba.njit
    def index(r, s, c):
        return jit.index32(r, s, c)

    assert index(np.int32(3), np.int32(1000), np.int32(7)) == 3007
    assert index(np.int32(-2), np.int32(5), np.int32(1)) == -9
    assert index(np.int32(70000), np.int32(70000), np.int32(0)) == np.int32(np.int64(70000 * 70000) - 2 ** 32)


def test_a_level_beyond_the_32_bit_sample_index_is_refused_before_any_work():
    """A whole map whose level holds 2**32 samples or more would wrap the kernel's flat index and read the wrong
    pixels: refused with the map's name and the way out (a zero-stride view stands in for the huge image)."""
    from types import SimpleNamespace

    from aerial_loc_env.errors import MapError
    from aerial_loc_env.sensors.camera import CameraModel

    side = 1 << 16
    huge = SimpleNamespace(name="huge", height_px=side, width_px=side, gsd_x_m=0.25, gsd_y_m=0.25)
    image = np.broadcast_to(np.zeros((1, 1, 3), np.uint8), (side, side, 3))
    with pytest.raises(MapError, match=r"huge.*32-bit sample index.*downsample"):
        PatchSampler(huge, CameraModel(), PatchGeometry(60, 40), image, 200.0, downsample=1.0)
