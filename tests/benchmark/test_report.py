"""The report's tables (``benchmark/report.py``): the scenarios side by side, and Tables 6/9 never pooling two
settings with shadows into one cell."""

from __future__ import annotations

from aerial_loc_env.benchmark.report import comparison_table, table9


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
