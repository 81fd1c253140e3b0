"""Executors: where the episodes of a grid run. Local processes by default; Ray as an optional extra."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence

from ..errors import ConfigError, require_extra
from .runner import EpisodeTask, run_episode


def _worker_init() -> None:
    # One numeric thread per worker process: the workers are the parallelism.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import cv2

    cv2.setNumThreads(1)


def local_executor(tasks: Sequence[EpisodeTask], on_result: Callable[[list[dict]], None], workers: int) -> None:
    """Run in this process (workers <= 1) or a pool of processes; results arrive as episodes finish."""
    if workers <= 1:
        _worker_init()
        for task in tasks:
            on_result(run_episode(task))
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init) as pool:
        futures = [pool.submit(run_episode, t) for t in tasks]
        try:
            for fut in as_completed(futures):
                on_result(fut.result())
        except BaseException:
            for fut in futures:
                fut.cancel()
            raise


def ray_executor(tasks: Sequence[EpisodeTask], on_result: Callable[[list[dict]], None], workers: int) -> None:
    """Run the same episodes as Ray tasks (a local instance unless RAY_ADDRESS points at a cluster)."""
    ray = require_extra("ray", "ray", "The Ray executor")
    started = False
    if not ray.is_initialized():
        ray.init(address=os.environ.get("RAY_ADDRESS"), num_cpus=None if os.environ.get("RAY_ADDRESS") else workers,
                 include_dashboard=False, log_to_driver=False)
        started = True
    try:
        remote = ray.remote(num_cpus=1)(run_episode)
        pending = [remote.remote(t) for t in tasks]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            on_result(ray.get(ready[0]))
    finally:
        if started:
            ray.shutdown()


EXECUTORS = {"local": local_executor, "ray": ray_executor}


def get_executor(name: str):
    try:
        return EXECUTORS[name]
    except KeyError:
        raise ConfigError(f"unknown executor {name!r}; use one of {', '.join(EXECUTORS)}") from None
