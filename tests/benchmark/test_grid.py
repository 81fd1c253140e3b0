"""Experiment grids (``benchmark/grid.py``): where a list is expected, a single entry is a list of one."""

from __future__ import annotations

import pytest
from shared_helpers import LATIN1, REPO_ROOT, SHARED_DATA

from aerial_loc_env.benchmark.grid import (
    EXPERIMENT_DIR,
    available_experiments,
    check_scenarios,
    grid_from_dict,
    load_grid,
    make_grid,
)
from aerial_loc_env.config import read_toml
from aerial_loc_env.env import scenarios
from aerial_loc_env.errors import ConfigError


def test_a_single_name_is_one_entry_not_its_letters() -> None:
    g = make_grid("one", "dead-reckoning", "AerialLoc/Small-v3", seeds=1)
    assert [a.name for a in g.agents] == ["dead-reckoning"] and [s.id for s in g.scenarios] == ["AerialLoc/Small-v3"]
    g = grid_from_dict({"agents": {"name": "mcl-ssd", "params": {"n_particles": 50}}, "scenarios": {"id": "S"},
                        "seeds": 1, "plots": "track", "paper": "table5"})
    assert [a.name for a in g.agents] == ["mcl-ssd"] and g.agents[0].params == {"n_particles": 50}
    assert [s.id for s in g.scenarios] == ["S"] and g.plots == ("track",) and g.paper == ("table5",)
    assert make_grid("gen", (a for a in ["a", "b"]), ["S"], seeds=1).trials() == 2


@pytest.mark.parametrize("key, value", [("agents", 5), ("scenarios", 1.5), ("plots", {"track": 1}),
                                        ("paper", 3)])
def test_a_value_that_is_no_list_is_refused_naming_the_key(key: str, value: object) -> None:
    data = {"agents": ["a"], "scenarios": ["s"], "seeds": 1, key: value}
    with pytest.raises(ConfigError, match=rf"{key} = .* must be a list"):
        grid_from_dict(data)


def _grid(**kw) -> dict:
    return {"name": "t", "agents": ["dead-reckoning"], "scenarios": ["AerialLoc/Small-v3"], "seeds": 1, **kw}


def test_non_utf8_experiment_is_a_clear_error(tmp_path):
    p = tmp_path / "latin.toml"
    p.write_bytes(LATIN1)
    with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
        load_grid(p)


@pytest.mark.parametrize("kw, words", [
    ({"seeds": {"start": "a", "count": 2}}, ["seeds.start", "'a'", "integer"]),
    ({"seeds": {"start": 0, "count": "x"}}, ["seeds.count", "'x'", "integer"]),
    ({"converge_threshold_m": "x"}, ["converge_threshold_m", "'x'", "number"]),
    ({"diverge_threshold_m": [1]}, ["diverge_threshold_m", "number"]),
    ({"seeds": [True, False]}, ["seeds", "integers"]),
    ({"seeds": {"start": True, "count": 2}}, ["seeds.start", "integer"]),
    ({"seeds": True}, ["seeds"]),
])
def test_experiment_values_that_are_not_numbers(kw, words):
    with pytest.raises(ConfigError) as err:
        grid_from_dict(_grid(**kw), where="exp.toml")
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_relative_map_path_resolves_against_the_experiment_file(tmp_path, monkeypatch):
    (tmp_path / "maps").mkdir()
    exp = tmp_path / "exp.toml"
    exp.write_text('name = "m"\nagents = ["dead-reckoning"]\nseeds = 1\n[[scenarios]]\nid = "AerialLoc/RealMap-v2"\n'
                   'overrides = {"map.path" = "maps/tile.tif"}\n[[scenarios]]\nid = "AerialLoc/RealMap-v2"\n'
                   'label = "b"\noverrides = {map = {path = "maps/other.tif"}}\n')
    monkeypatch.chdir(REPO_ROOT)
    grid = load_grid(exp)
    paths = [scenarios.split_overrides(s.overrides)["map"]["path"] for s in grid.scenarios]
    assert paths == [str(tmp_path / "maps" / "tile.tif"), str(tmp_path / "maps" / "other.tif")]


def test_shipped_experiments_read_relative_map_paths_from_the_working_directory(tmp_path, monkeypatch):
    """The experiments inside the package (installed anywhere) name ../shared/data beside the project: from the
    working directory, not from the package's experiments folder (where `bench generalization` looked for
    aerial_loc_env/benchmark/shared/data and stopped)."""
    monkeypatch.chdir(tmp_path)
    grid = load_grid("generalization")
    paths = [scenarios.split_overrides(s.overrides).get("map", {}).get("path") for s in grid.scenarios]
    assert [p for p in paths if p] == [str(tmp_path / "../shared/data/manila_pasig_river.tif")]


@pytest.mark.slow
@pytest.mark.parametrize("name", available_experiments())
def test_every_shipped_experiment_builds_its_scenarios_from_the_repository_root(name, monkeypatch):
    """What `aerial-loc bench NAME` checks before any trial: each scenario's env builds (spec, overrides, map)."""
    monkeypatch.chdir(REPO_ROOT)
    if not SHARED_DATA.is_dir() and any("pairs" in s for s in read_toml(EXPERIMENT_DIR / f"{name}.toml",
                                                                      "experiment").get("scenarios", [])):
        pytest.skip(f"experiment '{name}' flies the real pairs of {SHARED_DATA}, which are absent (they live beside "
                    "the project, see ../shared/data/README.md)")
    grid = load_grid(name)
    if not SHARED_DATA.is_dir() and any("map" in scenarios.split_overrides(s.overrides) for s in grid.scenarios):
        pytest.skip(f"experiment '{name}' reads a real tile from {SHARED_DATA}, which is absent (it lives beside "
                    "the project, see ../shared/data/README.md)")
    check_scenarios(grid)
