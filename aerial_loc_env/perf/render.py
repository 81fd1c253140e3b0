"""Camera rendering speed: ``CameraRenderer``'s frames, the floor, and eq. (3) for many particles.

The frame rows render consecutive frames of one flight over one synthetic scene, as the env does: ``_scene`` is a
768 m map at 0.25 m/px (textured ground, 700 box buildings 5-30 m tall, soft cast shadows from a sun 40 deg up),
``_flight`` a 200 m radius circle at the paper's 41.7 m/s and 4 Hz (a frame overlaps the last one, as in an
episode); each call renders the next frame with shading strength 0.9, motion blur at the flight speed and the
renderer's photometry and noise. With shadows, the setup bakes them into the map over the flight's box before
timing, as the env does at reset, so a frame is the baked path.

- ``render ... cast shadows + noise (200 m)`` (target 2.0x): the nadir camera on the baked box;
- ``... no shadows``: the same frames without shadows;
- ``... (350 m, pyramid level 1)`` (target 2.0x): a coarser pyramid level, the box baked at that level on the
  first frame (the setup's compiling render);
- ``... perspective of the height model`` and ``... + gimbal tilt`` (target 3.0x): the perspective camera (the
  ray march, the per-pixel maps, the facades) sampling the baked box, untilted and tilted by a few mrad; the box
  is made from the footprints as that camera sees them and padded by two grid cells as the env pads it, so no
  frame leaves it for the per-frame path;
- ``FLOOR_NAME``: one bare bilinear warp of a 600 x 400 frame from the map at a fixed pose, by a renderer of its
  own (the ratios' denominator, ``perf/__init__.py``);
- ``camera.project_pixels``: eq. (3) for 5000 poses x 256 pixels, as the measurement models call it.

Each setup renders one frame before the timing starts: compiling the kernels (or loading them from numba's cache)
is never timed. The figures are in the README (speed) and docs/perf-log.md.
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

            # the footprints as the camera sees them (a box made from the untilted ones misses some tilted frames
            # by under a pixel, and those would time the slower per-frame path)
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
