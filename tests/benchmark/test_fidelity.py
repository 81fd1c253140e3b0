"""benchmark/fidelity.py: the flight fitted to a pair, Kendall's tau, the bootstrap interval of a ratio, the table,
the command end to end on synthetic pairs, and a folder of pairs as benchmark scenarios."""

from __future__ import annotations

import json

import numpy as np
import pytest
from synthetic_pairs import write_pair

from aerial_loc_env.benchmark import fidelity
from aerial_loc_env.benchmark.grid import make_grid
from aerial_loc_env.errors import ConfigError


def test_the_flight_fits_the_pair():
    """A 512 m tile at 0.5 m/px gets RealPair-v2's own geometry; a smaller one flies lower and shorter; one too
    small for the camera and the prior is refused naming the size it needs."""
    assert fidelity.fit_flight((512.0, 512.0)) == {"flight.altitude_m": 200.0, "flight.duration_s": 60.0}
    small = fidelity.fit_flight((400.0, 380.0))
    assert 100.0 < small["flight.altitude_m"] < 200.0 and small["flight.duration_s"] < 60.0
    with pytest.raises(ConfigError, match=r"a pair covering 150 x 150 m is too small .* needs at least \d+ m across"):
        fidelity.fit_flight((150.0, 150.0))


def test_kendall_tau():
    assert fidelity.kendall_tau([1, 2, 3, 4], [10, 20, 30, 40]) == 1.0
    assert fidelity.kendall_tau([1, 2, 3, 4], [4, 3, 2, 1]) == -1.0
    assert fidelity.kendall_tau([1, 2, 3, 4], [1, 3, 2, 4]) == pytest.approx(4 / 6)
    assert fidelity.kendall_tau([1, 1, 2], [1, 2, 3]) == pytest.approx(2 / np.sqrt(6))      # tau-b with a tie
    with pytest.raises(ConfigError, match="two equal sequences"):
        fidelity.kendall_tau([1], [1])


def test_bootstrap_interval_holds_the_ratio_and_is_reproducible():
    gen = np.random.default_rng(1)
    real = [list(gen.normal(2.0, 0.3, 4)) for _ in range(5)]
    sim = list(gen.normal(3.0, 0.4, 8))
    lo, hi = fidelity.bootstrap_ratio(sim, real)
    ratio = np.median(sim) / np.median(np.concatenate(real))
    assert lo < ratio < hi and (lo, hi) == fidelity.bootstrap_ratio(sim, real)
    assert 1.0 < lo and hi < 2.5


def test_tau_interval_follows_how_far_apart_the_agents_are():
    """Agents far apart (medians 1 m apart, trial noise 0.05 m) keep their order in every resample: the interval is
    the point; identical agents have no order, so tau's bootstrap spreads on both sides of 0; the same draw twice
    gives the same interval; one agent has no interval."""
    gen = np.random.default_rng(2)
    apart = [({p: {s: m + gen.normal(0, 0.05) for s in range(4)} for p in "abcde"},
              {s: m + gen.normal(0, 0.05) for s in range(8)}) for m in (1.0, 2.0, 3.0, 4.0)]
    real, sim = [a for a, _ in apart], [b for _, b in apart]
    assert fidelity.bootstrap_tau(real, sim) == (1.0, 1.0)
    assert fidelity.bootstrap_tau(real, sim[::-1]) == (-1.0, -1.0)
    alike = [({p: {s: gen.normal(2.0, 0.5) for s in range(4)} for p in "abcde"},
              {s: gen.normal(2.0, 0.5) for s in range(8)}) for _ in range(5)]
    lo, hi = fidelity.bootstrap_tau([a for a, _ in alike], [b for _, b in alike])
    assert lo < 0.0 < hi and (lo, hi) == fidelity.bootstrap_tau([a for a, _ in alike], [b for _, b in alike])
    with pytest.raises(ConfigError, match=">= 2 agents"):
        fidelity.bootstrap_tau(real[:1], sim[:1])


def test_one_agent_has_no_order():
    """fidelity with one agent: its figures, and no tau (the report says so instead of failing)."""
    rows = _rows("A", "p1", [1.0, 1.2]) + _rows("A", "sim", [2.0])
    res = fidelity.fidelity(rows, ["p1"], "sim", ["A"])
    assert res.agents[0].ratio == pytest.approx(2.0 / 1.1) and np.isnan(res.tau) and not res.meets_targets
    assert "Kendall tau-b: none with one agent" in fidelity.fidelity_table(res)


def _rows(agent: str, scenario: str, rmses, converged=True):
    return [{"agent": agent, "scenario": scenario, "rmse_m": r, "converged": converged} for r in rmses]


def test_the_comparison_from_rows():
    rows = (_rows("A", "p1", [1.0, 1.2]) + _rows("A", "p2", [1.1]) + _rows("A", "sim", [2.0, 2.2])
            + _rows("B", "p1", [3.0, 3.1]) + _rows("B", "p2", [2.9]) + _rows("B", "sim", [1.5, 1.7], False)
            + _rows("C", "p1", [5.0]) + _rows("C", "p2", [6.0]) + _rows("C", "sim", [6.0, 7.0]))
    res = fidelity.fidelity(rows, ["p1", "p2"], "sim", ["A", "B", "C"])
    assert res.real_order == ("A", "B", "C") and res.sim_order == ("B", "A", "C")
    assert res.tau == pytest.approx(1 / 3)
    a = {x.agent: x for x in res.agents}
    assert a["A"].ratio == pytest.approx(2.1 / 1.1) and a["B"].sim_converged == 0.0 and a["C"].real_trials == 2
    table = fidelity.fidelity_table(res)
    assert "| A | 1.10 m (100% of 3) | 2.10 m (100% of 2) | 1.91 (" in table and "(!) | 1 | 2 |" in table
    assert "real order: A < B < C" in table and "Kendall tau-b: +0.33 (95 % interval " in table
    assert -1.0 <= res.tau_lo <= res.tau_hi <= 1.0
    assert not res.meets_targets
    with pytest.raises(ConfigError, match="agent 'D' has 0 real and 0 simulated trials"):
        fidelity.fidelity(rows, ["p1", "p2"], "sim", ["D"])


