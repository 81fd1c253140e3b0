"""Dense measurement models (SSD, NCC, MI) and the vectorized patch reconstruction they share.

The scene helpers at the top (a small textured map, a briefing stand-in, a shadow-free frame rendered by the
camera's own eq. (3) affine) are reused by the abBRIEF, edge and baseline tests.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from reference_models import (  # tests/: the kernels' references
    msd,
    mutual_information,
    mutual_information_reference,
    ncc,
)

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.dense import (
    DenseConfig,
    MIModel,
    NCCModel,
    SSDModel,
    entropy,
)
from aerial_loc_env.estimators.patches import PatchGeometry, PatchSampler, to_gray
from aerial_loc_env.sensors.camera import CameraModel, Pose
from aerial_loc_env.sensors.render import CameraRenderer, Photometry

ALT_M = 100.0
GSD_M = 0.5
#: 120 x 80 px over 60 m x 40 m at 100 m: 0.5 m/px like the map
CAMERA = CameraModel(width_px=120, height_px=80, hfov_deg=math.degrees(2 * math.atan(0.3)))


def textured_map(size_px: int = 400, seed: int = 0, buildings: int = 25) -> SimpleNamespace:
    """An Orthomap stand-in: smooth multi-scale texture plus bright rectangular roofs (RGB uint8)."""
    g = np.random.default_rng(seed)
    img = np.zeros((size_px, size_px), np.float32)
    for sigma, amp in ((12.0, 60.0), (4.0, 35.0), (1.5, 15.0)):
        img += amp * cv2.GaussianBlur(g.standard_normal((size_px, size_px)).astype(np.float32), (0, 0), sigma) \
            * sigma
    img = 110 + img / (img.std() + 1e-6) * 30
    for _ in range(buildings):
        x0, y0 = g.integers(0, size_px - 40, 2)
        w, h = g.integers(12, 40, 2)
        img[y0:y0 + h, x0:x0 + w] = g.uniform(170, 230)
    gray = np.clip(img, 0, 255)
    # independent smooth colour fields (roofs, lawns, asphalt differ in hue, not only in brightness)
    tint = [cv2.GaussianBlur(g.standard_normal((size_px, size_px)).astype(np.float32), (0, 0), 6.0) for _ in "rb"]
    tint = [t / (t.std() + 1e-6) * 25 for t in tint]
    rgb = np.stack([gray + tint[0], gray - 0.5 * (tint[0] + tint[1]), gray + tint[1]], axis=-1)
    return orthomap_standin(rgb.clip(0, 255).astype(np.uint8))


def orthomap_standin(rgb: np.ndarray, gsd_m: float = GSD_M, nodata: np.ndarray | None = None) -> SimpleNamespace:
    h, w = rgb.shape[:2]
    return SimpleNamespace(rgb=rgb, gsd_x_m=gsd_m, gsd_y_m=gsd_m, width_px=w, height_px=h, nodata=nodata,
                           dsm_m=None, width_m=w * gsd_m, height_m=h * gsd_m, name="synthetic")


def briefing_standin(orthomap, camera: CameraModel = CAMERA, altitude_m: float = ALT_M,
                     mean_xy_m: tuple[float, float] | None = None, std_xy_m: float = 5.0) -> SimpleNamespace:
    """The Briefing fields the estimators read (docs/ARCHITECTURE.md)."""
    prior = SimpleNamespace(kind="gaussian", mean_xy_m=mean_xy_m or (orthomap.width_m / 2, orthomap.height_m / 2),
                            std_xy_m=std_xy_m)
    noise = SimpleNamespace(speed_std_mps=0.1, yaw_rate_std_radps=math.radians(5), heading_std_rad=0.02,
                            altitude_std_m=1.0, lateral_std_mps=0.1)
    return SimpleNamespace(orthomap=orthomap, camera=camera, prior=prior, dt_s=0.25, altitude_m=altitude_m,
                           odometry_noise=noise, scenario_id="test")


def render_frame(orthomap, x_m: float, y_m: float, yaw_rad: float, camera: CameraModel = CAMERA,
                 altitude_m: float = ALT_M, seed: int = 0) -> np.ndarray:
    """A shadow-free camera frame from the project's renderer, with its default photometry (exposure and
    white-balance jitter, tone curve, noise, vignetting)."""
    renderer = CameraRenderer(orthomap, camera, Photometry(), strict=False)
    return renderer.render(Pose(x_m, y_m, yaw_rad, altitude_m), np.random.default_rng(seed)).image


def observation(image: np.ndarray, yaw_rad: float = 0.0, altitude_m: float = ALT_M) -> dict:
    return {"image": image, "odometry": np.zeros(3, np.float32), "yaw": np.array([yaw_rad], np.float32),
            "altitude": np.array([altitude_m], np.float32)}


def offset_grid(x_m: float, y_m: float, yaw_rad: float, step_m: float = 2.0, n: int = 4,
                yaws_rad: tuple[float, ...] = (-0.15, 0.0, 0.15)) -> np.ndarray:
    """States (M, 3) around a pose; row 0 is the pose itself."""
    d = np.arange(-n, n + 1) * step_m
    dx, dy, dyaw = np.meshgrid(d, d, np.asarray(yaws_rad), indexing="ij")
    states = np.stack([x_m + dx.ravel(), y_m + dy.ravel(), yaw_rad + dyaw.ravel()], axis=1)
    centre = np.flatnonzero((dx.ravel() == 0) & (dy.ravel() == 0) & (dyaw.ravel() == 0))[0]
    return np.concatenate([states[centre:centre + 1], np.delete(states, centre, axis=0)])


def particle_states(m, n: int = 150, seed: int = 4) -> np.ndarray:
    """Particles around the map centre plus some whose footprint leaves the map."""
    g = np.random.default_rng(seed)
    cx, cy = m.width_m / 2, m.height_m / 2
    near = np.column_stack([cx + g.normal(0, 15, n), cy + g.normal(0, 15, n), g.uniform(-np.pi, np.pi, n)])
    far = np.array([[-40.0, cy, 0.3], [m.width_m + 5, cy, 1.0], [cx, 3.0, -2.0]])
    return np.concatenate([near, far])


# ---------------------------------------------------------------------- similarity functions
def test_mi_of_an_image_with_itself_is_its_entropy_and_drops_for_an_unrelated_image():
    g = np.random.default_rng(1)
    img = cv2.GaussianBlur(g.uniform(0, 255, (100, 100)).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    other = g.uniform(0, 255, img.shape).astype(np.float32)
    bins = 16
    h = entropy(img, bins)
    mi = mutual_information(np.stack([img.ravel(), other.ravel()]), img.ravel(), bins)
    assert mi[0] == pytest.approx(h, rel=1e-9)
    # independent images: the plug-in MI estimate is only its small-sample bias ~ (B-1)^2 / (2 K) nats
    assert 0.0 <= mi[1] < 4 * (bins - 1) ** 2 / (2 * img.size)
    assert mi[1] < 0.1 * h


def test_mi_matches_a_histogram2d_reference():
    g = np.random.default_rng(2)
    a = g.uniform(0, 255, 500)
    b = np.clip(a + g.normal(0, 40, a.size), 0, 255)
    joint, _, _ = np.histogram2d(b, a, bins=8, range=[[0, 256], [0, 256]])
    p = joint / joint.sum()
    px, py = p.sum(1, keepdims=True), p.sum(0, keepdims=True)
    nz = p > 0
    expected = float((p[nz] * np.log(p[nz] / (px @ py)[nz])).sum())
    assert mutual_information(b[None], a, 8)[0] == pytest.approx(expected, rel=1e-9)


def test_ncc_is_invariant_to_gain_and_offset_and_ssd_is_not():
    g = np.random.default_rng(3)
    ref = g.uniform(0, 255, 300)
    patch = ref + g.normal(0, 20, ref.size)
    rows = np.stack([patch, 0.4 * patch + 30.0, 1.7 * patch - 50.0])
    values = ncc(rows, ref)
    assert values[1] == pytest.approx(values[0], abs=1e-6)
    assert values[2] == pytest.approx(values[0], abs=1e-6)
    assert ncc(-rows[:1], ref)[0] == pytest.approx(-values[0], abs=1e-6)
    assert ncc(np.full((1, ref.size), 7.0), ref)[0] == 0.0
    assert not np.isclose(msd(rows[1:2], ref)[0], msd(rows[:1], ref)[0])


def test_msd_matches_the_direct_formula():
    g = np.random.default_rng(4)
    rows, ref = g.uniform(0, 255, (5, 64)), g.uniform(0, 255, 64)
    assert msd(rows, ref) == pytest.approx(((rows - ref) ** 2).mean(axis=1), rel=1e-4)


# ---------------------------------------------------------------------- patch reconstruction
def test_patch_sampler_reproduces_the_reduced_camera_frame_at_the_true_pose():
    m = textured_map()
    x, y, yaw = 100.0, 95.0, 0.7
    frame = render_frame(m, x, y, yaw)
    geo = PatchGeometry(60, 40)
    sampler = PatchSampler(m, CAMERA, geo, to_gray(m.rgb), ALT_M)
    patches, valid = sampler.sample(np.array([[x, y, yaw], [x + 10, y, yaw]]), ALT_M)
    ref = cv2.resize(to_gray(frame), (60, 40), interpolation=cv2.INTER_AREA)
    assert valid.all()
    err_true = np.abs(patches[0] - ref).mean()
    err_off = np.abs(patches[1] - ref).mean()
    assert err_true < 0.25 * err_off


def test_out_of_map_and_nodata_particles_are_flagged_not_nan():
    m = textured_map(200)
    nodata = np.zeros((200, 200), bool)
    nodata[:, :20] = True
    m = orthomap_standin(m.rgb, nodata=nodata)
    sampler = PatchSampler(m, CAMERA, PatchGeometry(30, 20), to_gray(m.rgb), ALT_M, nodata=m.nodata)
    states = np.array([[50.0, 50.0, 0.0], [5.0, 50.0, 0.0], [-100.0, 50.0, 0.0], [25.0, 50.0, 0.0]])
    _, valid = sampler.sample(states, ALT_M)
    assert valid.tolist() == [True, False, False, False]   # the last one's footprint covers the no-data strip
    model = SSDModel(DenseConfig(patch_width_px=30, patch_height_px=20))
    model.reset(briefing_standin(m), np.random.default_rng(0))
    prep = model.prepare(observation(render_frame(m, 50.0, 50.0, 0.0)), np.random.default_rng(0))
    ll = model.log_likelihood(prep, states, ALT_M)
    assert np.all(np.isfinite(ll)) and ll[0] > ll[1:].max()


# ---------------------------------------------------------------------- models
@pytest.mark.parametrize("cls", [SSDModel, NCCModel, MIModel])
def test_dense_models_peak_at_the_true_pose_on_a_shadow_free_frame(cls):
    m = textured_map()
    model = cls()
    model.reset(briefing_standin(m), np.random.default_rng(0))
    for x, y, yaw in ((100.0, 100.0, 0.3), (80.0, 120.0, -2.0)):
        prep = model.prepare(observation(render_frame(m, x, y, yaw), yaw), np.random.default_rng(0))
        states = offset_grid(x, y, yaw)
        ll = model.log_likelihood(prep, states, ALT_M)
        assert ll.shape == (len(states),) and ll.dtype == np.float64
        assert int(np.argmax(ll)) == 0, (cls.__name__, states[np.argmax(ll)])


def test_dense_config_rejects_bad_values():
    with pytest.raises(ConfigError, match="patch_width_px"):
        build_config(DenseConfig, {"patch_width_px": 1})
    with pytest.raises(ConfigError, match="sigma"):
        build_config(DenseConfig, {"sigma": 0.0})
    with pytest.raises(ConfigError, match="unknown key"):
        build_config(DenseConfig, {"patch_size": 3})


def test_models_refuse_to_run_before_reset_and_a_wrong_image_size():
    model = NCCModel()
    with pytest.raises(ConfigError, match="reset"):
        model.prepare(observation(np.zeros((80, 120, 3), np.uint8)), np.random.default_rng(0))
    model.reset(briefing_standin(textured_map(200)), np.random.default_rng(0))
    with pytest.raises(ConfigError, match="differs"):
        model.prepare(observation(np.zeros((40, 120, 3), np.uint8)), np.random.default_rng(0))


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
    states = particle_states(m)
    ll = model.log_likelihood(prep, states, ALT_M)
    patches, valid = model.sampler.sample(states, ALT_M)
    flat = patches.reshape(len(states), -1)
    flat[~valid] = 0.0
    xi = np.where(valid, mutual_information_reference(flat, prep.ref, model.config.bins) / prep.extra[0], 0.0)
    np.testing.assert_allclose(ll, -np.square(1.0 - xi) / (2.0 * model.config.sigma ** 2), rtol=0, atol=1e-9)
    assert int(np.argmax(ll)) != len(states) - 1 and np.isfinite(ll).all()
