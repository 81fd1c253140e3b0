"""Speed benchmarks (never timed assertions in tests): medians on one core, with the machine noted.

Each module in this package defines ``BENCHMARKS``: a list of ``Benchmark``. ``python -m aerial_loc_env.perf``
runs them all (or those whose name contains one of the arguments) and prints a table.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..sysinfo import machine

__all__ = ["Benchmark", "machine", "measure", "single_core"]


@dataclass(frozen=True)
class Benchmark:
    name: str                        # e.g. "render 600x400 + cast shadows + noise"
    setup: Callable[[], Callable[[], object]]  # returns the function to time (setup excluded)
    target_s: float | None = None    # target median in seconds per call, or None
    unit: str = "call"               # what one call is ("frame", "step", ...)
    repeats: int = 30
    per_call_items: int = 1          # e.g. steps per call, to report per-item figures and rates


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


def measure(bench: Benchmark) -> dict:
    fn = bench.setup()
    fn()  # warm-up
    times = []
    for _ in range(bench.repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    arr = np.asarray(times)
    med = float(np.median(arr)) / bench.per_call_items
    return {
        "name": bench.name,
        "median_s": med,
        "p95_s": float(np.percentile(arr, 95)) / bench.per_call_items,
        "rate_per_s": 1.0 / med if med > 0 else float("inf"),
        "unit": bench.unit,
        "target_s": bench.target_s,
        "ok": None if bench.target_s is None else med <= bench.target_s,
    }
