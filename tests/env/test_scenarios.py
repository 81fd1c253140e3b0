"""Scenario specs: one per registered id, found at import, overrides validated with clear errors."""

from __future__ import annotations

import shutil
import sys

import gymnasium as gym
import pytest
from shared_helpers import LATIN1, REPO_ROOT

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
        assert f"AerialLoc/{name}-v{3 if name == 'Small' else 2}" in ids


@pytest.mark.parametrize("sid", [s for s in specs() if s not in ("AerialLoc/RealMap-v2", "AerialLoc/RealPair-v2")])
def test_specs_validate_and_round_trip(sid):
    sc = load_scenario(sid)
    again = build_scenario(sc.to_dict(), where="round trip")
    assert again.sections == sc.sections


def test_paper_defaults_follow_table_4():
    sc = load_scenario("AerialLoc/PaperShadows-v2")
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
        load_scenario("AerialLoc/Small-v3", overrides)


def test_gym_make_validates_overrides():
    with pytest.raises(ConfigError, match="unknown key 'bogus'"):
        gym.make("AerialLoc/Small-v3", bogus=1)
    with pytest.raises(ConfigError, match="out of range"):
        gym.make("AerialLoc/Small-v3", speed_mps=1e6)


def test_real_map_needs_an_existing_path(tmp_path):
    with pytest.raises(ConfigError, match="map.path"):
        gym.make("AerialLoc/RealMap-v2")
    with pytest.raises(MapError, match="does not exist"):
        gym.make("AerialLoc/RealMap-v2", path=str(tmp_path / "nowhere.tif"))


def test_unknown_scenario_lists_the_registered_ones():
    with pytest.raises(ConfigError, match="AerialLoc/Small-v3"):
        load_scenario("NoSuchScenario")


def test_split_overrides_and_spec_dict():
    assert split_overrides({"flight.altitude_m": 1.0, "camera": {"hfov_deg": 50.0}}) == {
        "flight": {"altitude_m": 1.0}, "camera": {"hfov_deg": 50.0}}
    d = scenario_spec_dict("Small", altitude_m=90.0)
    assert d["id"] == "AerialLoc/Small-v3" and d["flight"]["altitude_m"] == 90.0


def test_cli_lists_ids(capsys):
    assert main([]) == 0
    out = capsys.readouterr().out
    for name in REQUIRED:
        assert f"AerialLoc/{name}-v{3 if name == 'Small' else 2}" in out
    assert main(["--show", "Small"]) == 0
    shown = tomllib.loads(capsys.readouterr().out)          # valid TOML, the full validated spec
    assert build_scenario(shown).sections == load_scenario("Small").sections


@pytest.mark.parametrize("old, new", [("AerialLoc/Small-v0", "AerialLoc/Small-v3"),
                                      ("AerialLoc/Small-v1", "AerialLoc/Small-v3"),
                                      ("AerialLoc/PaperShadows-v1", "AerialLoc/PaperShadows-v2")])
def test_an_older_version_of_an_id_names_the_registered_one(old, new):
    """The ids went to v1 when their frames changed for the same seed, to v2 when the odometry gained the lateral
    speed (Small on to v3 since): asking for an older one says which id to use (from the spec loader and from
    Gymnasium itself), never an unrelated 'unknown scenario'."""
    with pytest.raises(ConfigError, match=rf"'{old}' is not registered.*'{new}'"):
        load_scenario(old)
    with pytest.warns(DeprecationWarning, match="out of date"), \
            pytest.raises(gym.error.Error, match=new):
        gym.make(old)


@pytest.mark.parametrize("name", ["RealisticPaper", "SeasonChange", "Downtown", "Crosswind", "Small"])
def test_the_v2_of_an_id_now_v3_names_the_v3(name):
    """The four realistic ids went to v3 when their worlds' last bits became the same on every CPU, Small when its
    level-1 frames took the bake: their v2 names the v3 (the spec loader, Gymnasium, ``registered_version``)."""
    old, new = f"AerialLoc/{name}-v2", f"AerialLoc/{name}-v3"
    with pytest.raises(ConfigError, match=rf"'{old}' is not registered.*'{new}'"):
        load_scenario(old)
    with pytest.warns(DeprecationWarning, match="out of date"), pytest.raises(gym.error.Error, match=new):
        gym.make(old)
    assert scenarios.registered_version(old) == new


