"""Experiment grids (``benchmark/grid.py``): where a list is expected, a single entry is a list of one."""

from __future__ import annotations

import pytest

from aerial_loc_env.benchmark.grid import grid_from_dict, make_grid
from aerial_loc_env.errors import ConfigError


def test_a_single_name_is_one_entry_not_its_letters() -> None:
    g = make_grid("one", "dead-reckoning", "AerialLoc/Small-v1", seeds=1)
    assert [a.name for a in g.agents] == ["dead-reckoning"] and [s.id for s in g.scenarios] == ["AerialLoc/Small-v1"]
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
