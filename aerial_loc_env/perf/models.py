"""Speed of the comparison measurement models and baselines: one MCL step (prepare the 600 x 400 frame, score
N = 700 particles) on a 2000 x 2000 px, 0.25 m/px synthetic map with the paper's camera at 200 m.

Targets (ratios to the floor, one bare map warp; issue 12, MI's tightened by issue 25): SSD and NCC at 60 x 40
patches <= 5x; MI <= 8x; abBRIEF <= 8x; on AVX2-only CPUs as with AVX-512.

What a row times: every model samples each particle's view straight from the stored map level by its affine and
scores it in the same compiled pass (``estimators/patches_kernels.py``, numba): no coordinate maps, no (N, h, w)
stack, N h w samples a step (1.68 M for SSD and NCC at 60 x 40), the coordinates in one vectorized loop, the
neighbour pairs' loads and the fma chain 8 points at a time in a second (``jit.bilinear_f32x8``). abBRIEF's
camera side (CIELab of the whole 600 x 400 frame and its area reduction) is a fixed cost per step. The harness's
warm-up call compiles the kernel (cached on disk after). The figures are in docs/perf-log.md.
"""

from __future__ import annotations

from collections.abc import Callable
from types import SimpleNamespace

import cv2
import numpy as np

from aerial_loc_env.perf import Benchmark

_N = 700
_ALT_M = 200.0


def _scene(seed: int = 0) -> tuple[SimpleNamespace, dict, np.ndarray]:
    """A textured map (briefing-like namespace), one observation and N particle states around the truth."""
    from aerial_loc_env.sensors.camera import CameraModel

    g = np.random.default_rng(seed)
    size = 2000
    img = np.zeros((size, size), np.float32)
    for sigma in (24.0, 6.0, 2.0):
        img += cv2.GaussianBlur(g.standard_normal((size, size)).astype(np.float32), (0, 0), sigma) * sigma
    img = np.clip(120 + img / img.std() * 35, 0, 255)
    rgb = np.repeat(img[..., None], 3, axis=2).astype(np.uint8)
    gsd = 0.25
    orthomap = SimpleNamespace(rgb=rgb, gsd_x_m=gsd, gsd_y_m=gsd, width_px=size, height_px=size, nodata=None,
                               dsm_m=None, width_m=size * gsd, height_m=size * gsd, name="perf")
    camera = CameraModel()
    briefing = SimpleNamespace(orthomap=orthomap, camera=camera, altitude_m=_ALT_M, dt_s=0.25,
                               prior=SimpleNamespace(kind="gaussian", mean_xy_m=(250.0, 250.0), std_xy_m=15.0),
                               odometry_noise=SimpleNamespace(speed_std_mps=0.1, yaw_rate_std_radps=0.087,
                                                              heading_std_rad=0.035, altitude_std_m=1.0,
                                                              lateral_std_mps=0.1),
                               scenario_id="perf")
    x, y, yaw = 250.0, 250.0, 0.4
    a = camera.camera_to_map(orthomap, x, y, yaw, _ALT_M)
    frame = cv2.warpAffine(rgb, a, (camera.width_px, camera.height_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    obs = {"image": frame, "odometry": np.zeros(3, np.float32), "yaw": np.array([yaw], np.float32),
           "altitude": np.array([_ALT_M], np.float32)}
    states = np.column_stack([x + g.normal(0, 15, _N), y + g.normal(0, 15, _N), yaw + g.normal(0, 0.05, _N)])
    return briefing, obs, states


def _model_step(name: str, **params) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.estimators.mcl.measurement import MODELS

        briefing, obs, states = _scene()
        model = MODELS[name](params, f"perf {name}")
        model.reset(briefing, np.random.default_rng(0))
        g = np.random.default_rng(1)

        def step() -> object:
            return model.log_likelihood(model.prepare(obs, g), states, _ALT_M)

        return step

    return setup


def _ssd_loop_reference() -> Callable[[], object]:
    """What the vectorized models replace: one ``cv2.warpAffine`` per particle (same level, same patches)."""
    from aerial_loc_env.estimators.mcl.dense import SSDModel

    briefing, obs, states = _scene()
    model = SSDModel()
    model.reset(briefing, np.random.default_rng(0))
    sampler = model.sampler
    size = (sampler.geometry.width_px, sampler.geometry.height_px)

    def step() -> object:
        ref = model.prepare(obs, None).ref
        affines = sampler.grid_to_level(states, _ALT_M)
        patches = np.stack([cv2.warpAffine(sampler.level, a, size, flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
                            for a in affines])
        return np.square(patches.reshape(len(states), -1) - ref).mean(axis=1)

    return step


def _agent_step(spec: str) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.estimators.registry import make_agent

        briefing, obs, _ = _scene()
        agent = make_agent(spec)
        agent.reset(briefing, seed=0)
        agent.step(obs)                       # first fix: later steps search the tracking window

        def step() -> object:
            return agent.step(obs)

        return step

    return setup


def _import_models() -> None:
    import importlib

    for module in ("dense", "abbrief", "edges"):
        try:
            importlib.import_module(f"aerial_loc_env.estimators.mcl.{module}")
        except ImportError:  # pragma: no cover - a model not written yet
            pass


_import_models()

BENCHMARKS = [
    Benchmark("MCL step SSD 60x40, N=700", _model_step("ssd"), target_ratio=5.0, unit="step"),
    Benchmark("MCL step NCC 60x40, N=700", _model_step("ncc"), target_ratio=5.0, unit="step"),
    Benchmark("MCL step MI 60x40 16 bins, N=700", _model_step("mi"), target_ratio=8.0, unit="step"),
    Benchmark("reference: SSD with one warpAffine per particle, N=700", _ssd_loop_reference, unit="step"),
    Benchmark("MCL step abBRIEF 60x40 12x64x2 bits, N=700", _model_step("abbrief"), target_ratio=8.0,
              unit="step"),
    Benchmark("MCL step edges 6x4 cells (incl. camera features), N=700", _model_step("edges"), unit="step"),
    Benchmark("baseline step template-ncc (1 m/px, 40 m window)", _agent_step("template-ncc"), unit="step"),
    Benchmark("baseline step features-orb (0.5 m/px, 40 m window)", _agent_step("features-orb"), unit="step",
              repeats=10),
]
