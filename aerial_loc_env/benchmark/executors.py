"""Executors: where the episodes of a grid run. Local processes by default; Ray as an optional extra.

An executor takes the episode tasks, a callback that receives each episode's ``(rows, failures)`` as soon as
it finishes (the runner writes them to disk at once), and a worker count. Results may arrive in any order:
the store and the reports do not depend on it.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager

from aerial_loc_env.benchmark.episodes import EpisodeTask, run_episode
from aerial_loc_env.errors import ConfigError, require_extra

OnResult = Callable[[tuple[list[dict], list[dict]]], None]


THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _worker_init(parent_pid: int | None = None) -> None:
    # One numeric thread per worker process: the workers are the parallelism.
    for var in THREAD_VARS:
        os.environ.setdefault(var, "1")
    import cv2

    cv2.setNumThreads(1)
    if parent_pid is not None:
        exit_with_parent(parent_pid)


PR_SET_PDEATHSIG = 1   # linux/prctl.h


def exit_with_parent(parent_pid: int, poll_s: float = 1.0) -> None:
    """End this worker when the run that started it dies, even by SIGKILL (it would otherwise wait on its
    task queue for ever). Linux: the kernel sends SIGTERM at the parent's death (prctl PR_SET_PDEATHSIG);
    everywhere: a daemon thread checks every ``poll_s`` that the parent is still ours."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover (no prctl: the thread below still watches)
            pass
    if os.getppid() != parent_pid:   # the parent died before the signal was armed
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Spawned workers inherit these at start, before NumPy's BLAS reads them (an initializer is too late:
    unpickling the task imports NumPy first); this process's own setting is restored afterwards."""
    saved = {var: os.environ.get(var) for var in THREAD_VARS}
    for var in THREAD_VARS:
        os.environ.setdefault(var, "1")
    try:
        yield
    finally:
        for var, value in saved.items():
            if value is None:
                os.environ.pop(var, None)
            else:
                os.environ[var] = value


def local_executor(tasks: Sequence[EpisodeTask], on_result: OnResult, workers: int) -> None:
    """Run in this process (workers <= 1) or a pool of spawned processes (nothing extra to install)."""
    workers = min(workers, len(tasks))
    if workers <= 1:
        _worker_init()
        for task in tasks:
            on_result(run_episode(task))
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    ctx = mp.get_context("spawn")
    with _single_threaded_children():
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                                   initargs=(os.getpid(),))
        try:
            futures = [pool.submit(run_episode, t) for t in tasks]
            for fut in as_completed(futures):
                on_result(fut.result())
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


def ray_executor(tasks: Sequence[EpisodeTask], on_result: OnResult, workers: int) -> None:
    """Run the same episodes as Ray tasks: on the cluster at ``RAY_ADDRESS`` (whose nodes must have this
    package installed), else on a local instance with ``workers`` CPUs. An instance already initialized by
    the caller is used as is."""
    ray = require_extra("ray", "ray", "The Ray executor (--executor ray)")
    started = False
    if not ray.is_initialized():
        address = os.environ.get("RAY_ADDRESS")
        ray.init(address=address, num_cpus=None if address else max(workers, 1), include_dashboard=False,
                 log_to_driver=False, configure_logging=False)
        started = True
    try:
        remote = ray.remote(num_cpus=1)(_ray_episode)
        pending = [remote.remote(t) for t in tasks]
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            on_result(ray.get(ready[0]))
    finally:
        if started:
            ray.shutdown()


def _ray_episode(task: EpisodeTask) -> tuple[list[dict], list[dict]]:
    _worker_init()
    return run_episode(task)


EXECUTORS: dict[str, Callable[[Sequence[EpisodeTask], OnResult, int], None]] = {
    "local": local_executor, "ray": ray_executor}


def get_executor(name: str) -> Callable[[Sequence[EpisodeTask], OnResult, int], None]:
    try:
        return EXECUTORS[name]
    except KeyError:
        raise ConfigError(f"unknown executor {name!r}; use one of {', '.join(EXECUTORS)}") from None
