"""Point estimates of a weighted particle cloud: the weighted mean (the primary paper) and the mean-shift mode
(Comaniciu & Meer, used by the second reference), which stays on one cluster when several compete instead of
landing between them.
"""

from __future__ import annotations

import math

import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.estimators.mcl import estimate_kernels as _k


def weighted_mean(xy: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Weighted mean (2,) of positions ``xy`` (N, 2) with normalized weights ``W`` (N,): ``W @ xy`` (one compiled
    pass, ``portable.matmul``'s floats)."""
    out = np.empty(2)
    _k.weighted_mean(*_cloud(xy, W), out)
    return out


def weighted_cov(xy: np.ndarray, W: np.ndarray, center: np.ndarray | None = None) -> np.ndarray:
    """Weighted 2x2 covariance about ``center`` (default: the weighted mean): ``(d * W[:, None]).T @ d``, ``d = xy
    - center`` (one compiled pass, ``portable.matmul``'s floats)."""
    xy, W = _cloud(xy, W)
    c = weighted_mean(xy, W) if center is None else np.asarray(center, dtype=np.float64).reshape(2)
    out = np.empty((2, 2))
    _k.weighted_cov(xy, W, c, out)
    return out


def _cloud(xy: np.ndarray, W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``xy`` (N, 2) and ``W`` (N,) as float64 arrays for the compiled passes (a view of the states as it is)."""
    xy, W = np.asarray(xy, dtype=np.float64), np.asarray(W, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 2 or W.shape != (xy.shape[0],):
        raise ValueError(f"estimate: positions (N, 2) and weights (N,) expected, got {xy.shape} and {W.shape}")
    return xy, W


def max_std_m(cov: np.ndarray) -> float:
    """The 1-sigma spread along the major axis of a 2x2 covariance: the square root of its largest eigenvalue,
    in closed form (``(a + c) / 2 + hypot((a - c) / 2, b)``; within a few ulp of ``eigvalsh``, without the
    fixed cost of a LAPACK call per step)."""
    a, b, c = float(cov[0, 0]), float(cov[0, 1]), float(cov[1, 1])
    return math.sqrt(max(0.5 * (a + c) + math.hypot(0.5 * (a - c), b), 0.0))


def circular_mean(angles_rad: np.ndarray, W: np.ndarray) -> float:
    return math.atan2(portable.matmul(W, np.sin(angles_rad)), portable.matmul(W, np.cos(angles_rad)))


def circular_mean_of_yaws(states: np.ndarray, W: np.ndarray) -> float:
    """``circular_mean(states[:, 2], W)`` with the yaws' cosines and sines from ``yaw_cos_sin`` (the same floats)."""
    cos, sin = yaw_cos_sin(states)
    return math.atan2(portable.matmul(W, sin), portable.matmul(W, cos))


#: the last yaw_cos_sin: (the states array, a copy of its yaw column, their cosines, their sines)
_YAW_TRIG: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None] = [None]


def yaw_cos_sin(states: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """NumPy's ``cos`` and ``sin`` of the yaw column ``states[:, 2]``, kept for the last states array asked about:
    an MCL step takes them of the same particles twice (the measurement model's affines, the point estimate's
    circular mean). Given again only for the same array whose yaws still equal the kept copy (moved particles,
    or another array, get new ones), so the floats are those of computing them again."""
    yaw = states[:, 2]
    last = _YAW_TRIG[0]
    if last is not None and last[0] is states and bool((last[1] == yaw).all()):
        return last[2], last[3]
    cos, sin = np.cos(yaw), np.sin(yaw)
    _YAW_TRIG[0] = (states, yaw.copy(), cos, sin)
    return cos, sin


def mean_shift(xy: np.ndarray, W: np.ndarray, bandwidth_m: float, *, n_seeds: int = 8, max_iter: int = 30,
               tol_m: float = 0.01, rng: np.random.Generator | None = None) -> np.ndarray:
    """The highest-density mode (2,) of the weighted cloud under a Gaussian kernel of ``bandwidth_m``.

    Seeds: the heaviest particle, the weighted mean and (with ``rng``) further particles drawn by weight; all
    seeds climb at once (a (seeds, N) kernel matrix per iteration), then the mode with the largest kernel
    density wins. O(seeds * N * iterations).
    """
    seeds = [xy[int(np.argmax(W))], weighted_mean(xy, W)]
    if rng is not None and n_seeds > 2:
        seeds.extend(xy[rng.choice(xy.shape[0], size=n_seeds - 2, p=W)])
    m = np.array(seeds, dtype=np.float64)
    inv2h2 = 0.5 / bandwidth_m ** 2
    for _ in range(max_iter):
        k = _kernel(m, xy, W, inv2h2)                           # (S, N)
        s = k.sum(axis=1, keepdims=True)
        new = np.where(s > 0, portable.matmul(k, xy) / np.maximum(s, 1e-300), m)
        shift = float(np.max(np.abs(new - m)))
        m = new
        if shift < tol_m:
            break
    density = _kernel(m, xy, W, inv2h2).sum(axis=1)
    return m[int(np.argmax(density))]


def _kernel(m: np.ndarray, xy: np.ndarray, W: np.ndarray, inv2h2: float) -> np.ndarray:
    d2 = ((m[:, None, :] - xy[None, :, :]) ** 2).sum(axis=2)
    return portable.exp(-d2 * inv2h2) * W[None, :]
