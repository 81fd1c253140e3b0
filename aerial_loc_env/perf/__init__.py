"""Speed benchmarks (never timed assertions in tests): medians on one core, as ratios to a floor, machine noted.

Each module in this package defines ``BENCHMARKS``: a list of ``Benchmark``. ``python -m aerial_loc_env.perf``
runs them all (or those whose name contains one of the arguments) and prints a table.

Absolute milliseconds do not travel between machines (nor between a quiet and a loaded one); ratios do. Every
benchmark is reported as a ratio to the *floor*: one bare bilinear warp of a 600 x 400 camera frame from the map
(``FLOOR_NAME``, ``CameraRenderer.database_patch``), the least any frame costs. The floor is timed interleaved
with each benchmark (a few floor calls after every benchmark call) and the ratio is the median over the calls of
(the call's time / the median of the floor calls right after it), so load that comes and goes during a run slows
both sides of each ratio alike and the ratio stays put. The first floor calls after a heavy benchmark are
several times slower (its freed memory faults back in, caches are cold), so each batch starts with untimed warm-up
calls: the floor is always the warm, bare warp. Times are the process's CPU time (``time.process_time``): on a
shared machine a long call is descheduled many times while a short floor call mostly runs whole, so wall-clock
ratios of long benchmarks grow with the load; CPU times do not (the wall-clock median is reported beside them).
Memory-bound work still slows when other processes share the caches: take figures from a quiet machine where
possible, and always note the load (printed at the start and end). Targets are ratios (``target_ratio``).

Work spread over several processes (vectorized envs, ``perf/vector.py``) is timed by the wall clock
(``clock="wall"``: its workers' CPU time is not this process's) and compared with a ``baseline`` benchmark (rate /
the baseline's rate, against ``baseline_target``): one baseline call is timed after each call, as the floor is, and
the figure is the median over the calls of the pair's rate ratio, so a baseline row timed in a quieter or busier
moment of the run cannot make it. Those rows need the other cores idle.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from aerial_loc_env.sysinfo import machine

__all__ = ["FLOOR_NAME", "Benchmark", "load", "machine", "measure", "single_core"]

FLOOR_NAME = "database patch 600x400 (200 m)"   # the floor benchmark (perf/render.py)
_FLOOR_WARMUP_CALLS = 2                          # untimed floor calls after each benchmark call, then
_FLOOR_CALLS_PER_CALL = 3                        # timed floor calls interleaved after each benchmark call


@dataclass(frozen=True)
class Benchmark:
    name: str                        # e.g. "render 600x400 + cast shadows + noise"
    setup: Callable[[], Callable[[], object]]  # returns the function to time (setup excluded)
    target_ratio: float | None = None  # target: median per item / the floor's median in the same run, or None
    unit: str = "call"               # what one item is ("frame", "step", ...)
    repeats: int = 30
    per_call_items: int = 1          # e.g. steps per call, to report per-item figures and rates
    clock: str = "cpu"               # "wall" where the work spreads over threads or processes (vectorized envs)
    baseline: str | None = None      # the benchmark whose rate this one's is compared with (timed interleaved)
    baseline_target: float | None = None  # the least rate / the baseline's rate (e.g. 1.5: 50 % faster)


def single_core() -> None:
    """Pin the numeric libraries to one thread so the figures are per-core.

    BLAS reads its thread count when numpy is first imported, so ``make bench`` also sets the variables in the
    environment; here threadpoolctl (when installed) limits an already-loaded BLAS as well.
    """
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:  # pragma: no cover
        pass


def load() -> str:
    """The machine's load averages (1, 5, 15 min) and core count, noted beside every run's figures."""
    try:
        one, five, fifteen = os.getloadavg()
    except OSError:  # pragma: no cover - not on this platform
        return "load unknown"
    return f"load {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} cores"


def _timed(fn: Callable[[], object]) -> tuple[float, float]:
    """(CPU seconds of this process, wall seconds) of one call."""
    c0, t0 = time.process_time(), time.perf_counter()
    fn()
    return time.process_time() - c0, time.perf_counter() - t0


def measure(bench: Benchmark, floor_fn: Callable[[], object] | None = None,
            baseline: tuple[Callable[[], object], int] | None = None) -> dict:
    """Median (and p95) seconds per item of ``bench``; with ``floor_fn``, the floor timed interleaved with it and
    the median over the calls of (call / the floor calls right after it) (``ratio``), judged against
    ``bench.target_ratio`` (``ok``); with ``baseline`` (the baseline benchmark's function and its items per call),
    one baseline call timed after each call by the same clock and the median over the calls of the baseline's time
    per item / the call's (``vs_baseline``: the rate over the baseline's)."""
    fn = bench.setup()
    fn()  # warm-up
    col = 1 if bench.clock == "wall" else 0               # wall: other processes' CPU is not this one's
    base_fn, base_items = baseline if baseline is not None else (None, 1)
    times, floors, paired = [], [], []
    for _ in range(bench.repeats):
        times.append(_timed(fn))
        if floor_fn is not None:
            for _ in range(_FLOOR_WARMUP_CALLS):
                floor_fn()
            floors.append(float(np.median([_timed(floor_fn)[0] for _ in range(_FLOOR_CALLS_PER_CALL)])))
        if base_fn is not None:
            per_item = times[-1][col] / bench.per_call_items
            paired.append(_timed(base_fn)[col] / base_items / max(per_item, 1e-12))
    arr = np.asarray(times) / bench.per_call_items       # (repeats, 2): CPU, wall
    med = float(np.median(arr[:, col]))
    floor_s = float(np.median(floors)) if floors else None
    ratio = float(np.median(arr[:, col] / np.maximum(floors, 1e-9))) if floors else None
    return {
        "name": bench.name,
        "clock": bench.clock,
        "baseline": bench.baseline,
        "baseline_target": bench.baseline_target,
        "vs_baseline": float(np.median(paired)) if paired else None,
        "median_s": med,
        "p95_s": float(np.percentile(arr[:, col], 95)),
        "wall_median_s": float(np.median(arr[:, 1])),
        "rate_per_s": 1.0 / med if med > 0 else float("inf"),
        "unit": bench.unit,
        "floor_s": floor_s,
        "ratio": ratio,
        "target_ratio": bench.target_ratio,
        "ok": None if bench.target_ratio is None or ratio is None else ratio <= bench.target_ratio,
    }