def test_registered_version_names_the_current_id_of_an_old_one():
    assert scenarios.registered_version("AerialLoc/RealMap-v1") == "AerialLoc/RealMap-v2"
    assert scenarios.registered_version("AerialLoc/Small-v3") == "AerialLoc/Small-v3"
    assert scenarios.registered_version("AerialLoc/Nowhere-v1") is None
    assert scenarios.registered_version("Small") is None


def test_section_given_a_non_table_says_so():
    with pytest.raises(ConfigError, match=r"flight = 5: 'flight' is a section of fields, not one value") as err:
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
        assert "AerialLoc/Small-v3" in ids
        assert scenarios.load_scenario("AerialLoc/Small-v3").flight.altitude_m == 100.0
        with pytest.raises(ConfigError, match=r"broken\.toml.*invalid TOML"):
            scenarios.load_scenario("broken")
        with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
            scenarios.load_scenario("AerialLoc/Latin-v0")
        assert scenarios.main([]) == 0
        out = capsys.readouterr().out
        assert "AerialLoc/Small-v3" in out and "broken.toml" in out and "latin.toml" in out
    finally:
        scenarios._scan.cache_clear()
        for sid in ("AerialLoc/Latin-v0", "AerialLoc/Broken-v0"):
            gym.registry.pop(sid, None)


def test_scenarios_show_realmap_without_a_path(capsys):
    from aerial_loc_env.env.scenarios import main

    assert main(["--show", "AerialLoc/RealMap-v2"]) == 0
    out = capsys.readouterr().out
    assert 'id = "AerialLoc/RealMap-v2"' in out and "# path = (required" in out and "altitude_m = 50.0" in out


@pytest.mark.parametrize("section, value, example", [
    ("haze", 0.5, "haze={'extinction_per_km': 0.5} or **{'haze.extinction_per_km': 0.5}"),
    ("flight", 100, "flight={'altitude_m': 100}"),
    ("perspective", True, "perspective={'enabled': True}"),
    ("episode", "global", "episode={'start': 'global'}"),
    ("map", "tile.tif", "map={'path': 'tile.tif'}"),
    ("reward", None, "reward={'scale_m': ...}"),
])
def test_a_section_given_one_value_names_its_fields_with_an_example(section, value, example):
    """Every section given a single value gets the same message: it is a section, how to set one of its fields
    (one whose type fits the value, as a dict or a dotted key), and the list of its fields."""
    with pytest.raises(ConfigError) as err:
        gym.make("AerialLoc/Small-v3", **{section: value})
    text = str(err.value)
    assert text.startswith(f"AerialLoc/Small-v3 overrides: {section} = {value!r}: '{section}' is a section of fields, "
                           "not one value; set one of its fields, e.g. "), text
    assert example in text and f"Fields of [{section}]: " in text


def test_haze_given_one_value_also_names_the_databases_haze_field():
    with pytest.raises(ConfigError, match=r"did you mean the field 'database\.haze'\?.*extinction_per_km"):
        load_scenario("AerialLoc/Small-v3", {"haze": 0.5})


def test_a_spec_file_with_a_section_as_one_value_shows_the_table_form():
    with pytest.raises(ConfigError, match=r"x\.toml: haze = 0\.5: .*write it as a table: \[haze\] with a line such "
                                          r"as extinction_per_km = 0\.5"):
        build_scenario({"id": "AerialLoc/X-v1", "haze": 0.5}, where="x.toml")


