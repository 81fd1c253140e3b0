"""Speed of one full MCL step (issue 4): motion, shadow detection, shadow-aware likelihood, resampling, estimate
at N = 700 particles, K = 70 pairs, c = 3 channels, on a 600 x 400 frame with cast shadows over a 2000 x 2000 px,
0.25 m/px synthetic map (the paper's camera at 200 m). Rendering is excluded: the frame is made once.

Target (issue 12): <= 1.0x the floor (one bare map warp) per step, median on one core.

Where the time goes (shadow-aware step, profiled): the frame's shadow detection and pairs ~0.3x the floor, the
particles' likelihood ~0.35x (of which the per-particle affines of ``camera_to_map`` and their product with
the pair points ~0.2x; the gather of 2K database words per particle and the XNOR count the rest), motion,
resampling, estimate and the filter's bookkeeping ~0.4-0.5x together: many small NumPy calls on N = 700, whose
fixed costs also dominate Table 5's steps at small K (a K = 10 step costs 0.7-0.8 of a K = 70 one).

Since then (bit-identical outputs, tests/estimators/test_mcl_step_speedups.py): ``camera_to_map`` scales the rows of the
world affine instead of N tiny 3x3 products (~100 -> ~40 us at N = 700), the motion model draws all its normals
in one call, the estimate's spread is a closed-form 2x2 eigenvalue, the detector's luminance means are exact
integer sums and the pair indices int32: ~1.23 -> ~1.12 ms a step (-9 %) on the 2-core machine, quiet. What is
left is still spread thin: detection ~0.15 ms (c3 0.035, its two masked means 0.035), reduction 0.03, the
particles' projections ~0.1 (the float32 einsum 0.06), index + gather + XNOR ~0.17, motion 0.08 (0.03 of it the
3.5k normal draws), resampling 0.045, estimate 0.05; no single call is above 0.06 ms.

Then compiled passes (numba; bit-identical, a 3-seed Table 5 run on the paper and realistic settings equal trial
for trial): the particles' side of the pairs (``mcl/intensity_pairs_kernels.pair_agreements``: projection, rounding,
lookup in the map's own RGB bytes and the XNOR count, pair-major so that one pair's lookups at all particles share
cache lines; ~0.1 ms), the frame's side (``camera_pairs``: pixels, reduced mask, coordinates), and the detector's
index, quantization and class statistics (``shadow_detection._index8`` / ``_split_stats``, c3 from a table of
NumPy's own arctan2 floats). Measured as the harness measures (each step right after floor warps, which evict
the caches; two alternating runs each against 3045540, load 1.2-1.5): shadow-aware 1.26x -> 0.96-0.99x,
conventional 1.12-1.15x -> 0.77-0.80x, restoration 1.70-1.72x -> 1.27-1.29x. What is left
after a floor warp: detection 0.21 ms (0.07 of it OpenCV's reduction, then cvtColor, Otsu and two morphology
passes), the pair kernel ~0.25 (cold: its lookups miss), ``camera_to_map`` ~0.14, the two ``rng.integers`` ~0.08,
motion ~0.13, the two observation parses ~0.12, estimate ~0.09.

Then fewer fixed costs and a prefetch (same bytes: the tests above, tests/estimators/test_mcl_step_speedups.py, and an
8-agent, 2-episode, 41-step PaperShadows run equal estimate for estimate, particle for particle): each particle's
``camera_to_map`` affine inside the pair kernel (``intensity_pairs_kernels.pose_affine``, NumPy's cos/sin), the motion's
per-particle arithmetic one pass, the detector's opening and closing one call (``_OpenClose``), its 1/4 reduction
(``_quarter``, cv2.resize's bytes) and exact luminance sums compiled, the likelihoods' log-mean without the
normalized weights, the pair lookups unrolled for RGB, and each pair's map lines prefetched while the previous
pair's lookups run (every step draws new pairs, whose lines no step touched: 4.5 -> 3.6 us a pair after floor
warps, 6.6 -> 4.4 on a 5 m cloud). Three runs each alternating with 57ad3e6 in one session on the 2-core Xeon VM
(load 1.55-1.92 from ``uptime``, another engineer's benchmarks on the other core; floor 0.84-0.89 ms):

=============================================  ===============  ===============
row                                            57ad3e6          now
=============================================  ===============  ===============
shadow-aware N=700 K=70 c=3                    0.96-0.98x       0.73-0.74x
conventional                                   0.80-0.81x       0.60-0.61x
restoration                                    1.30-1.32x       1.02-1.03x
shadow-weighted, map detector                  1.36-1.39x       1.13-1.14x
SSD / NCC 60x40 (perf/models.py)               4.22-4.31x /     4.19-4.26x /
                                               4.32-4.36x       4.32-4.38x
MI / abBRIEF / edges                           5.87-5.94x /     5.87-5.93x /
                                               7.29-7.36x /     7.29-7.33x /
                                               6.68-6.72x       6.66-6.78x
=============================================  ===============  ===============

What is left of a shadow-aware step after floor warps (instrumented, wall us, load 0.5): the first observation parse
~48 (6 warm: whatever runs first after the floor pays ~40), motion ~75 (the 3.5k normal draws ~35), the two
``rng.integers`` ~24, reduction ~38 (reading the cold frame), detection ~110 (cvtColor 10, the c3-table index 42,
Otsu 13, class statistics 29, morphology 25), the frame's pairs ~33, the pair kernel ~165 (~34 pairs kept), the
two log-sum-exps ~27, resampling ~37 plus the gather 10, estimate ~48. Tried and not kept: one ``rng.integers``
with per-element bounds (the same draws) was slower in the step (28 vs 24 us); the luminance (cvtColor's 15-bit
fixed point, exact over all 2^24 colours) inside the index pass made that pass as much slower as cvtColor cost;
prefetching every 4th or 16th particle, or two pairs ahead, was no better than every particle one pair ahead.
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
    obs = {"image": frame, "odometry": np.array([41.7, 0.0], np.float32), "yaw": np.array([yaw], np.float32),
           "altitude": np.array([_ALT_M], np.float32)}
    return briefing, obs


def _mcl_step(spec: str, **overrides) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.estimators.registry import make_agent

        briefing, obs = _scene()
        agent = make_agent(spec, particles_in_extras=False, **overrides)
        agent.reset(briefing, seed=0)
        agent.step(obs)  # past the first (motionless) step
        still = dict(obs, odometry=np.zeros(2, np.float32))   # keep the particles on the map

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
]
