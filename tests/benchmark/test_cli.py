"""``aerial-loc bench`` (``benchmark/cli.py``): its default experiment shows the realistic gap beside the paper's
setting, and the likelihood plot compares one ground with and without shadows."""

from __future__ import annotations

from aerial_loc_env.benchmark.cli import _with_and_without_shadows
from aerial_loc_env.benchmark.grid import load_grid, make_grid
from aerial_loc_env.benchmark.report import paper_sections


def test_the_default_runs_the_paper_setting_beside_the_realistic_gap():
    grid = load_grid("default")
    assert [s.id for s in grid.scenarios] == ["AerialLoc/PaperShadows-v2", "AerialLoc/RealisticPaper-v3"]
    assert grid.paper[0] == "comparison"
    row = {"agent": "SSD", "seed": 0, "errors_m": [1.0], "converged": True, "diverged": False,
           "agent_spec": {"name": "mcl-ssd", "params": {}}, "shadow_fraction_mean": 0.3}
    rows = [{**row, "scenario": s.display} for s in grid.scenarios]
    side_by_side = paper_sections(grid.paper, rows)[0]
    assert all(f"| {s.display}: RMSE / p95 [m] |" in side_by_side for s in grid.scenarios)


def test_the_likelihood_pair_is_one_ground_with_and_without_shadows():
    default = load_grid("default")   # two grounds, both with shadows: the first beside its shadow-free twin
    first, twin = _with_and_without_shadows(default)
    assert first == default.scenarios[0] and twin.id == first.id
    assert twin.overrides["shadows.strength_range"] == [0.0, 0.0]
    for name in ("table9", "table9_realistic", "shadow_mismatch"):   # two conditions of one ground: as listed
        grid = load_grid(name)
        assert _with_and_without_shadows(grid) == list(grid.scenarios[:2]), name
    one = make_grid("one", ["mcl-ssd"], ["AerialLoc/Small-v3"], seeds=1)
    assert [s.id for s in _with_and_without_shadows(one)] == ["AerialLoc/Small-v3"] * 2
