"""The learned model's compiled kernels (``estimators/mcl/learned_kernels.py``) against plain NumPy: the encoder
(any odd kernel, stride and channel count, the outputs and terms padded to the kernel's groups) equals a direct
zero-padded convolution in float64, and the particles' scores (the surface computed at the cells their lookups
read, or over the box by ``cv2.matchTemplate``) equal a dense surface over the particles' box read by the same
bilinear lookups.

Tolerances: float32 sums of at most a few hundred products of unit-scale terms (relative error about
sqrt(terms) * 2^-24, below 1e-5); the scores are means of cosines (|value| <= 1) over the frame's cells."""

from __future__ import annotations

import math

import numpy as np
import pytest
from test_dense_models import briefing_standin, render_frame, textured_map
from test_mcl import observation

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl import learned
from aerial_loc_env.estimators.mcl.measurement import make_model

MODEL = "aerial_loc_env.estimators.mcl.learned:LearnedModel"


def _reference(image: np.ndarray, weights, biases, strides) -> np.ndarray:
    """The encoder's forward pass written out: float64 zero-padded convolutions, ReLU between, unit vectors."""
    x = np.asarray(image, np.float64)[None]
    for i, (w, b, s) in enumerate(zip(weights, biases, strides, strict=True)):
        cout, cin, k, _ = w.shape
        p = k // 2
        h, wd = x.shape[1:]
        ho, wo = (h - 1) // s + 1, (wd - 1) // s + 1
        xp = np.pad(x, ((0, 0), (p, p), (p, p)))
        y = np.zeros((cout, ho, wo)) + np.asarray(b, np.float64)[:, None, None]
        for dy in range(k):
            for dx in range(k):
                patch = xp[:, dy:dy + s * (ho - 1) + 1:s, dx:dx + s * (wo - 1) + 1:s]
                y += np.einsum("oc,chw->ohw", w[:, :, dy, dx].astype(np.float64), patch)
        x = np.maximum(y, 0.0) if i < len(weights) - 1 else y
    e = x.transpose(1, 2, 0)
    return e / np.maximum(np.linalg.norm(e, axis=2, keepdims=True), 1e-6)


@pytest.mark.parametrize(("kernels", "strides", "channels", "shape"), [
    ((5, 3, 3, 1), (2, 1, 1, 1), (16, 16, 16, 8), (41, 29)),   # the shipped design
    ((3, 1), (1, 1), (5, 3), (17, 12)),                      # outputs not a multiple of four
    ((3, 5), (3, 2), (6, 7), (23, 31)),                      # strides 3 and 2, a 5 x 5 after the first
    ((1,), (1,), (4,), (1, 1)),
    ((7, 3), (2, 1), (4, 4), (2, 3)),                        # a kernel wider than the image
])
def test_encoder_equals_a_direct_convolution(kernels, strides, channels, shape) -> None:
    g = np.random.default_rng(7)
    cins = (1,) + tuple(channels[:-1])
    ws = [(g.standard_normal((co, ci, k, k)) / math.sqrt(ci * k * k)).astype(np.float32)
          for co, ci, k in zip(channels, cins, kernels, strict=True)]
    bs = [(0.1 * g.standard_normal(co)).astype(np.float32) for co in channels]
    image = g.standard_normal(shape).astype(np.float32)
    out = learned.Encoder(ws, bs, list(strides))(image)
    ref = _reference(image, ws, bs, strides)
    assert out.dtype == np.float32 and out.shape == ref.shape
    np.testing.assert_allclose(out, ref, atol=1e-5)


def test_encoder_rejects_a_zero_stride() -> None:
    with pytest.raises(ConfigError, match="strides"):
        learned.Encoder([np.zeros((4, 1, 3, 3), np.float32)], [np.zeros(4, np.float32)], [0])


def _dense_scores(model, prepared, states: np.ndarray) -> np.ndarray:
    """The scores as one dense surface over the particles' whole box (clipped to the padded map), in float64."""
    emb = model.map
    a = emb.world_to_cell
    sx = a[0, 0] * states[:, 0] + a[0, 1] * states[:, 1] + a[0, 2] - prepared.centre_cell[0]
    sy = a[1, 0] * states[:, 0] + a[1, 1] * states[:, 1] + a[1, 2] - prepared.centre_cell[1]
    th, tw = prepared.template.shape[:2]
    mh, mw = emb.cells.shape[:2]
    fin = np.isfinite(sx) & np.isfinite(sy)
    a0, b0 = max(0, math.floor(sx[fin].min())), max(0, math.floor(sy[fin].min()))
    a1, b1 = min(mw - tw, math.ceil(sx[fin].max()) + 1), min(mh - th, math.ceil(sy[fin].max()) + 1)
    t = prepared.template.astype(np.float64)
    surface = np.array([[np.sum(emb.cells[b:b + th, c:c + tw] * t) for c in range(a0, a1 + 1)]
                        for b in range(b0, b1 + 1)]) / prepared.n_valid
    h, w = surface.shape
    surface = np.pad(surface, ((0, max(0, 2 - h)), (0, max(0, 2 - w))), mode="edge")
    v = learned.bilinear(surface, np.where(fin, sx - a0, -1.0), np.where(fin, sy - b0, -1.0), -1.0)
    return np.clip(v, -1.0, 1.0)


@pytest.fixture(scope="module")
def prepared_model():
    m = textured_map(300, seed=4)
    truth = (75.0, 75.0, 0.3)
    model = make_model(MODEL)
    model.reset(briefing_standin(m), np.random.default_rng(0))
    return model, model.prepare(observation(render_frame(m, *truth), yaw=truth[2]), np.random.default_rng(0)), truth


@pytest.mark.parametrize("path", ["cells", "box"])
@pytest.mark.parametrize("cloud", ["spread", "one", "a row", "a column", "at the edge", "with NaN"])
def test_scores_equal_a_dense_surface(prepared_model, cloud: str, path: str, monkeypatch) -> None:
    """Either way of computing the surface: at the particles' cells by the kernel, or over the box by OpenCV."""
    monkeypatch.setattr(learned, "CELLS_PER_REGION_CELL", 1e12 if path == "cells" else 0)
    model, prepared, truth = prepared_model
    g = np.random.default_rng(11)
    states = np.column_stack([truth[0] + g.normal(0, 12, 300), truth[1] + g.normal(0, 12, 300),
                              np.full(300, truth[2])])
    if cloud == "one":
        states = states[:1]
    elif cloud == "a row":
        states[:, 1] = truth[1] + 0.3
    elif cloud == "a column":
        states[:, 0] = truth[0] - 0.2
    elif cloud == "at the edge":         # over a corner of the map, some beyond its padding (-1 there)
        corner = np.linalg.solve(model.map.world_to_cell[:, :2], -model.map.world_to_cell[:, 2])
        states[:, :2] += corner - truth[:2] + g.normal(0, 40, (300, 2))
    elif cloud == "with NaN":
        states[:5, 0] = np.nan
    got = model.scores(prepared, states)
    ref = _dense_scores(model, prepared, states)
    assert np.all(np.isfinite(got)) and (got > -1.0).any()
    if cloud == "at the edge":
        assert (got == -1.0).any()
    np.testing.assert_allclose(got, ref, atol=2e-6)
