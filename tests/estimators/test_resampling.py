"""Resampling schemes: unbiasedness (statistical, fixed seed), their variance ordering properties, ESS and the
log-sum-exp normalization."""

from __future__ import annotations

import numpy as np
import pytest

from aerial_loc_env import portable
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl import resampling

SCHEMES = sorted(resampling.SCHEMES)


def _weights(n: int = 12, seed: int = 3) -> np.ndarray:
    W = np.random.default_rng(seed).dirichlet(np.full(n, 0.7))
    return W


@pytest.mark.parametrize("name", SCHEMES)
def test_scheme_is_unbiased(name: str) -> None:
    """E[copies of n] = M W_n. Over R independent resamplings the mean count has standard error at most
    sqrt(M W (1 - W) / R) (the multinomial variance bounds all five schemes), so 5 standard errors (plus a
    1e-9 floor for the zero-variance cases) is a test that fails with probability < 1e-5 per particle."""
    W = _weights()
    M, R = W.size, 4000
    rng = np.random.default_rng(0)
    fn = resampling.get_scheme(name)
    counts = np.zeros(W.size)
    for _ in range(R):
        idx = fn(W, M, rng)
        assert idx.shape == (M,) and idx.min() >= 0 and idx.max() < W.size
        counts += np.bincount(idx, minlength=W.size)
    mean = counts / R
    se = np.sqrt(M * W * (1 - W) / R)
    assert np.all(np.abs(mean - M * W) <= 5 * se + 1e-9), (name, mean, M * W)


@pytest.mark.parametrize("name", ["systematic", "low_variance"])
def test_comb_schemes_keep_counts_within_one_of_expectation(name: str) -> None:
    """A comb of M evenly spaced teeth hits an interval of length W_n floor(M W_n) or ceil(M W_n) times."""
    W = _weights(50, seed=5)
    rng = np.random.default_rng(1)
    for _ in range(200):
        c = np.bincount(resampling.get_scheme(name)(W, W.size, rng), minlength=W.size)
        assert np.all(c >= np.floor(W.size * W) - 1e-9) and np.all(c <= np.ceil(W.size * W) + 1e-9)


def test_residual_keeps_the_deterministic_copies() -> None:
    W = _weights(30, seed=7)
    rng = np.random.default_rng(2)
    for _ in range(100):
        c = np.bincount(resampling.residual(W, W.size, rng), minlength=W.size)
        assert np.all(c >= np.floor(W.size * W))
        assert c.sum() == W.size


def test_multinomial_is_noisier_than_systematic() -> None:
    """The point of the low-variance schemes: the spread of the copy counts is smaller."""
    W = _weights(40, seed=9)
    rng = np.random.default_rng(3)
    var = {}
    for name in ("multinomial", "systematic"):
        c = np.array([np.bincount(resampling.get_scheme(name)(W, W.size, rng), minlength=W.size)
                      for _ in range(500)])
        var[name] = float(c.var(axis=0).sum())
    assert var["systematic"] < 0.5 * var["multinomial"]


def test_degenerate_weights_copy_the_one_particle() -> None:
    W = np.zeros(20)
    W[7] = 1.0
    for name in SCHEMES:
        assert np.all(resampling.get_scheme(name)(W, 20, np.random.default_rng(0)) == 7)


def test_ess_and_normalization() -> None:
    assert resampling.ess(np.full(100, 0.01)) == pytest.approx(100)
    W, log_mean = resampling.normalize_log_weights(np.array([1000.0, 1000.0, -np.inf, 1000.0 - np.log(2)]))
    np.testing.assert_allclose(W, [0.4, 0.4, 0.0, 0.2])
    assert log_mean == pytest.approx(1000.0 + np.log(2.5 / 4))
    assert resampling.ess(W) == pytest.approx(1 / (0.16 + 0.16 + 0.04))
    W, log_mean = resampling.normalize_log_weights(np.full(5, -np.inf))
    np.testing.assert_allclose(W, 0.2)
    assert log_mean == -np.inf


def test_unknown_scheme_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="multinomial"):
        resampling.get_scheme("bogus")


def _normalize_reference(log_w: np.ndarray) -> tuple[np.ndarray, float]:
    """``normalize_log_weights`` as it was: the non-finite values masked to -inf first, always (with its
    ``portable`` exp and log)."""
    lw = np.where(np.isfinite(log_w), log_w, -np.inf)
    m = float(np.max(lw))
    if not np.isfinite(m):
        return np.full(lw.shape[0], 1.0 / lw.shape[0]), -np.inf
    w = portable.exp(lw - m)
    s = float(w.sum())
    return w / s, m + portable.log(s / lw.shape[0])


