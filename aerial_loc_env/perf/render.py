"""Camera rendering speed: one 600 x 400 frame with cast shadows and sensor noise (target 2.0x the floor),
database patches (the floor itself, ``FLOOR_NAME``: one bare bilinear warp of the frame from the map), and eq. (3)
projections for many particles.

The perspective rows (target 3.0x, issue 11) measured 7.9-8.3x (9.1x with gimbal tilt) at load 0.7-0.8 and
7.2-7.5x (8.2-8.5x) at load 2.3-2.9 on 2 cores before their maps were made on the march's block grid and the views
sampled the baked shadows, 6.3-6.5x (7.3x) and 5.4-5.7x (6.4-6.7x) after (alternating runs; about 25 % less CPU
per frame). With the maps as numba kernels (``sensors.perspective_kernels``, bit-identical) and the compiled
finishing pass, 4.95-4.97x (5.47-5.73x) at load 1.5-2; in one process, interleaved (load 2.2), the maps cost 2.28x
the floor inside the render (2.56x tilted) where the OpenCV/NumPy maps cost 2.57x (3.17x): the frame 5.41x against
6.15x (5.96x against 7.02x).

Then (issue 11's last row) the baked box's remap, the finishing pass, the facades and the second finishing pass
became one compiled pass (``render_kernels.remap_finish``: OpenCV 5's remap arithmetic bit for bit, the facades'
gains applied to each row before its tone), the maps' kernels were rewritten so that LLVM vectorizes them (their
module docstring has the figures), and the bake box here is padded by two grid cells as the env pads it (6 of the
121 perspective frames had fallen back to the per-frame grid): 4.90-5.15x (5.42-5.77x tilted) at load 0-1.6 ->
3.07-3.24x (3.22-3.38x) at load 0-0.9, the frames unchanged. Where a frame's 2.6 ms go now (in flight, load 0,
floor 0.81-0.86 ms): ``remap_finish`` 1.48-1.52 ms (the bilinear sampling and tone about 0.9, the sensor stage
0.25, the ~10.7k facade pixels 0.06-0.1, and 0.1-0.2 more than ``warp_finish`` with the frame's affine on the same
box: the maps' reads and what the maps kernels evicted), ``view_maps`` 0.45, ``march`` 0.18, the Python around them
0.45 (``ReliefView.maps`` 0.19; the rest of the render about a hundred small NumPy/OpenCV calls, 2-5 us each when
cold). Measured and not kept: prefetching the box rows that the row 8 rows down reads (no faster), the flat cells'
points computed in the pass instead of read from the maps (1.44 against 1.28 ms replayed: the arithmetic and the
per-cell copies cost more than the reads), the rows sampled bottom-up so that the maps written last are read first
(1.57 against 1.48 ms). What 3x needs: the maps and the sampling in one pass per band of rows (the maps would not go
through memory; the facades' gains, computed by NumPy between the two kernels, would wait as a list of their
pixels' pre-tone values for a last small pass), and fewer small NumPy calls a frame.

The same code measured on another kind of 2-core Xeon VM (Emerald Rapids, 2.1 GHz, a host whose neighbours load
its memory: the floor's own median ranged 1.18-2.13 ms within one run) gave 2.20-2.49x (render) and 3.54-3.95x
(perspective; tilted 3.53-4.17x): the passes are compute- and cache-bound where the floor's warp of one pose stays
in cache. What was done about it (frames unchanged, each step measured in alternating runs or replayed interleaved
in one process): the box's neighbour loads as AVX-512 gathers of neighbour pairs where gathers are fast
(``jit.gather_pairs16``, Sapphire Rapids on: 1.36 ms of scalar loads a frame -> 0.43 ms, 32-bit gathers
0.78), the tone lookups as VBMI byte permutes (``lut_rgba16``: 0.44 -> 0.30 ms of lookups), the noise bank's rows
prefetched 16 rows ahead (the box-sampling pass 1.75 -> 1.70-1.72 ms replayed with the variants' order rotated;
the first figure given, 2.34 -> 2.19-2.22, was inflated by the order) and the tilt's two matrix inverses made once
per camera (0.05-0.09 ms a tilted frame): render 1.52-1.82x, perspective 2.95-3.39x and tilted 3.06-3.42x there,
the spread being the host's load (the same code, minutes apart). Measured and not kept: the maps made a band of
rows at a time inside the sampling pass (``view_maps`` and the sampling fused, so that no map goes through memory;
the facades, whose gains NumPy computes from the pass's facing directions, finished after it): replayed, the fused
pass 2.70 ms against 2.66 for the two kernels, plus 0.1 ms for the facades, and 3.9-4.0x against 3.2-3.4x in the
benchmark; the box's rows prefetched ahead through the maps, and the maps' own rows (no gain).

Next session, same VM (frames unchanged; kernels replayed with the variants' order rotated, whole frames of two
renderers interleaved in one process with their order rotated, or alternating runs: a variant replayed second had
found the box and the bank warm in L3, which had flattered some earlier replayed figures): the sensor stage in
float32 lanes (``render_kernels._vignetted``: the exact /255 multiply as ``h v (1/255)`` in float32, checked over all
pairs; numba had widened the integer form to 8 int64 lanes; 0.43-0.47 -> 0.33-0.36 ms back to back), the bilinear
weights kept per pixel with the blend looping over a pixel's channels (``remap_finish`` 1.70-1.76 -> 1.44-1.54 ms,
``warp_finish`` 1.67 -> 1.45 ms replayed), facades listed by the maps kernel in pixel order and walked by row
(no counting sort or copies), the height lookups as ``jit.gather_f32x16`` (``view_maps`` 3-5 %), the box
lines 16 rows ahead prefetched from the maps (0.02-0.09 ms), the tone table's gains by one compiled call and the
footprint's corners once a frame. This benchmark's box is now made from the footprints as the tilted camera sees
them (6 of the tilted flight's 125 frames had left the untilted box by under a pixel and timed the per-frame
fallback). In 24 shorter runs the rows measured 2.57-3.17x and 2.68-3.28x (each at or under 3x in 22), two whole
``make bench`` runs 2.95x / 3.07x and 2.86x / 3.15x; 54f7072 alternating with six of them 3.08-3.32x / 3.20-3.31x.
A quiet frame: ``remap_finish`` 1.35-1.45 ms, ``view_maps`` 0.6-0.68, ``march`` 0.24 and 0.38 ms of Python (cold:
a NumPy call costs 3-5x its warm time after the kernels and the floor's warps; the tone table, the noise offsets'
``rng.integers`` and the maps' preamble are the largest). Measured and not kept: drawing the frame's photometry
before the maps (no faster: every Python step of a frame runs cold), the maps written only in relief cells with
the flat cells' points computed in the sampling pass (0.13 ms slower, tilted 0.39), the sigma from a gathered table
instead of the square root, the facades' four bytes scaled together, the noise bank prefetched 32-128 rows ahead.

What is left does not move with arithmetic or the interpreter (the session after, same VM; variants as scratch copies
in alternating runs, none kept): the noise off altogether 2.40-2.61x against 2.65-2.82x (the whole noise step is
worth about 0.25x), but with the noise on: an int8 bank (half its bytes) 2.51-2.59x against 2.53-2.58x, a
counter-based hash instead of the bank (three 32-bit multiplies a value) 2.77-2.83x against 2.56-2.67x, the sigma's
square root replaced by a linear form 2.58-2.66x against 2.57-2.62x, the tilt's divisions replaced by products
(tilted row) 2.71-2.89x against 2.69-2.97x, the maps' whole Python preamble memoized per pose (an upper bound for
moving it into a compiled call) 2.55-2.86x against 2.64-2.76x. Each within the run-to-run spread: what is left points
at a frame's memory traffic (the maps written and read back, the box's new lines) and the caches the floor's warps
leave cold, which would also be why it grows more than the floor's when the host's neighbours load the memory.

Where a baked-shadow frame's time goes (2-core Xeon VM, load 1-2, floor 0.87-0.95 ms): the RGBA warp of the baked
box 1.0-1.3 ms (more than the floor: a flight reads a new, rotated region each frame, and the finishing pass in
between evicts it from L2, which costs the next warp about 0.3 ms), then ONE compiled pass
(``sensors.render_kernels.finish``, numba) of 0.55-0.6 ms for everything the six OpenCV passes and the RGB drop, alpha
and mask did in 1.15 ms (tone lookups 0.2, vignetting and noise with the sigma computed 0.33), the pose geometry
and the frame's draws 0.05-0.1 ms. Measured and not taken: the sigma read from a table (a gather per element, 0.6-1.0
ms against 0.33 for the float32 square root: gathers are slow on this CPU), the kernel in bands interleaved with
warps of those bands (no faster, and not bit-identical: a shifted warp matrix rounds differently), the pass run
bottom-up, huge pages for the baked box. Since then the warp is done inside the pass (``render_kernels.warp_finish``:
OpenCV 5's warpAffine arithmetic reproduced bit for bit, each row warped and finished in L1, the box's rows 8 frame
rows ahead prefetched): 2.42-2.51x -> 2.08-2.16x (2.15-2.29 -> 1.85-1.90 ms; the env step 2.40-2.47 -> 2.14-2.19
ms) in three alternating runs at load 0.8-1.0. Then 2.04-2.15x -> 1.75-1.84x (1.78-1.90 -> 1.54-1.57 ms) with the
pass compiled for 512-bit vectors throughout (``jit.wide_vectors``): with LLVM's default mix of 256- and
512-bit loops the pass took 1.25 ms back to back but 1.45-1.75 ms after 4 ms of other work (the floor warps
between frames here, the estimators in an episode; a bare Python loop did it too), 1.10 and 1.11-1.15 ms with it.
The same hint on the MCL kernels made SSD/NCC and the pair models slower (4.3x -> 5.1x), so it is not there; the
perspective kernels as rewritten since take it (0.21 -> 0.19 ms, 0.55 -> 0.53 ms a frame). The first frame of a
process compiles the kernels (about 3 s with an empty numba cache, 0.3-0.4 s to load them from it): setups render
one frame before the timing starts.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import cv2
import numpy as np

from aerial_loc_env.perf import FLOOR_NAME, Benchmark

_MAP_PX = 3072
_GSD_M = 0.25
_SPEED_MPS = 41.6667   # the paper's flight speed


@lru_cache(maxsize=1)
def _scene(seed: int = 0):
    """A 768 m synthetic scene: textured ground, box buildings 5-30 m tall, soft cast shadows (sun 40 deg)."""
    from types import SimpleNamespace

    from aerial_loc_env.world.shadows import Sun, sun_occlusion

    rng = np.random.default_rng(seed)
    rgb = cv2.resize(rng.integers(40, 220, (384, 384, 3), dtype=np.uint8), (_MAP_PX, _MAP_PX),
                     interpolation=cv2.INTER_CUBIC)
    dsm = np.zeros((_MAP_PX, _MAP_PX), np.float32)
    for _ in range(700):
        u, v = rng.integers(0, _MAP_PX - 80, 2)
        w, h = rng.integers(20, 80, 2)
        dsm[v:v + h, u:u + w] = rng.uniform(5.0, 30.0)
        rgb[v:v + h, u:u + w] = rng.integers(60, 200, 3)
    grid = sun_occlusion(dsm, _GSD_M, _GSD_M, Sun(azimuth_deg=200.0, elevation_deg=40.0), downsample=2)
    orthomap = SimpleNamespace(rgb=rgb, gsd_x_m=_GSD_M, gsd_y_m=_GSD_M, height_px=_MAP_PX, width_px=_MAP_PX,
                               nodata=None, name="bench-scene", dsm_m=dsm)
    return orthomap, grid


def _flight() -> list[tuple[float, float, float]]:
    """Consecutive frames of a flight, as the env renders them: a 200 m radius circle around the scene's centre at
    the paper's 41.7 m/s and 4 Hz (10.4 m between frames, so a frame overlaps the last one as in an episode)."""
    n = round(2.0 * np.pi * 200.0 / (_SPEED_MPS * 0.25))
    theta = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    c = 0.5 * _MAP_PX * _GSD_M
    return [(c + 200.0 * np.cos(t), c + 200.0 * np.sin(t), float(np.angle(np.exp(1j * (t + np.pi / 2)))))
            for t in theta]