def test_an_altimeter_too_noisy_for_the_altitude_is_refused_at_gym_make_naming_its_field():
    with pytest.raises(ConfigError, match=r"^AerialLoc/Small-v3: altimeter\.bias_std_m = 500 m is too large for "
                                          r"flight\.altitude_m = 100 m.*in \[0, 16\.67\] m"):
        gym.make("AerialLoc/Small-v3", **{"altimeter.bias_std_m": 500})
    assert load_scenario("AerialLoc/Small-v3", {"altimeter.bias_std_m": 500, "altitude_m": 3000.0,
                                                "camera.hfov_deg": 1.0}).altimeter.bias_std_m == 500


class _World:
    """What check_relief reads of a world: the ground's height model and its maximum."""

    def __init__(self, tallest_m: float | None) -> None:
        self.ground = type("Ground", (), {"dsm_m": None if tallest_m is None else [[tallest_m]]})()
        self.dsm_max_m = tallest_m


@pytest.mark.parametrize("overrides, tallest_m, refused", [
    ({"perspective.enabled": True, "altitude_m": 100.0}, 95.0, False),       # at 0.95 x the altitude: seen whole
    ({"perspective.enabled": True, "altitude_m": 100.0}, 95.1, True),
    ({"perspective.enabled": False, "altitude_m": 100.0}, 200.0, False),     # the affine view: no clipping
    ({"perspective.enabled": False}, None, False),                           # affine, no height model: fine
])
def test_check_relief_refuses_buildings_the_perspective_camera_would_cut(overrides, tallest_m, refused):
    sc = load_scenario("AerialLoc/Small-v3", overrides)
    if refused:
        with pytest.raises(ConfigError, match=r"tallest building of the map is 95\.1 m, but flight\.altitude_m = 100 m"
                                              r".*flight\.altitude_m >= 101 m.*city\.max_building_height_m \(allowed "
                                              r"\[6, 300\] m, now 60\) at most 95"):
            scenarios.check_relief(sc, _World(tallest_m))
    else:
        scenarios.check_relief(sc, _World(tallest_m))


@pytest.mark.parametrize("overrides, tallest_m, said", [
    ({"perspective.enabled": True}, None, r"the map 'ground' has no height model"),
    ({"perspective.enabled": True, "map.use_dsm": False}, 200.0, r"map\.use_dsm = false turns the height model off"),
])
def test_check_relief_refuses_a_perspective_camera_without_a_height_model(overrides, tallest_m, said):
    """Without a height model the perspective camera is the affine one: refused, naming the fix (it used to be a
    silent no-op)."""
    sc = load_scenario("AerialLoc/Small-v3", overrides)
    world = _World(tallest_m)
    world.ground.name = "ground"
    with pytest.raises(ConfigError, match=rf"^AerialLoc/Small-v3: perspective\.enabled = true .*{said}.*set "
                                          r"perspective\.enabled = false"):
        scenarios.check_relief(sc, world)


def test_a_perspective_camera_over_a_map_file_without_dsm_is_refused_at_gym_make(tmp_path):
    import cv2
    import numpy as np

    png = tmp_path / "tile.png"
    cv2.imwrite(str(png), np.random.default_rng(0).integers(0, 255, (800, 800, 3), dtype=np.uint8))
    with pytest.raises(ConfigError, match=r"^AerialLoc/RealMap-v2: perspective\.enabled = true .* the map 'tile' "
                                          r"has no height model"):
        gym.make("AerialLoc/RealMap-v2", path=str(png), map={"gsd_m": 0.5}, perspective={"enabled": True})


def test_a_perspective_camera_below_the_towers_is_refused_at_gym_make():
    """Small-v3's city has 60 m buildings: a perspective camera at 60 m would see them cut at 57 m."""
    with pytest.raises(ConfigError, match=r"^AerialLoc/Small-v3: the tallest building of the map is 60\.0 m, but "
                                          r"flight\.altitude_m = 60 m: .*fly higher \(flight\.altitude_m >= 64 m\)"):
        gym.make("AerialLoc/Small-v3", **{"perspective.enabled": True, "flight.altitude_m": 60.0})
