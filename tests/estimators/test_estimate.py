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