def _render_setup(altitude_m: float, shadows: bool, perspective: bool = False,
                  tilt_rad: tuple[float, float] = (0.0, 0.0)) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.sensors.camera import Pose
        from aerial_loc_env.sensors.perspective import PerspectiveConfig
        from aerial_loc_env.sensors.render import CameraRenderer

        orthomap, grid = _scene()
        renderer = CameraRenderer(orthomap, perspective=PerspectiveConfig(enabled=True) if perspective else None)
        rng = np.random.default_rng(1)
        poses = [Pose(*p, altitude_m) for p in _flight()]
        state = {"i": 0}
        shading = {"strength": 0.9}
        occlusion = grid if shadows else None
        if shadows:  # as the env does at reset: shaded into the map over the flight's box (views sample it too)
            from aerial_loc_env.sensors.perspective import footprint_px, tilt_homography

            # the footprints as the camera sees them (tilted: 6 of the 125 frames had left a box made from the
            # untilted ones by up to 0.8 px and taken the per-frame path, about 3x slower)
            tilt = tilt_homography(renderer.camera, *tilt_rad) if any(tilt_rad) else None
            corners = np.concatenate([footprint_px(renderer.camera_to_map(p), renderer.camera, tilt) for p in poses])
            pad = 2 * grid.factor    # as the env pads it (else a view's reads leave the box at the circle's extremes)
            box = (*(np.floor(corners.min(axis=0)).astype(int) - pad),
                   *(np.ceil(corners.max(axis=0)).astype(int) + pad))
            occlusion = renderer.bake(grid, shading, box) or grid

        renderer.render(poses[0], np.random.default_rng(0), occlusion, shading, tilt_rad=tilt_rad)  # compiles

        def run() -> object:
            state["i"] = (state["i"] + 1) % len(poses)
            return renderer.render(poses[state["i"]], rng, occlusion, shading, speed_mps=_SPEED_MPS,
                                   tilt_rad=tilt_rad)

        return run

    return setup


