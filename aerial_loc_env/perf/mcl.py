"""Speed of one full MCL step (issue 4): motion, shadow detection, likelihood, resampling, estimate at N = 700
particles, K = 70 pairs, c = 3 channels, on a 600 x 400 frame with cast shadows over a 2000 x 2000 px, 0.25 m/px
synthetic map (the paper's camera at 200 m). Rendering is excluded: the frame is made once (``_scene``: a bare warp
of the map at one pose, two building shadows shaded in).

Each row times ``step`` of one shipped agent (shadow-aware, conventional, restoration, shadow-weighted with the map
detector) on that frame after a first step, with zero odometry so that the particles stay on the map. Each step
does an episode's work: it draws new pairs, so the frame's side (detection, pairs) and the particles' side
(projection, lookups, counts) are redone, and the harness's floor warps between steps leave the caches cold as
an episode's rendering does.

Target (issue 12): <= 1.0x the floor (one bare map warp) per step, median on one core. The figures, and where a
step's time goes, are in docs/perf-log.md.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from aerial_loc_env.perf import Benchmark

_ALT_M = 200.0


def _scene(seed: int = 0) -> tuple[object, dict]:
    """A real Briefing over a textured colour map and one shadowed observation at its centre."""
    from aerial_loc_env.env.briefing import Briefing, OdometryNoise, Prior
    from aerial_loc_env.sensors.camera import CameraModel
    from aerial_loc_env.world.maps.geo import LocalTangentGeoref
    from aerial_loc_env.world.maps.orthomap import Orthomap
    from aerial_loc_env.world.shadows import apply_shading

    g = np.random.default_rng(seed)
    size, gsd = 2000, 0.25
    chans = []
    for _ in range(3):
        img = np.zeros((size, size), np.float32)
        for sigma in (24.0, 6.0, 2.0):
            img += cv2.GaussianBlur(g.standard_normal((size, size)).astype(np.float32), (0, 0), sigma) * sigma
        chans.append(np.clip(120 + img / img.std() * 35, 0, 255))
    rgb = np.stack(chans, axis=-1).astype(np.uint8)
    orthomap = Orthomap(rgb, gsd, gsd, LocalTangentGeoref(37.5, 127.0, gsd, gsd, 0.0, float(size)), name="perf")
    camera = CameraModel()
    x, y, yaw = 250.0, 250.0, 0.4
    briefing = Briefing(orthomap, camera, Prior("gaussian", (x, y), 15.0), 0.25, _ALT_M, OdometryNoise(), "perf")
    a = camera.camera_to_map(orthomap, x, y, yaw, _ALT_M)
    frame = cv2.warpAffine(rgb, a, (camera.width_px, camera.height_px), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    occ = np.zeros(frame.shape[:2], np.float32)
    occ[60:220, 80:300] = 1.0          # two building shadows, ~30 % of the frame
    occ[250:380, 380:560] = 1.0
    frame = apply_shading(frame, occ, 0.9)
    obs = {"image": frame, "odometry": np.array([41.7, 0.0, 0.0], np.float32), "yaw": np.array([yaw], np.float32),
           "altitude": np.array([_ALT_M], np.float32)}
    return briefing, obs


def _mcl_step(spec: str, **overrides) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.estimators.registry import make_agent

        briefing, obs = _scene()
        agent = make_agent(spec, particles_in_extras=False, **overrides)
        agent.reset(briefing, seed=0)
        agent.step(obs)  # past the first (motionless) step
        still = dict(obs, odometry=np.zeros(3, np.float32))   # keep the particles on the map

        def step() -> object:
            return agent.step(still)

        return step

    return setup


BENCHMARKS = [
    Benchmark("mcl step shadow-aware N=700 K=70 c=3 (600x400)", _mcl_step("mcl-shadow-aware"),
              target_ratio=1.0, unit="step", repeats=200),
    Benchmark("mcl step conventional N=700 K=70 c=3 (600x400)", _mcl_step("mcl-conventional"),
              unit="step", repeats=200),
    Benchmark("mcl step restoration N=700 K=70 c=3 (600x400)", _mcl_step("mcl-restoration"),
              unit="step", repeats=200),
    Benchmark("mcl step shadow-weighted, map detector N=700 K=70 c=3", _mcl_step("mcl-shadow-weighted"),
              unit="step", repeats=200),
    # the learned model (issue 23): the frame warped north-up and embedded, one correlation surface over the
    # particles' box, bilinear lookups; the map's embedding is made at reset. Target: <= 5x the floor.
    Benchmark("mcl step learned N=700 (600x400)", _mcl_step("mcl-learned"), target_ratio=5.0, unit="step",
              repeats=200),
]
