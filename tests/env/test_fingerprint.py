"""Generations of the simulator: generator versions and the scenario fingerprint in the benchmark's trial keys,
so that a resumed run never mixes rows made by two generations of the world."""

from __future__ import annotations

import json

from aerial_loc_env.benchmark.grid import ScenarioEntry, make_grid
from aerial_loc_env.benchmark.runner import resolve_grid, resolve_scenario, run_grid
from aerial_loc_env.env import fingerprint as fp
from aerial_loc_env.env import load_scenario
from aerial_loc_env.world import city

TINY = {"id": "AerialLoc/Small-v3", "overrides": {"flight.duration_s": 2.0}, "label": "tiny"}


def _grid(**overrides):
    scenario = {**TINY, "overrides": {**TINY["overrides"], **overrides}}
    return make_grid("gen", [{"name": "dead-reckoning", "label": "dr"}], [scenario], seeds=2)


def test_generator_versions_are_collected_from_the_modules():
    versions = fp.generator_versions()
    assert versions["world.city"] == city.GENERATOR_VERSION
    assert all(isinstance(v, int) for v in versions.values())


def test_fingerprint_follows_spec_and_generators_not_description():
    sc = load_scenario("AerialLoc/Small-v3")
    spec = sc.to_dict()
    base = fp.fingerprint(spec)
    assert fp.scenario_fingerprint(sc) == base
    assert fp.fingerprint({**spec, "description": "another text"}) == base
    assert fp.fingerprint({**spec, "flight": {**spec["flight"], "altitude_m": 99.0}}) != base
    bumped = {**fp.generator_versions(), "world.city": city.GENERATOR_VERSION + 1}
    assert fp.fingerprint(spec, bumped) != base
    resolved = resolve_scenario(ScenarioEntry("AerialLoc/Small-v3"))
    assert resolved["fingerprint"] == base and resolved["generators"] == fp.generator_versions()


def test_changed_spec_gives_new_trial_keys():
    a = resolve_grid(_grid()).keys
    b = resolve_grid(_grid(**{"shadows.strength_range": [0.0, 0.0]})).keys
    assert a.keys() == b.keys() and not set(a.values()) & set(b.values())


def test_resumed_run_never_mixes_generations(tmp_path, monkeypatch):
    """Rows of the old generation stay on disk untouched, but the resumed run re-runs every trial and returns
    (and reports) only rows of the new one."""
    out = tmp_path / "run"
    old = run_grid(_grid(), str(out), workers=1, progress=False)
    assert len(old) == 2
    old_fp = {r["scenario_config"]["fingerprint"] for r in old}
    before = (out / "trials.jsonl").read_bytes()
    bumped = {**fp.generator_versions(), "world.city": city.GENERATOR_VERSION + 1}
    monkeypatch.setattr(fp, "generator_versions", lambda: bumped)   # a new generation of the city generator
    new = run_grid(_grid(), str(out), workers=1, progress=False)
    assert len(new) == 2
    new_fp = {r["scenario_config"]["fingerprint"] for r in new}
    assert len(new_fp) == 1 and not new_fp & old_fp
    assert all(r["scenario_config"]["generators"]["world.city"] == city.GENERATOR_VERSION + 1 for r in new)
    assert {r["key"] for r in new}.isdisjoint({r["key"] for r in old})
    assert (out / "trials.jsonl").read_bytes().startswith(before)       # the old rows are kept, not rewritten
    on_disk = [json.loads(line) for line in (out / "trials.jsonl").read_text().splitlines()]
    assert len(on_disk) == 4


def test_v2_rows_never_share_keys_with_v1_rows_and_wind_is_in_the_key():
    """The v2 spec (the id, the [wind] section, the lateral odometry noise) fingerprints apart from the same setting
    as a v1 spec was resolved, and any wind field changes the key."""
    spec = load_scenario("AerialLoc/Small-v3").to_dict()
    v1 = {k: v for k, v in spec.items() if k != "wind"}
    v1["id"] = "AerialLoc/Small-v1"
    v1["odometry"] = {k: v for k, v in spec["odometry"].items() if k != "lateral_std_mps"}
    versions = {k: v for k, v in fp.generator_versions().items() if k != "world.wind"}
    assert fp.fingerprint(v1, versions) != fp.fingerprint(spec)
    assert "world.wind" in fp.generator_versions()
    windy = load_scenario("AerialLoc/Small-v3", {"wind.speed_range_mps": [2.0, 2.0]})
    assert fp.scenario_fingerprint(windy) != fp.fingerprint(spec)
