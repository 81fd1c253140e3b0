"""Scenario specs: one per registered id, found at import, overrides validated with clear errors."""

from __future__ import annotations

import shutil
import sys

import gymnasium as gym
import pytest
from conftest import LATIN1, REPO_ROOT

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env import scenarios
from aerial_loc_env.env.scenarios import (
    build_scenario,
    load_scenario,
    main,
    scenario_spec_dict,
    specs,
    split_overrides,
)
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.paths import spec_dir

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

REQUIRED = ("PaperShadows", "PaperNoShadows", "GlobalLocalization", "CloudShadows", "MavicPro", "RealMap", "Small")


def test_every_spec_file_is_registered_and_required_ids_exist():
    files = sorted(spec_dir("envs").glob("*.toml"))
    ids = [sid for sid in gym.registry if sid.startswith("AerialLoc/")]
    assert len(files) == len(specs()) == len(ids)
    for name in REQUIRED:
        assert f"AerialLoc/{name}-v1" in ids


@pytest.mark.parametrize("sid", [s for s in specs() if s != "AerialLoc/RealMap-v1"])
def test_specs_validate_and_round_trip(sid):
    sc = load_scenario(sid)
    again = build_scenario(sc.to_dict(), where="round trip")
    assert again.sections == sc.sections


def test_paper_defaults_follow_table_4():
    sc = load_scenario("AerialLoc/PaperShadows-v1")
    assert sc.flight.altitude_m == 200.0 and sc.flight.duration_s == 60.0 and sc.flight.rate_hz == 4.0
    assert sc.flight.speed_mps * sc.flight.duration_s == pytest.approx(2500.0, rel=1e-3)
    assert (sc.camera.width_px, sc.camera.height_px) == (600, 400)
    assert (sc.city.width_m, sc.city.height_m, sc.city.gsd_m) == (1200.0, 1400.0, 0.25)
    assert sc.episode.start == "tracking" and sc.episode.prior_std_m == 15.0
    mavic = load_scenario("MavicPro")
    assert mavic.camera.hfov_deg == 78.8 and mavic.flight.altitude_m == 100.0
    assert load_scenario("global_localization").episode.start == "global"


def test_three_override_forms_agree():
    a = load_scenario("Small", {"altitude_m": 80.0})
    b = load_scenario("Small", {"flight.altitude_m": 80.0})
    c = load_scenario("Small", {"flight": {"altitude_m": 80.0}})
    assert a.flight == b.flight == c.flight
    assert a.flight.altitude_m == 80.0
    assert a.flight.duration_s == load_scenario("Small").flight.duration_s  # the rest of the spec is kept


@pytest.mark.parametrize("overrides, match", [
    ({"altitude": 80.0}, "unknown key 'altitude'"),
    ({"flight": {"altitud_m": 80.0}}, "unknown key.*altitud_m.*allowed keys"),
    ({"weather.rain": 1.0}, "unknown section 'weather'"),
    ({"width_px": 64}, "ambiguous.*camera.*observation"),
    ({"altitude_m": -1.0}, "altitude_m.*out of range"),
    ({"rate_hz": float("nan")}, "rate_hz.*finite"),
    ({"start": "teleport"}, "start.*not allowed"),
    ({"observation": {"width_px": 2}}, "width_px.*out of range"),
    ({"duration_s": "long"}, "duration_s.*must be a number"),
])
def test_bad_overrides_are_clear_errors(overrides, match):
    with pytest.raises(ConfigError, match=match):
        load_scenario("AerialLoc/Small-v1", overrides)


def test_gym_make_validates_overrides():
    with pytest.raises(ConfigError, match="unknown key 'bogus'"):
        gym.make("AerialLoc/Small-v1", bogus=1)
    with pytest.raises(ConfigError, match="out of range"):
        gym.make("AerialLoc/Small-v1", speed_mps=1e6)


