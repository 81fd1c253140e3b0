"""Resampling schemes as plain functions ``(W, M, rng) -> indices`` (the ``particles`` library's style).

``W`` are normalized weights (N,), ``M`` the number of draws; every scheme is unbiased: the expected number of
copies of particle n is ``M * W[n]``. They differ in variance: multinomial (the primary paper) is the noisiest;
residual, stratified and systematic reduce it; low-variance (Thrun et al., the second reference) is
systematic resampling written as one comb of M teeth. All are O(N + M) via cumulative sums and
``searchsorted``; the ESS helpers decide *when* to resample.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.resampling_kernels import inverse_cdf_indices, max_and_shift, sum_and_divide

Resampler = Callable[[np.ndarray, int, np.random.Generator], np.ndarray]


def inverse_cdf(su: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Indices ``n`` with ``cdf[n-1] <= su < cdf[n]`` for sorted uniforms ``su`` in [0, 1), ``cdf`` the cumulative
    sum of ``W`` with its last value set to 1 (a guard against round-off: never index N). One compiled pass with
    the indices of ``np.minimum(np.searchsorted(cdf, su, side="right"), N - 1)`` (test_resampling.py)."""
    if W.shape[0] == 0:
        raise ValueError("resampling: no weights to draw from (W is empty)")
    W = np.ascontiguousarray(W, dtype=np.float64)
    su = np.ascontiguousarray(su, dtype=np.float64)
    return inverse_cdf_indices(W, su, np.empty(su.shape[0], np.intp))


def multinomial(W: np.ndarray, M: int, rng: np.random.Generator) -> np.ndarray:
    """M independent draws from the categorical distribution W (Choi & Park, Fig. 11)."""
    return inverse_cdf(np.sort(rng.random(M)), W)


def stratified(W: np.ndarray, M: int, rng: np.random.Generator) -> np.ndarray:
    """One uniform in each of the M strata [m/M, (m+1)/M)."""
    return inverse_cdf((np.arange(M) + rng.random(M)) / M, W)


def systematic(W: np.ndarray, M: int, rng: np.random.Generator) -> np.ndarray:
    """One shared uniform offset for the M strata: the lowest-variance of the comb schemes."""
    return inverse_cdf((np.arange(M) + rng.random()) / M, W)


def low_variance(W: np.ndarray, M: int, rng: np.random.Generator) -> np.ndarray:
    """Thrun, Burgard & Fox's low-variance sampler (the second reference): r ~ U[0, 1/M), teeth r + m/M.

    Mathematically the systematic scheme; kept under its own name because the reference uses it.
    """
    r = rng.uniform(0.0, 1.0 / M)
    return inverse_cdf(r + np.arange(M) / M, W)


def residual(W: np.ndarray, M: int, rng: np.random.Generator) -> np.ndarray:
    """floor(M W) deterministic copies, the remaining draws multinomial on the residual weights."""
    N = W.shape[0]
    counts = np.floor(M * W).astype(np.int64)
    rest = M - int(counts.sum())
    idx = np.repeat(np.arange(N), counts)
    if rest > 0:
        r = M * W - counts
        r = r / r.sum()
        idx = np.concatenate([idx, multinomial(r, rest, rng)])
    return idx


SCHEMES: dict[str, Resampler] = {
    "multinomial": multinomial,
    "systematic": systematic,
    "stratified": stratified,
    "residual": residual,
    "low_variance": low_variance,
}


def get_scheme(name: str, where: str = "resampling") -> Resampler:
    if name not in SCHEMES:
        raise ConfigError(f"{where}: unknown resampling scheme {name!r}; use one of {', '.join(SCHEMES)}")
    return SCHEMES[name]


def normalize_log_weights(log_w: np.ndarray) -> tuple[np.ndarray, float]:
    """Normalized weights W and log of the mean unnormalized weight (log-sum-exp, never overflows).

    Non-finite log-weights (-inf for impossible particles, NaN never expected) count as weight 0; if every
    weight is 0 the result is uniform and the log-mean is -inf, which the core treats as a collapse. The maximum,
    the shift, the sum and the division are compiled passes around ``portable.exp`` (the same floats on every CPU;
    the sum is NumPy's pairwise sum, tests/estimators/test_resampling.py).
    """
    w, m = _exp_below_max(log_w)
    if w is None:
        n = log_w.shape[0]
        return np.full(n, 1.0 / n), -np.inf
    W = np.empty_like(w)
    s = float(sum_and_divide(w, W))
    return W, m + portable.log(s / log_w.shape[0])


def log_mean_weight(log_w: np.ndarray) -> float:
    """``normalize_log_weights(log_w)[1]`` without the normalized weights (the core needs only this of the
    step's likelihoods)."""
    w, m = _exp_below_max(log_w)
    if w is None:
        return -np.inf
    return m + portable.log(float(w.sum()) / log_w.shape[0])


def _exp_below_max(log_w: np.ndarray) -> tuple[np.ndarray | None, float]:
    """``exp(lw - max(lw))`` and that maximum, ``lw`` = ``log_w`` with its non-finite values as -inf; (None, -inf)
    when none is finite. A finite maximum of ``log_w`` itself means it holds no NaN (the maximum would be NaN) nor
    +inf: then ``lw`` is ``log_w`` (its -inf stay -inf), and the masking pass is skipped."""
    log_w = np.ascontiguousarray(log_w, dtype=np.float64)
    shifted = np.empty_like(log_w)
    m = float(max_and_shift(log_w, shifted))
    if not math.isfinite(m):
        lw = np.where(np.isfinite(log_w), log_w, -np.inf)
        m = float(max_and_shift(lw, shifted))
        if not math.isfinite(m):
            return None, -np.inf
    return portable.exp(shifted, out=shifted), m


def ess(W: np.ndarray) -> float:
    """Effective sample size 1 / sum(W^2) of normalized weights, in [1, N]."""
    return 1.0 / portable.matmul(W, W)