@lru_cache(maxsize=1)
def _patch_setup() -> Callable[[], object]:
    """The floor: one renderer (its private RGBA map copy) shared by the floor row and the interleaved floor calls,
    so that the row times the same warm warp as the ratios' denominator."""
    from aerial_loc_env.sensors.camera import Pose
    from aerial_loc_env.sensors.render import CameraRenderer

    renderer = CameraRenderer(_scene()[0])
    pose = Pose(384.0, 384.0, 0.7, 200.0)
    return lambda: renderer.database_patch(pose)


def _project_setup() -> Callable[[], object]:
    from aerial_loc_env.sensors.camera import CameraModel

    orthomap, _ = _scene()
    rng = np.random.default_rng(2)
    n = 5000
    x, y, yaw = rng.uniform(170, 598, n), rng.uniform(170, 598, n), rng.uniform(-np.pi, np.pi, n)
    uv = rng.uniform(0, 600, (256, 2))
    camera = CameraModel()
    return lambda: camera.project_pixels(orthomap, uv, x, y, yaw, 200.0)


BENCHMARKS = [
    Benchmark("render 600x400 + cast shadows + noise (200 m)", _render_setup(200.0, True), target_ratio=2.0,
              unit="frame", repeats=200),
    Benchmark("render 600x400 + noise, no shadows (200 m)", _render_setup(200.0, False), unit="frame",
              repeats=200),
    Benchmark("render 600x400 + cast shadows + noise (350 m, pyramid level 1)", _render_setup(350.0, True),
              target_ratio=2.0, unit="frame", repeats=200),
    Benchmark("render 600x400 perspective of the height model + cast shadows + noise (200 m)",
              _render_setup(200.0, True, perspective=True), target_ratio=3.0, unit="frame", repeats=200),
    Benchmark("render 600x400 perspective + gimbal tilt + cast shadows + noise (200 m)",
              _render_setup(200.0, True, perspective=True, tilt_rad=(0.004, -0.003)), target_ratio=3.0,
              unit="frame", repeats=200),
    Benchmark(FLOOR_NAME, _patch_setup, unit="patch", repeats=200),
    Benchmark("camera.project_pixels: 5000 poses x 256 pixels (eq. 3)", _project_setup, unit="call", repeats=50),
]
