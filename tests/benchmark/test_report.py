"""The report's tables (``benchmark/report.py``): the scenarios side by side, and Tables 6/9 never pooling two
settings with shadows into one cell."""

from __future__ import annotations

import math

import numpy as np

from aerial_loc_env.benchmark.report import comparison_table, interval_table, pooled_rmse, table9, trial_intervals


def _row(agent: str, spec: str, scenario: str, errors_m: list[float], *, converged: bool = True,
         shadow: float = 0.3) -> dict:
    return {"agent": agent, "scenario": scenario, "seed": 0, "errors_m": errors_m, "converged": converged,
            "diverged": False, "shadow_fraction_mean": shadow, "agent_spec": {"name": spec, "params": {}},
            "step_time_median_ms": 1.0, "compute_time_total_s": 2.0}


def test_the_comparison_puts_every_scenario_beside_the_others():
    rows = [_row("SSD", "mcl-ssd", "paper", [3.0, 4.0]), _row("SSD", "mcl-ssd", "paper", [0.0, 0.0]),
            _row("SSD", "mcl-ssd", "realistic", [6.0], converged=False),
            _row("DR", "dead-reckoning", "paper", [1.0]), _row("DR", "dead-reckoning", "realistic", [9.0])]
    lines = comparison_table(rows).splitlines()
    assert lines[2] == ("| agent | paper: RMSE / p95 [m] | converged (1/2 trials) "
                        "| realistic: RMSE / p95 [m] | converged (1 trials) |")
    # SSD pooled over its two paper trials: sqrt((9 + 16) / 4) = 2.5; ordered by the worst RMSE: SSD (6) < DR (9)
    assert lines[4].startswith("| SSD | 2.50 / ") and lines[4].endswith("| 2/2 | 6.00 / 6.00 | 0/1 |")
    assert lines[5] == "| DR | 1.00 / 1.00 | 1/1 | 9.00 / 9.00 | 1/1 |"


def test_an_agent_missing_on_a_scenario_has_dashes():
    rows = [_row("SSD", "mcl-ssd", "paper", [1.0]), _row("NCC", "template-ncc", "realistic", [2.0])]
    assert "| NCC | - | - | 2.00 / 2.00 | 1/1 |" in comparison_table(rows)


def test_table9_is_one_table_per_scenario_when_several_have_shadows():
    rows = [_row("SSD", "mcl-ssd", "paper", [1.0]), _row("SSD", "mcl-ssd", "realistic", [3.0])]
    t9 = table9(rows)
    assert "## Tables 6 and 9 (paper): ours / paper" in t9 and "## Tables 6 and 9 (realistic): ours / paper" in t9
    paper, realistic = t9.split("## Tables 6 and 9 (realistic)")
    assert "| Sim. w/ shadow RMSE [m] | 1.00 / 12.50 |" in paper
    assert "| Sim. w/ shadow RMSE [m] | 3.00 / 12.50 |" in realistic   # not the pooled sqrt(5) = 2.24


def test_table9_pools_the_paper_pair_without_and_with_shadows_into_one_table():
    rows = [_row("SSD", "mcl-ssd", "no shadows", [1.0], shadow=0.0), _row("SSD", "mcl-ssd", "shadows", [3.0])]
    t9 = table9(rows)
    assert t9.count("## Tables 6 and 9") == 1 and "## Tables 6 and 9: ours / paper" in t9
    assert "| Sim. w/o shadow RMSE [m] | 1.00 / 7.70 |" in t9 and "| Sim. w/ shadow RMSE [m] | 3.00 / 12.50 |" in t9


def _trial(scenario: str, errors_m: list[float], ttc: float | None) -> dict:
    e = np.asarray(errors_m, dtype=float)
    return {"agent": "A", "scenario": scenario, "errors_m": list(e), "rmse_m": float(np.sqrt(np.mean(e ** 2))),
            "converged": ttc is not None, "time_to_converge_s": ttc}


def test_intervals_collapse_on_identical_trials_and_hold_the_point_figures():
    """Identical trials: every resample equals the sample, so each interval is the value itself; the figures are
    the median-trial RMSE, the pooled RMSE, the recalls and convergence over all steps of the trials."""
    rows = [_trial("s", [1.0, 4.0, 12.0, 6.0], 1.5) for _ in range(4)]
    value, (lo, hi) = trial_intervals(rows, resamples=50)
    rmse = math.sqrt((1 + 16 + 144 + 36) / 4)
    assert np.allclose(value, [rmse, rmse, 0.5, 0.75, 1.5, 1.0])
    assert np.allclose(lo, value) and np.allclose(hi, value)


def test_intervals_are_deterministic_cover_the_value_and_resample_the_scenarios():
    """Two scenarios of very different errors: resampling the scenarios first (two stages) spreads the pooled
    RMSE's interval over both (a resample may hold only one of them); same seed, same interval."""
    g = np.random.default_rng(3)
    rows = [_trial("pairs: a", list(g.normal(0, 1, 20)), 0.0) for _ in range(5)] + \
        [_trial("pairs: b", list(g.normal(0, 10, 20)), None) for _ in range(5)]
    value, (lo, hi) = trial_intervals(rows, resamples=400, seed=1)
    again = trial_intervals(rows, resamples=400, seed=1)
    assert np.array_equal(lo, again[1][0]) and np.array_equal(hi, again[1][1])
    assert np.all(lo[:4] <= value[:4]) and np.all(value[:4] <= hi[:4])
    pooled_a = pooled_rmse(rows[:5])
    pooled_b = pooled_rmse(rows[5:])
    # P(a resample holds only one scenario) = 1/2: both extremes are inside the 95 % interval
    assert lo[1] < 1.2 * pooled_a and hi[1] > 0.9 * pooled_b
    assert lo[5] == 0.0 and hi[5] == 1.0 and value[5] == 0.5


def test_the_interval_table_groups_scenarios_by_label_prefix():
    rows = [_trial("real pairs: a", [1.0, 2.0], 0.0), _trial("real pairs: b", [3.0], 0.0),
            _trial("held-out worlds: x", [8.0], None)]
    lines = [x for x in interval_table(rows).splitlines() if x.startswith("| ") and "---" not in x][1:]
    assert [x.split(" | ")[0] for x in lines] == ["| real pairs", "| held-out worlds"]
    assert lines[0].split(" | ")[2] == "2" and lines[1].split(" | ")[2] == "1"