@pytest.mark.slow
def test_the_command_on_synthetic_pairs(tmp_path, capsys):
    """Two pairs and Small-v3 at the pairs' geometry, three agents, short episodes: the table, both files, and a
    re-run that only reads what is there."""
    from aerial_loc_env.cli import main

    for name, shift in (("one.png", (0.2, 0.1)), ("two.png", (-0.3, 0.0))):
        write_pair(tmp_path / "pairs", name, size_px=1024, shift_m=shift)
    argv = ["fidelity", "--pairs-dir", str(tmp_path / "pairs"), "--sim", "AerialLoc/Small-v3", "--agents",
            "dead-reckoning,template-ncc,mcl-conventional", "--seeds", "2", "--sim-seeds", "2", "--out",
            str(tmp_path / "out"), "--workers", "1", "--set", "flight.duration_s=3", "--quiet"]
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "at 200 m, 60 s (fitted to 512 x 512 m), overrides {'flight.duration_s': 3}" in text
    assert "| sim: Small-v3: median RMSE (converged) |" in text and "Kendall tau-b:" in text
    assert "pairs/one.png: misregistration +0.3" in text
    data = json.loads((tmp_path / "out" / "fidelity.json").read_text())
    (result,) = data["results"]
    assert [a["agent"] for a in result["agents"]] == ["dead-reckoning", "template NCC", "MCL conventional"]
    assert all(a["real_trials"] == 4 and a["sim_trials"] == 2 for a in result["agents"])
    rows = (tmp_path / "out" / "trials.jsonl").read_text().splitlines()
    assert len(rows) == 3 * (2 * 2 + 2)
    assert main(argv) == 0                                   # resumed: nothing new
    assert len((tmp_path / "out" / "trials.jsonl").read_text().splitlines()) == len(rows)
    # a sensitivity run: an override for the preset only; the real trials are those already there
    assert main([*argv, "--sim-set", "flight.altitude_m=180"]) == 0
    assert "presets only {'flight.altitude_m': 180}" in capsys.readouterr().out
    again = (tmp_path / "out" / "trials.jsonl").read_text().splitlines()
    assert len(again) == len(rows) + 3 * 2                   # only the preset's trials are new
    new = [json.loads(line) for line in again[len(rows):]]
    assert all(r["scenario_spec"]["overrides"]["flight.altitude_m"] == 180 for r in new)
    assert json.loads((tmp_path / "out" / "fidelity.json").read_text())["sim_overrides"] == {"flight.altitude_m": 180}


def test_bad_sources_are_clear_errors(tmp_path):
    with pytest.raises(ConfigError, match=r"holds A/ .* A/ is missing"):
        fidelity.main(["--pairs-dir", str(tmp_path)])
    a, b = write_pair(tmp_path / "x")
    with pytest.raises(ConfigError, match=r"--pair .*: give EARLIER LATER \[GSD\]"):
        fidelity.main(["--pair", str(a)])
    with pytest.raises(ConfigError, match=r"fidelity: --sim-set 'perspective' must look like KEY=VALUE"):
        fidelity.main(["--pair", str(a), str(b), "--out", str(tmp_path / "o1"), "--sim-set", "perspective"])
    with pytest.raises(ConfigError, match=r"contrastt"):      # an unknown key: refused before any trial
        fidelity.main(["--pair", str(a), str(b), "--out", str(tmp_path / "o2"), "--sim-set", "database.contrastt=2"])
    assert not (tmp_path / "o2" / "trials.jsonl").exists()
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "experiment.json").write_text('{"experiments": ["mine"]}')
    with pytest.raises(ConfigError, match=r"holds the results of experiment 'mine', not 'fidelity'"):
        fidelity.main(["--pair", str(a), str(b), "--out", str(tmp_path / "busy")])


def test_a_folder_of_pairs_is_one_scenario_per_pair_in_an_experiment(tmp_path):
    write_pair(tmp_path / "pairs", "one.png", size_px=1024)
    write_pair(tmp_path / "pairs", "two.png", size_px=800)
    grid = make_grid("p", ["dead-reckoning"], [{"pairs": str(tmp_path / "pairs"), "label": "synthetic"},
                                               "AerialLoc/Small-v3"], seeds=1)
    entries = grid.scenarios
    assert [e.display for e in entries] == ["synthetic: pairs/one.png", "synthetic: pairs/two.png", "Small-v3"]
    assert entries[0].id == "AerialLoc/RealPair-v2" and entries[0].overrides["flight.altitude_m"] == 200.0
    assert entries[1].overrides["flight.altitude_m"] < 200.0           # a 400 m tile: its own fitted flight
    assert entries[1].overrides["map.path_b"].endswith("B/two.png")
    with pytest.raises(ConfigError, match=r"scenarios\[0\]: a pairs entry needs pairs = \"DIR\""):
        make_grid("p", ["dead-reckoning"], [{"pairs": str(tmp_path / "pairs"), "speed": 3}], seeds=1)
