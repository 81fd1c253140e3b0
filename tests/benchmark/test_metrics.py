"""Trial metrics (``benchmark/metrics.py``): the convergence threshold scales with the scenario (footprint,
prior) and the report states it; the fix rate shows a baseline that never fixes."""

from __future__ import annotations

import numpy as np
import pytest

import aerial_loc_env  # noqa: F401
from aerial_loc_env.benchmark.grid import make_grid
from aerial_loc_env.benchmark.metrics import MetricConfig, fix_rate, time_to_convergence
from aerial_loc_env.benchmark.report import markdown_report
from aerial_loc_env.benchmark.runner import run_grid
from aerial_loc_env.env import load_scenario


def test_threshold_is_the_papers_10_m_at_its_geometry_and_scales_elsewhere():
    auto = MetricConfig(None, None)
    paper = auto.for_scenario(load_scenario("AerialLoc/PaperShadows-v2"))
    assert paper.converge_threshold_m == pytest.approx(10.0, abs=0.01)     # 150 m footprint / 15, 15 m prior
    assert paper.diverge_threshold_m == pytest.approx(50.0, abs=0.05)
    real = auto.for_scenario(load_scenario("AerialLoc/RealMap-v2", {"map.path": "tile.tif"}))
    sc = load_scenario("AerialLoc/RealMap-v2", {"map.path": "tile.tif"})
    footprint_w = sc.camera.footprint_m(sc.flight.altitude_m)[0]
    assert real.converge_threshold_m == pytest.approx(min(footprint_w / 15.0, sc.episode.prior_std_m))
    assert real.converge_threshold_m < sc.episode.prior_std_m               # below the 5 m prior's spread
    tight = auto.for_scenario(load_scenario("AerialLoc/PaperShadows-v2", {"episode.prior_std_m": 3.0}))
    assert tight.converge_threshold_m == 3.0
    fixed = MetricConfig(10.0, 50.0).for_scenario(sc)
    assert (fixed.converge_threshold_m, fixed.diverge_threshold_m) == (10.0, 50.0)


def test_fix_rate_counts_absolute_fixes():
    assert fix_rate(["ok", "dead_reckoning", "ok", "lost"]) == 0.5
    assert fix_rate(["dead_reckoning"] * 3) == 0.0
    assert np.isnan(fix_rate([]))


@pytest.mark.slow
def test_dead_reckoning_from_a_tight_prior_no_longer_converges_everywhere(tmp_path):
    """A 5 m prior on Small-v3: with the fixed 10 m threshold dead reckoning 'converged' on most episodes
    without ever fixing; the scaled threshold (5 m) tells it apart, and the report states the threshold and
    the fix rates."""
    grid = make_grid("tight", ["dead-reckoning", "template-ncc"], [
        {"id": "AerialLoc/Small-v3", "overrides": {"episode.prior_std_m": 5.0}}], seeds=4)
    rows = run_grid(grid, str(tmp_path / "out"), workers=1, progress=False)
    dr = [r for r in rows if r["agent"] == "dead-reckoning"]
    assert len(dr) == 4 and all(r["converge_threshold_m"] == pytest.approx(5.0) for r in dr)
    old = [np.isfinite(time_to_convergence(np.asarray(r["errors_m"]), np.arange(len(r["errors_m"])), 10.0))
           for r in dr]
    new = [r["converged"] for r in dr]
    assert sum(old) >= 3 and sum(new) < sum(old), (old, new)   # the old fixed 10 m called most of them converged
    assert all(r["fix_rate"] == 0.0 for r in dr)
    assert all(r["fix_rate"] > 0.0 for r in rows if r["agent"] == "template-ncc")
    report = markdown_report("tight", "", rows, "test machine")
    assert "fix rate" in report and "conv. threshold" in report and "footprint" in report
