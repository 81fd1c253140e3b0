"""Speed of the procedural city: uncached generation of the default map, and the cached (memory-mapped) load."""

from __future__ import annotations

from collections.abc import Callable

from aerial_loc_env.perf import Benchmark


def _generate() -> Callable[[], object]:
    from aerial_loc_env.world.city import CityConfig, generate_city

    cfg = CityConfig()
    return lambda: generate_city(cfg)


def _cached() -> Callable[[], object]:
    from aerial_loc_env.world.city import default_city

    default_city()          # make sure the bundle exists (generated once, outside the timing)
    return default_city


BENCHMARKS = [
    Benchmark("city: generate default map 4800x5600 px (uncached)", _generate, target_ratio=5000.0, unit="map",
              repeats=3),
    Benchmark("city: default_city() cached load (memory-mapped)", _cached, target_ratio=500.0, unit="map", repeats=10),
]
