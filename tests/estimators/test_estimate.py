"""The filter's estimate (``estimators/mcl/estimate.py``): the closed-form spread against LAPACK's eigenvalue."""

from __future__ import annotations

import numpy as np
import pytest

from aerial_loc_env.estimators.mcl.estimate import max_std_m


def test_closed_form_spread_matches_eigvalsh():
    """``(a + c)/2 + hypot((a - c)/2, b)`` adds two non-negative terms (no cancellation), each within 1-2 ulp;
    LAPACK's symmetric solver is backward stable (a few ulp of ||cov||, and the largest eigenvalue is
    ||cov||): so relative agreement to 8 ulp (2e-15) of the eigenvalue, half that on its square root."""
    g = np.random.default_rng(5)
    covs = [np.zeros((2, 2)), np.diag([4.0, 4.0]), np.diag([1e-9, 1e6]), np.array([[1.0, 1.0], [1.0, 1.0]])]
    for _ in range(2000):
        m = g.normal(size=(2, 2)) * 10 ** g.uniform(-3, 4)
        covs.append(m @ m.T)
    for cov in covs:
        ref = float(np.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)))
        assert max_std_m(cov) == pytest.approx(ref, rel=1e-15 * 8 / 2, abs=1e-300)


def test_yaw_cos_sin_is_numpys_and_follows_the_particles():
    """The kept cosines and sines are given again only for the same array with the same yaws: moved particles
    (in place) and another array with equal yaws get NumPy's own of their column; the circular mean from them is
    ``circular_mean``'s float."""
    from aerial_loc_env.estimators.mcl.estimate import circular_mean, circular_mean_of_yaws, yaw_cos_sin

    g = np.random.default_rng(5)
    states = np.column_stack([g.normal(size=(700, 2)), g.uniform(-np.pi, np.pi, 700)])
    W = g.dirichlet(np.ones(700))
    for _ in range(3):
        cos, sin = yaw_cos_sin(states)
        np.testing.assert_array_equal(cos, np.cos(states[:, 2]))
        np.testing.assert_array_equal(sin, np.sin(states[:, 2]))
        assert yaw_cos_sin(states)[0] is cos                       # the same particles: kept
        assert circular_mean_of_yaws(states, W) == circular_mean(states[:, 2], W)
        other = states.copy()
        assert yaw_cos_sin(other)[0] is not cos                    # another array: its own
        states[g.integers(0, 700), 2] += 0.25                      # one particle turned, in place
        np.testing.assert_array_equal(yaw_cos_sin(states)[0], np.cos(states[:, 2]))
    states[3, 2] = np.nan
    assert np.isnan(yaw_cos_sin(states)[1][3]) and yaw_cos_sin(states)[0] is not yaw_cos_sin(states.copy())[0]


def test_weighted_mean_and_cov_are_portable_matmuls_floats():
    """The compiled mean and covariance equal the expressions they replaced (``portable.matmul(W, xy)``,
    ``portable.matmul((d * W[:, None]).T, d)``) bit for bit, on the filter's strided (N, 3) states view, with
    and without a given centre; a pairwise (NumPy) sum differs from them somewhere (the test can fail)."""
    from aerial_loc_env import portable
    from aerial_loc_env.estimators.mcl.estimate import weighted_cov, weighted_mean

    g = np.random.default_rng(9)
    differs = 0
    for n in (1, 7, 700, 5000):
        states = np.column_stack([g.normal(300.0, 40.0, (n, 2)) * 10 ** g.uniform(-2, 2), g.uniform(-3, 3, n)])
        W = g.random(n) ** 3
        W /= W.sum()
        xy = states[:, :2]
        mean = portable.matmul(W, xy)
        assert np.array_equal(weighted_mean(xy, W), mean)
        for c in (mean, np.array([250.0, 310.0])):
            d = xy - c
            expected = portable.matmul((d * W[:, None]).T, d)
            assert np.array_equal(weighted_cov(xy, W, None if c is mean else c), expected)
            differs += not np.array_equal((d * W[:, None]).T @ d, expected)
    assert differs > 0
    with pytest.raises(ValueError, match=r"positions \(N, 2\)"):
        weighted_mean(states, W)
