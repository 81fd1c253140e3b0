"""City-scale maps read by window: ``gym.make`` + first reset (time and the process's peak RSS, also with an MCL
agent flying an episode), the env step and the MCL step (shadow-aware, N = 700: the agent reads its own windows of
the map) on a synthetic 40000 x 40000 px COG (10 km at 0.25 m), beside the same steps on the embedded city's map.

The COG is generated here, tile band by tile band (so generating it stays within memory too), and kept in the
cache folder (``paths.cache_dir("bench")``, named by its size and generator version) for later runs; delete that
folder to reclaim its disk. ``gym.make`` + reset runs in a fresh interpreter per call, so its peak RSS is the
whole cost of opening the map (imports included), not the benchmark process's: each call prints that process's
times and peak RSS on a line above its row (the row's CPU column is the waiting benchmark process's own). The peak
is the interpreter's own high-water mark (``VmHWM``; ``getrusage``'s maximum also counts the benchmark process's
memory, which a child started by ``subprocess`` shares until it executes the interpreter).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aerial_loc_env.perf import Benchmark

#: bumped when the synthetic map's pixels change (the cached COG's name carries it)
SYNTHETIC_VERSION = 1
_GSD_M = 0.25


@dataclass(frozen=True)
class SyntheticMap:
    """A textured test map of ``size_px`` squared, generated per window (any window, any order, same pixels):
    value noise at 2 m and 16 m cells from a hash of the lattice coordinates, and a no-data wedge in the north-west
    corner. North-up in EPSG:3857 near Zurich."""

    size_px: int
    gsd_m: float = _GSD_M

    @property
    def width_px(self) -> int:
        return self.size_px

    @property
    def height_px(self) -> int:
        return self.size_px

    @property
    def name(self) -> str:
        return f"synthetic-{self.size_px}"

    @property
    def georef(self):
        from aerial_loc_env.world.maps.geo import AffineGeoref, mercator_scale_factor

        scale = float(mercator_scale_factor(47.37))     # web mercator metres per ground metre there
        return AffineGeoref.north_up("EPSG:3857", 950_000.0, 6_000_000.0, self.gsd_m * scale, self.gsd_m * scale)

    def read(self, u0_px: int, v0_px: int, width_px: int, height_px: int) -> tuple[np.ndarray, np.ndarray | None]:
        rgb = np.zeros((height_px, width_px, 3), np.float32)
        for cell_px, weight in ((8, 0.55), (64, 0.45)):
            rgb += weight * _value_noise(u0_px, v0_px, width_px, height_px, cell_px)
        out = np.clip(rgb, 0, 255).astype(np.uint8)
        vv, uu = np.mgrid[v0_px:v0_px + height_px, u0_px:u0_px + width_px]
        nodata = (uu + vv) < self.size_px // 8
        out[nodata] = 0
        return out, (nodata if nodata.any() else None)


def _hash_rgb(i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """A deterministic colour (3 channels in 20..235) per integer lattice point."""
    h = (i.astype(np.uint64) * np.uint64(0x9E3779B1) ^ j.astype(np.uint64) * np.uint64(0x85EBCA77)) & np.uint64(
        0xFFFFFFFF)
    out = []
    for salt in (0x27D4EB2F, 0x165667B1, 0xC2B2AE3D):
        x = (h ^ np.uint64(salt)) * np.uint64(0x2C1B3C6D) & np.uint64(0xFFFFFFFF)
        x ^= x >> np.uint64(15)
        x = x * np.uint64(0x297A2D39) & np.uint64(0xFFFFFFFF)
        x ^= x >> np.uint64(13)
        out.append(20.0 + (x & np.uint64(0xFF)).astype(np.float32) * (215.0 / 255.0))
    return np.stack(out, axis=-1)


def _value_noise(u0: int, v0: int, w: int, h: int, cell: int) -> np.ndarray:
    """Bilinear value noise over lattice points every ``cell`` px, at the window's pixels (seamless across windows)."""
    i0, j0 = v0 // cell - 1, u0 // cell - 1
    i1, j1 = (v0 + h) // cell + 2, (u0 + w) // cell + 2
    ii, jj = np.mgrid[i0:i1, j0:j1]
    lattice = _hash_rgb(ii, jj)
    a = np.array([[1.0 / cell, 0.0, u0 / cell - j0], [0.0, 1.0 / cell, v0 / cell - i0]])
    return cv2.warpAffine(lattice, a, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def synthetic_cog(size_px: int, folder: Path | None = None) -> Path:
    """The synthetic COG of ``size_px`` squared, generated on first use into the cache folder (or ``folder``)."""
    from aerial_loc_env.paths import cache_dir
    from aerial_loc_env.world.maps.cog import write_cog

    folder = folder or cache_dir("bench")
    path = folder / f"synthetic-{size_px}px-v{SYNTHETIC_VERSION}.cog.tif"
    if not path.is_file():
        folder.mkdir(parents=True, exist_ok=True)
        write_cog(SyntheticMap(size_px), path)
    return path


#: the agent the bigmap rows fly (the MCL step benchmark's: shadow-aware, N = 700)
AGENT = "mcl-shadow-aware"

_OPEN_SCRIPT = """
import json, resource, sys, time
t0 = time.perf_counter()
import gymnasium as gym
import numpy as np
import aerial_loc_env.env  # noqa: F401
t1 = time.perf_counter()
env = gym.make("AerialLoc/RealMap-v2", path=sys.argv[1])
t2 = time.perf_counter()
obs, info = env.reset(seed=0)
t3 = time.perf_counter()
out = {"import_s": t1 - t0, "make_s": t2 - t1, "reset_s": t3 - t2}
if len(sys.argv) > 2:  # an agent flies the episode: it reads its own windows of the map
    from aerial_loc_env.estimators.registry import make_agent
    agent = make_agent(sys.argv[2])
    agent.reset(env.unwrapped.briefing, seed=0)
    t4 = time.perf_counter()
    out["agent_reset_s"], steps, done = t4 - t3, 0, False
    while not done:
        agent.step(obs)
        obs, _, term, trunc, info = env.step(np.zeros(2, np.float32))
        done, steps = term or trunc, steps + 1
    out["episode_s"], out["steps"] = time.perf_counter() - t4, steps
out["peak_rss_bytes"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
try:  # this process's own peak (getrusage's counts the parent's memory too: the child shared it until exec)
    with open("/proc/self/status") as fh:
        out["peak_rss_bytes"] = next(int(l.split()[1]) * 1024 for l in fh if l.startswith("VmHWM:"))
except (OSError, StopIteration):
    pass
print(json.dumps(out))
"""


def open_in_fresh_process(path: Path, agent: str | None = None) -> dict:
    """``gym.make("AerialLoc/RealMap-v2", path=path)`` + ``reset`` in a fresh interpreter (and, with ``agent``, that
    agent's reset and one episode flown with it): its times and peak RSS."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", _OPEN_SCRIPT, str(path)] + ([agent] if agent else []),
                          capture_output=True, text=True, env=env, timeout=1800)
    if done.returncode != 0:
        raise RuntimeError(f"opening {path} failed:\n{done.stderr[-4000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _make_reset(size_px: int, agent: str | None = None) -> Callable[[], Callable[[], object]]:
    def setup() -> Callable[[], object]:
        path = synthetic_cog(size_px)
        gb = path.stat().st_size / 1e9

        def run() -> object:
            t0 = time.perf_counter()
            r = open_in_fresh_process(path, agent)
            flown = "" if agent is None else (f", {agent} reset {r['agent_reset_s']:.2f} s + {r['steps']} env and "
                                              f"agent steps {r['episode_s']:.2f} s")
            print(f"    {path.name} ({gb:.2f} GB on disk): gym.make {r['make_s']:.2f} s + reset {r['reset_s']:.2f} s"
                  f"{flown} (imports {r['import_s']:.2f} s, wall {time.perf_counter() - t0:.2f} s), peak RSS "
                  f"{r['peak_rss_bytes'] / 1e9:.2f} GB", flush=True)
            return r

        return run

    return setup


def _episode(path_of: Callable[[], Path]) -> Callable[[], Callable[[], object]]:
    """perf.env's episode timer on RealMap-v2 over the map ``path_of()`` gives (made when the row runs)."""
    def setup() -> Callable[[], object]:
        from aerial_loc_env.perf.env import _episode_setup

        return _episode_setup("AerialLoc/RealMap-v2", path=str(path_of()))()

    return setup


def _agent_steps(path_of: Callable[[], Path]) -> Callable[[], Callable[[], object]]:
    """The agent's steps over recorded episodes (the env's frames rendered at setup), its reset (the first window
    read) included: window reads are amortized over the episode as in flight."""
    def setup() -> Callable[[], object]:
        import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
        from aerial_loc_env.env import AerialLocEnv
        from aerial_loc_env.estimators.registry import make_agent

        env = AerialLocEnv("AerialLoc/RealMap-v2", path=str(path_of()))
        episodes = []
        for seed in range(3):
            obs, _ = env.reset(seed=seed)
            frames, done = [obs], False
            while not done:
                obs, _, term, trunc, _ = env.step(np.zeros(2, np.float32))
                done = term or trunc
                if not done:
                    frames.append(obs)
            episodes.append((env.briefing, frames))
        agent = make_agent(AGENT)
        turn = iter(range(10**9))

        def episode() -> int:
            briefing, frames = episodes[next(turn) % len(episodes)]
            agent.reset(briefing, seed=0)
            for obs in frames:
                agent.step(obs)
            return len(frames)

        return episode

    return setup


def _city_bundle() -> Path:
    from aerial_loc_env.world.city import CityConfig, default_city

    path = default_city(CityConfig()).bundle_path
    assert path is not None
    return path


def _steps() -> int:
    from aerial_loc_env.env.scenarios import load_scenario

    return load_scenario("AerialLoc/RealMap-v2", {"map": {"path": "x"}}).flight.steps


BENCHMARKS = [
    Benchmark(name="bigmap: RealMap gym.make + reset, 40000^2 px COG (fresh process, RSS printed)",
              setup=_make_reset(40000), unit="open", repeats=3),
    Benchmark(name="bigmap: RealMap gym.make + reset, 12000^2 px COG (fresh process, RSS printed)",
              setup=_make_reset(12000), unit="open", repeats=3),
    Benchmark(name="bigmap: RealMap episode on the 40000^2 px COG (per step)",
              setup=_episode(lambda: synthetic_cog(40000)), unit="step", repeats=5, per_call_items=_steps()),
    Benchmark(name="bigmap: RealMap episode on the embedded 1.2 x 1.4 km city (per step)",
              setup=_episode(_city_bundle), unit="step", repeats=5, per_call_items=_steps()),
    Benchmark(name=f"bigmap: RealMap gym.make + reset + a {AGENT} episode, 40000^2 px COG (fresh process, RSS "
                   "printed)", setup=_make_reset(40000, AGENT), unit="open", repeats=3),
    Benchmark(name="bigmap: MCL step shadow-aware N=700 on the 40000^2 px COG (windows read by the agent)",
              setup=_agent_steps(lambda: synthetic_cog(40000)), unit="step", repeats=5, per_call_items=_steps()),
    Benchmark(name="bigmap: MCL step shadow-aware N=700 on the embedded 1.2 x 1.4 km city",
              setup=_agent_steps(_city_bundle), unit="step", repeats=5, per_call_items=_steps()),
]
