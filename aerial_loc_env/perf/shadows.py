"""Speed of the shadow layer: full-map cast shadows (per episode) and per-frame shading / cloud sampling."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from aerial_loc_env.perf import Benchmark

MAP_SHAPE = (4800, 5600)          # the paper's 1.2 x 1.4 km database at 0.25 m/px
GSD_M = 0.25
FRAME_SHAPE = (400, 600)          # the paper's camera image


@lru_cache(maxsize=1)
def synthetic_dsm() -> np.ndarray:
    """Random boxes (5-40 m wide, 3-60 m tall) on flat ground, about 35 % built up, float32."""
    rng = np.random.default_rng(0)
    h, w = MAP_SHAPE
    dsm = np.zeros(MAP_SHAPE, np.float32)
    for _ in range(1500):
        r, c = rng.integers(0, h), rng.integers(0, w)
        bh, bw = rng.integers(20, 160, size=2)
        dsm[r:r + bh, c:c + bw] = rng.uniform(3.0, 60.0)
    return dsm


def _cast(azimuth_deg: float, downsample: int):
    from aerial_loc_env.world.shadows import Sun, cast_shadows

    dsm, sun = synthetic_dsm(), Sun(azimuth_deg, 35.0)
    return lambda: cast_shadows(dsm, GSD_M, GSD_M, sun, downsample=downsample)


def _soft(downsample: int, azimuth_samples: int = 1):
    from aerial_loc_env.world.shadows import Sun, sun_occlusion

    dsm, sun = synthetic_dsm(), Sun(160.0, 35.0)
    return lambda: sun_occlusion(dsm, GSD_M, GSD_M, sun, downsample=downsample, azimuth_samples=azimuth_samples)


def _shading():
    from aerial_loc_env.world.shadows import apply_shading

    rng = np.random.default_rng(1)
    img = rng.integers(0, 256, (*FRAME_SHAPE, 3), dtype=np.uint8)
    occ = rng.random(FRAME_SHAPE, dtype=np.float32)
    out = np.empty_like(img)
    return lambda: apply_shading(img, occ, 0.8, out=out)


def _clouds():
    from aerial_loc_env.world.shadows import CloudField

    field = CloudField(np.random.default_rng(2), 1400.0, 1200.0, cover=0.4, scale_m=150.0)
    c, s = np.cos(0.3) * GSD_M, np.sin(0.3) * GSD_M
    image_to_world = np.array([[c, -s, 700.0], [-s, -c, 600.0]])   # a rotated 150 x 100 m footprint
    return lambda: field.occlusion_image(12.5, image_to_world, FRAME_SHAPE)


BENCHMARKS = [
    Benchmark("shadows: cast mask 4800x5600 @0.25m, sun az 160 (row sweep)", lambda: _cast(160.0, 1),
              target_ratio=1000.0, unit="map", repeats=5),
    Benchmark("shadows: cast mask 4800x5600 @0.25m, sun az 110 (col sweep)", lambda: _cast(110.0, 1),
              target_ratio=1000.0, unit="map", repeats=5),
    Benchmark("shadows: cast mask 4800x5600, downsample 2 (0.5 m)", lambda: _cast(110.0, 2),
              target_ratio=250.0, unit="map", repeats=5),
    Benchmark("shadows: soft occlusion 4800x5600, downsample 2", lambda: _soft(2), unit="map", repeats=5),
    Benchmark("shadows: soft occlusion 4800x5600, full res", lambda: _soft(1), unit="map", repeats=3),
    Benchmark("shadows: soft occlusion 4800x5600, downsample 2, 3 azimuth strips", lambda: _soft(2, 3),
              unit="map", repeats=3),
    Benchmark("shadows: apply_shading 600x400x3 uint8", _shading, target_ratio=0.6, unit="frm", repeats=300),
    Benchmark("shadows: cloud occlusion in a 600x400 footprint", _clouds, target_ratio=1.0, unit="frm",
              repeats=300),
]