def test_real_map_needs_an_existing_path(tmp_path):
    with pytest.raises(ConfigError, match="map.path"):
        gym.make("AerialLoc/RealMap-v1")
    with pytest.raises(MapError, match="does not exist"):
        gym.make("AerialLoc/RealMap-v1", path=str(tmp_path / "nowhere.tif"))


def test_unknown_scenario_lists_the_registered_ones():
    with pytest.raises(ConfigError, match="AerialLoc/Small-v1"):
        load_scenario("NoSuchScenario")


def test_split_overrides_and_spec_dict():
    assert split_overrides({"flight.altitude_m": 1.0, "camera": {"hfov_deg": 50.0}}) == {
        "flight": {"altitude_m": 1.0}, "camera": {"hfov_deg": 50.0}}
    d = scenario_spec_dict("Small", altitude_m=90.0)
    assert d["id"] == "AerialLoc/Small-v1" and d["flight"]["altitude_m"] == 90.0


def test_cli_lists_ids(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    for name in REQUIRED:
        assert f"AerialLoc/{name}-v1" in out
    assert main(["--show", "Small"]) == 0
    shown = tomllib.loads(capsys.readouterr().out)          # valid TOML, the full validated spec
    assert build_scenario(shown).sections == load_scenario("Small").sections


def test_an_older_version_of_an_id_names_the_registered_one():
    """The ids went to v1 when their frames changed for the same seed: asking for v0 says which id to use (from
    the spec loader and from Gymnasium itself), never an unrelated 'unknown scenario'."""
    with pytest.raises(ConfigError, match=r"'AerialLoc/Small-v0' is not registered.*'AerialLoc/Small-v1'"):
        load_scenario("AerialLoc/Small-v0")
    with pytest.warns(DeprecationWarning, match="out of date"), \
            pytest.raises(gym.error.Error, match=r"AerialLoc/Small-v1"):
        gym.make("AerialLoc/Small-v0")


def test_section_given_a_non_table_says_so():
    with pytest.raises(ConfigError, match=r"section 'flight'.*table.*got 5") as err:
        scenarios.split_overrides({"flight": 5})
    assert "unknown key" not in str(err.value)


def test_non_utf8_scenario_spec_is_a_clear_error(tmp_path):
    p = tmp_path / "latin.toml"
    p.write_bytes(LATIN1)
    with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
        scenarios._read(p)


def test_one_broken_spec_does_not_take_the_others_down(tmp_path, monkeypatch, capsys):
    folder = tmp_path / "envs"
    folder.mkdir()
    shutil.copy(REPO_ROOT / "envs" / "small.toml", folder / "small.toml")
    (folder / "latin.toml").write_bytes(b'id = "AerialLoc/Latin-v0"\n' + LATIN1)
    (folder / "broken.toml").write_text('id = "AerialLoc/Broken-v0"\n[flight\n')
    monkeypatch.setattr(scenarios, "spec_dir", lambda kind: folder)
    scenarios._scan.cache_clear()
    try:
        ids = scenarios.register_all()
        assert "AerialLoc/Small-v1" in ids
        assert scenarios.load_scenario("AerialLoc/Small-v1").flight.altitude_m == 100.0
        with pytest.raises(ConfigError, match=r"broken\.toml.*invalid TOML"):
            scenarios.load_scenario("broken")
        with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
            scenarios.load_scenario("AerialLoc/Latin-v0")
        assert scenarios.main([]) == 0
        out = capsys.readouterr().out
        assert "AerialLoc/Small-v1" in out and "broken.toml" in out and "latin.toml" in out
    finally:
        scenarios._scan.cache_clear()
        for sid in ("AerialLoc/Latin-v0", "AerialLoc/Broken-v0"):
            gym.registry.pop(sid, None)


def test_scenarios_show_realmap_without_a_path(capsys):
    from aerial_loc_env.env.scenarios import main

    assert main(["--show", "AerialLoc/RealMap-v1"]) == 0
    out = capsys.readouterr().out
    assert 'id = "AerialLoc/RealMap-v1"' in out and "# path = (required" in out and "altitude_m = 50.0" in out
