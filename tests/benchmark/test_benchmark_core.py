"""The benchmark's pure parts: metrics, the resumable store, grid specs."""

import json

import numpy as np
import pytest

from aerial_loc_env.benchmark.grid import grid_from_dict, load_grid
from aerial_loc_env.benchmark.metrics import MetricConfig, time_to_convergence, trial_metrics
from aerial_loc_env.benchmark.store import TrialStore, trial_key
from aerial_loc_env.errors import ConfigError


def test_time_to_convergence_is_first_time_error_stays_below():
    t = np.arange(6) * 0.25
    e = np.array([30.0, 5.0, 12.0, 4.0, 3.0, 2.0])
    assert time_to_convergence(e, t, 10.0) == pytest.approx(0.75)
    assert np.isnan(time_to_convergence(np.array([1.0, 20.0]), t[:2], 10.0))
    assert time_to_convergence(np.array([1.0, 2.0]), t[:2], 10.0) == 0.0


def test_trial_metrics_values():
    e = np.array([3.0, 4.0, 0.0, 0.0])
    cfg = MetricConfig(converge_threshold_m=5, diverge_threshold_m=1)
    m = trial_metrics(e, np.arange(4.0), np.full(4, 1e-3), cfg)
    assert m["rmse_m"] == pytest.approx(np.sqrt(25 / 4))
    assert m["mean_error_m"] == pytest.approx(7 / 4)
    assert m["final_error_m"] == 0.0 and not m["diverged"] and m["converged"]
    assert m["step_time_median_ms"] == pytest.approx(1.0)


def test_store_append_is_durable_and_skips_torn_lines(tmp_path):
    store = TrialStore(tmp_path / "run")
    store.append({"key": "a", "rmse_m": 1.0, "nan": float("nan")})
    with open(store.path, "a") as fh:  # a run killed mid-write leaves a torn line
        fh.write('{"key": "b", "rmse')
    store.append({"key": "c", "rmse_m": 2.0})
    rows = store.rows()
    assert [r["key"] for r in rows] == ["a", "c"]
    assert rows[0]["nan"] is None
    assert '{"key": "b", "rmse' in store.path.read_text()  # nothing on disk is removed


def test_trial_key_depends_on_every_part():
    a, s = {"name": "x", "params": {"K": 70}}, {"id": "S", "overrides": {}}
    assert trial_key(a, s, 1) == trial_key(json.loads(json.dumps(a)), s, 1)
    assert trial_key(a, s, 1) != trial_key(a, s, 2)
    assert trial_key(a, s, 1) != trial_key({"name": "x", "params": {"K": 10}}, s, 1)


def test_grid_sweep_expands_and_rejects_unknown_keys():
    g = grid_from_dict({"agents": [{"name": "mcl", "sweep": {"num_pairs": [10, 30]}}],
                        "scenarios": ["S-v0"], "seeds": {"start": 3, "count": 2}})
    assert [a.params for a in g.agents] == [{"num_pairs": 10}, {"num_pairs": 30}]
    assert g.seeds == (3, 4) and g.trials() == 4
    with pytest.raises(ConfigError, match="unknown key"):
        grid_from_dict({"agents": [], "scenarios": [], "seeds": [1], "colour": 1})
    with pytest.raises(ConfigError, match="seeds"):
        grid_from_dict({"agents": ["a"], "scenarios": ["s"], "seeds": []})
    with pytest.raises(ConfigError, match="not found"):
        load_grid("no-such-experiment")


def test_dotted_and_nested_params_are_the_same_trial():
    from aerial_loc_env.benchmark.grid import nest_params, param_value

    dotted = grid_from_dict({"agents": [{"name": "m", "params": {"measurement_params.n_pairs": 30, "n": 1}}],
                             "scenarios": ["S"], "seeds": 1})
    nested = grid_from_dict({"agents": [{"name": "m",
                                         "params": {"n": 1, "measurement_params": {"n_pairs": 30}}}],
                             "scenarios": ["S"], "seeds": 1})
    assert dotted.agents[0].spec() == nested.agents[0].spec()
    assert nest_params({"a.b": 1, "a": {"c": 2}}) == {"a": {"b": 1, "c": 2}}
    p = {"n_particles": 700, "measurement_params": {"n_pairs": 50}}
    assert param_value(p, "n_pairs") == 50 and param_value(p, "measurement_params.n_pairs") == 50
    assert param_value(p, "n_particles") == 700 and param_value(p, "missing", "x") == "x"


def test_grid_rejects_duplicate_labels_bad_plots_and_thresholds():
    with pytest.raises(ConfigError, match="twice"):
        grid_from_dict({"agents": ["a", "a"], "scenarios": ["s"], "seeds": 1})
    with pytest.raises(ConfigError, match="unknown plot"):
        grid_from_dict({"agents": ["a"], "scenarios": ["s"], "seeds": 1, "plots": ["pie"]})
    with pytest.raises(ConfigError, match="paper section"):
        grid_from_dict({"agents": ["a"], "scenarios": ["s"], "seeds": 1, "paper": ["table99"]})
    with pytest.raises(ConfigError, match="converge_threshold_m"):
        grid_from_dict({"agents": ["a"], "scenarios": ["s"], "seeds": 1, "converge_threshold_m": 80.0,
                        "diverge_threshold_m": 50.0})


def test_every_shipped_experiment_parses():
    from aerial_loc_env.benchmark.grid import available_experiments

    names = available_experiments()
    assert {"default", "table5", "table9", "sweep_n", "sweep_k", "global"} <= set(names)
    t5 = load_grid("table5")
    assert t5.trials() == 12 * 100 and len(t5.seeds) == 100


def test_paper_tables_from_rows():
    from aerial_loc_env.benchmark.report import PAPER_TABLE5, table5, table9

    def row(name, k, errs, shadow):
        return {"agent": name, "scenario": "s", "seed": 0, "errors_m": errs, "shadow_fraction_mean": shadow,
                "agent_spec": {"name": name, "params": {}},
                "agent_config": {"params": {"measurement_params": {"n_pairs": k}}},
                "shadow_pairs_normalized": 0.25, "step_time_median_ms": 1.0, "compute_time_total_s": 2.0}

    rows = [row("mcl-shadow-aware", 70, [3.0, 4.0], 0.3), row("mcl-shadow-aware", 70, [0.0, 0.0], 0.3),
            row("mcl-conventional", 10, [1.0], 0.3), row("mcl-shadow-aware", 70, [1.0], 0.0)]
    t = table5(rows)
    # pooled over the two shadowed trials: sqrt((9 + 16) / 4) = 2.5; the shadow-free trial is left out
    assert f"2.50 / {PAPER_TABLE5['shadow-aware'][70]:.2f}" in t and "1.00 / 7.05" in t
    t9 = table9(rows)
    assert "| Sim. w/o shadow RMSE [m] | 1.00 / 4.20 |" in t9
    assert "| Sim. w/ shadow RMSE [m] | 2.50 / 5.00 |" in t9