def test_normalization_skips_the_mask_only_where_it_changes_nothing():
    """Weights and log-mean (also ``log_mean_weight`` alone) equal the always-masking form bit for bit: finite
    log-weights of many scales, with -inf, +inf and NaN among them, and none finite."""
    from aerial_loc_env.estimators.mcl.resampling import log_mean_weight, normalize_log_weights

    g = np.random.default_rng(4)
    for t in range(300):
        n = int(g.integers(1, 900))
        lw = g.normal(g.uniform(-1e3, 1e3), 10 ** g.uniform(-3, 3), n)
        for bad, p in ((-np.inf, 0.2), (np.inf, 0.01), (np.nan, 0.01)):
            if t % 4 == 1 or (t % 4 == 2 and bad != -np.inf):
                lw[g.random(n) < p] = bad
        if t % 50 == 3:
            lw[:] = [-np.inf, np.nan][t % 2]
        W, lm = normalize_log_weights(lw)
        ref_W, ref_lm = _normalize_reference(lw)
        np.testing.assert_array_equal(W, ref_W)
        assert lm == ref_lm or (np.isnan(lm) and np.isnan(ref_lm))
        assert log_mean_weight(lw) == lm or (np.isnan(lm) and np.isnan(log_mean_weight(lw)))


def test_inverse_cdf_gives_numpys_searchsorted_indices() -> None:
    """The compiled lookup against the NumPy expressions it replaced (cumsum, last value 1, searchsorted right,
    clipped to N - 1), on keys that hit the cdf's own values, ties (zero weights), keys past 1, unsorted keys, NaN
    and infinite keys (NumPy sorts a NaN after every number)."""
    g = np.random.default_rng(7)
    for n in (1, 2, 5, 700):
        W = g.dirichlet(np.full(n, 0.5))
        W[g.random(n) < 0.2] = 0.0                     # runs of equal cdf values
        W = W / W.sum() if W.sum() > 0 else np.full(n, 1.0 / n)
        cdf = np.cumsum(W)
        cdf[-1] = 1.0
        keys = np.concatenate([g.random(300), cdf, [0.0, 1.0, 1.5, -0.5]])
        for su in (np.sort(keys), keys):
            expected = np.minimum(np.searchsorted(cdf, su, side="right"), n - 1)
            np.testing.assert_array_equal(resampling.inverse_cdf(su, W), expected)
    W = np.array([0.2, 0.0, 0.3, 0.5])
    cdf = np.cumsum(W)
    cdf[-1] = 1.0
    su = np.array([0.0, 0.1, np.nan, 0.2, 0.4, np.nan, 0.99, 1.0, 0.2, np.inf, -np.inf])
    np.testing.assert_array_equal(resampling.inverse_cdf(su, W),
                                  np.minimum(np.searchsorted(cdf, su, side="right"), 3))
    with pytest.raises(ValueError, match="empty"):
        resampling.inverse_cdf(np.zeros(3), np.zeros(0))


def test_normalization_gives_the_numpy_expressions_floats():
    """The compiled maximum, shift, pairwise sum and division around NumPy's exp against the NumPy expressions
    (``_normalize_reference``), bit for bit: sizes across the pairwise sum's blocks and halvings (1 to 5000),
    spreads from flat to one dominant weight, and -inf / +inf / NaN log-weights; the float64 pairwise sum against
    NumPy's ``sum``."""
    from aerial_loc_env.estimators.shadow_detection_kernels import _pairwise_sum

    g = np.random.default_rng(11)
    for t in range(400):
        n = int(g.integers(1, 300)) if t % 2 else int(g.integers(300, 5000))
        log_w = g.normal(0.0, 10 ** g.uniform(-3, 3), n) + g.uniform(-1e3, 1e3)
        if t % 7 == 0:
            log_w[g.random(n) < 0.3] = -np.inf
        if t % 11 == 0:
            log_w[g.integers(0, n)] = np.inf
        if t % 13 == 0:
            log_w[g.integers(0, n)] = np.nan
        W, lm = resampling.normalize_log_weights(log_w)
        W_ref, lm_ref = _normalize_reference(log_w)
        np.testing.assert_array_equal(W, W_ref)
        assert lm == lm_ref or (np.isnan(lm) and np.isnan(lm_ref))
        assert resampling.log_mean_weight(log_w) == lm or np.isnan(lm)
        a = g.random(n) * 10 ** g.uniform(-5, 5)
        assert _pairwise_sum(a, 0, n) == a.sum()
    W, lm = resampling.normalize_log_weights(np.full(5, -np.inf))
    np.testing.assert_array_equal(W, np.full(5, 0.2))
    assert lm == -np.inf
