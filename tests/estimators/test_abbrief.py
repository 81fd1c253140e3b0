"""abBRIEF measurement model: the BRIEF pattern, the CIELab a/b descriptor, the peak at the true pose."""

from __future__ import annotations

import numpy as np
import pytest
from test_dense_models import (
    ALT_M,
    briefing_standin,
    observation,
    offset_grid,
    particle_states,
    render_frame,
    textured_map,
)

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.abbrief import (
    ABBriefConfig,
    ABBriefModel,
    brief_pattern,
    lab_channels,
    reduced_lab,
)
from aerial_loc_env.estimators.patches import reduce_image


def test_brief_pattern_is_seeded_inside_its_cells_and_gaussian():
    w, h, kx, ky, t = 60, 40, 3, 2, 2000
    a1, a2 = brief_pattern(w, h, kx, ky, t, np.random.default_rng(5))
    b1, b2 = brief_pattern(w, h, kx, ky, t, np.random.default_rng(5))
    assert np.array_equal(a1, b1) and np.array_equal(a2, b2)
    assert a1.shape == (kx * ky * t,) and np.all(a1 != a2)
    cols, rows = a1 % w, a1 // w
    cell = (np.arange(kx * ky).repeat(t))
    cx, cy = cell % kx, cell // kx
    assert np.all(cols // (w // kx) == cx) and np.all(rows // (h // ky) == cy)
    # G II: per-axis std S/5 (20 px cells -> 4 px); rounding adds 1/12 px^2 of variance, clipping removes little
    dx = cols - ((cx + 0.5) * (w / kx) - 0.5)
    assert np.std(dx) == pytest.approx(np.sqrt(4.0 ** 2 + 1 / 12), rel=0.08)


def test_lab_channels_select_the_chromatic_planes():
    rgb = np.zeros((2, 2, 3), np.uint8)
    rgb[0, 0] = (255, 0, 0)         # red: a* > 0
    rgb[0, 1] = (0, 0, 255)         # blue: b* < 0
    rgb[1, :] = (128, 128, 128)     # grey: a* = b* = 0 (128 in 8-bit coding)
    ab = lab_channels(rgb, "ab")
    assert ab.shape == (2, 2, 2)
    assert ab[0, 0, 0] > 150 and ab[0, 1, 1] < 100
    assert ab[1, 0] == pytest.approx([128, 128], abs=1)
    assert lab_channels(rgb, "L").shape == (2, 2, 1)


@pytest.mark.parametrize("channels", ["ab", "L"])
def test_abbrief_peaks_at_the_true_pose_on_a_shadow_free_frame(channels):
    m = textured_map(seed=3)
    model = ABBriefModel(ABBriefConfig(channels=channels))
    model.reset(briefing_standin(m), np.random.default_rng(0))
    for x, y, yaw in ((100.0, 100.0, 0.3), (120.0, 90.0, 2.5)):
        prep = model.prepare(observation(render_frame(m, x, y, yaw), yaw), np.random.default_rng(0))
        states = offset_grid(x, y, yaw)
        ll = model.log_likelihood(prep, states, ALT_M)
        assert ll.dtype == np.float64 and int(np.argmax(ll)) == 0
        xi = model.similarity(prep, states, ALT_M)
        assert xi[0] > 0.9


def test_abbrief_out_of_map_particles_score_chance():
    m = textured_map(200)
    model = ABBriefModel()
    model.reset(briefing_standin(m), np.random.default_rng(0))
    prep = model.prepare(observation(render_frame(m, 50.0, 50.0, 0.0)), np.random.default_rng(0))
    xi = model.similarity(prep, np.array([[50.0, 50.0, 0.0], [-300.0, 50.0, 0.0]]), ALT_M)
    assert xi[1] == 0.5 and xi[0] > 0.9


def test_abbrief_config_checks_the_grid():
    with pytest.raises(ConfigError, match="keypoint"):
        build_config(ABBriefConfig, {"grid_width_px": 8, "keypoints_x": 5})
    with pytest.raises(ConfigError, match="channels"):
        build_config(ABBriefConfig, {"channels": "rgb"})


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
    states = np.concatenate([[[x, y, yaw]], particle_states(m)])
    xi = model.similarity(prep, states, ALT_M)
    ref = model.similarity_reference(prep, states, ALT_M)
    np.testing.assert_array_equal(xi, ref)                 # exact integer counts over the same bits
    assert np.any(xi == 0.5) and xi[0] > 0.8 and int(np.argmax(xi)) == 0


@pytest.mark.parametrize("channels", ["ab", "L", "Lab"])
@pytest.mark.parametrize("size", [(60, 40), (37, 23), (120, 80)])
def test_reduced_lab_is_bit_identical_to_reducing_the_selected_channels(channels, size):
    img = render_frame(textured_map(200, seed=6), 50.0, 50.0, 0.2)
    ref = reduce_image(lab_channels(img, channels), *size)          # (h, w) for one channel: cv2 drops it
    np.testing.assert_array_equal(reduced_lab(img, channels, *size), ref.reshape(size[1], size[0], -1))
