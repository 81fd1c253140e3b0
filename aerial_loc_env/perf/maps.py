"""Map database speed: GeoTIFF loading, memory-mapped bundles (what each vectorized env worker pays), and
vectorized world <-> lat/lon conversions. Synthetic 2048 x 2048 data, so the figures do not need ../shared/data.
"""

from __future__ import annotations

import pickle
import tempfile
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np

from aerial_loc_env.perf import Benchmark

_N = 2048


def _tile(tmp: Path) -> Path:
    """A JPEG-compressed EPSG:3395 GeoTIFF like the real tiles: smooth texture, black top-left wedge."""
    import tifffile

    rng = np.random.default_rng(0)
    rgb = cv2.resize(rng.integers(30, 230, (256, 256, 3), dtype=np.uint8), (_N, _N), interpolation=cv2.INTER_CUBIC)
    yy, xx = np.mgrid[:_N, :_N]
    rgb[xx + yy < _N // 2] = 0
    keys = (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 3395)
    path = tmp / "tile.tif"
    tifffile.imwrite(path, rgb, photometric="rgb", compression="jpeg", tile=(256, 256), extratags=[
        (33550, "d", 3, (0.1, 0.1, 0.0), True), (33922, "d", 6, (0, 0, 0, -46189.5, 4719172.2, 0), True),
        (34735, "H", len(keys), keys, True)])
    return path


def _load_geotiff() -> Callable[[], object]:
    from aerial_loc_env.world.maps.io import load_orthomap

    tmp = tempfile.TemporaryDirectory()
    path = _tile(Path(tmp.name))

    def run() -> object:
        _ = tmp   # keep the directory alive as long as the benchmark
        return load_orthomap(path)

    return run


def _bundle_open_and_pickle() -> Callable[[], object]:
    from aerial_loc_env.world.maps.io import load_orthomap
    from aerial_loc_env.world.maps.orthomap import Orthomap

    tmp = tempfile.TemporaryDirectory()
    bundle = load_orthomap(_tile(Path(tmp.name))).save_bundle(Path(tmp.name) / "tile.alm")

    def run() -> object:
        _ = tmp
        om = Orthomap.load_bundle(bundle)
        return pickle.loads(pickle.dumps(om))   # what gymnasium's AsyncVectorEnv does per worker

    return run


def _world_to_latlon(kind: str) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        from aerial_loc_env.world.maps.geo import LocalTangentGeoref, WorldMercatorGeoref
        from aerial_loc_env.world.maps.orthomap import Orthomap

        if kind == "EPSG:3395":
            g = WorldMercatorGeoref.north_up("EPSG:3395", -46189.5, 4719172.2, 0.1, 0.1)
        else:
            g = LocalTangentGeoref.centered(39.17, -0.414, _N, _N, 0.0776)
        om = Orthomap(np.zeros((_N, _N, 3), np.uint8), 0.0776, 0.0776, g)
        rng = np.random.default_rng(1)
        x, y = rng.uniform(0, om.width_m, 100_000), rng.uniform(0, om.height_m, 100_000)

        def run() -> object:
            return om.latlon_to_world(*om.world_to_latlon(x, y))

        return run

    return setup


def _border_nodata() -> Callable[[], object]:
    from aerial_loc_env.world.maps.io import border_connected

    rng = np.random.default_rng(2)
    black = rng.random((_N, _N)) < 0.02
    yy, xx = np.mgrid[:_N, :_N]
    black |= xx + yy < _N // 2

    def run() -> object:
        return border_connected(black)

    return run


BENCHMARKS = [
    Benchmark("maps: load 2048^2 JPEG GeoTIFF (decode, georef, border no-data)", _load_geotiff, repeats=5),
    Benchmark("maps: open 2048^2 bundle memory-mapped + pickle round trip", _bundle_open_and_pickle, repeats=30),
    Benchmark("maps: world->latlon->world 100k points, EPSG:3395", _world_to_latlon("EPSG:3395"), repeats=10,
              unit="point", per_call_items=100_000),
    Benchmark("maps: world->latlon->world 100k points, local tangent", _world_to_latlon("tangent"), repeats=10,
              unit="point", per_call_items=100_000),
    Benchmark("maps: border-connected no-data mask 2048^2", _border_nodata, repeats=10),
]
