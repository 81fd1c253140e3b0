"""Issue 13, bad inputs: each case a clear error naming the file/field, the problem and the fix, instead of a raw
traceback, a silently wrong result or an unclear message."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import gymnasium as gym
import numpy as np
import pytest
from conftest import SHARED_DATA

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.benchmark.grid import available_experiments, check_scenarios, grid_from_dict, load_grid
from aerial_loc_env.config import build_config
from aerial_loc_env.env import scenarios
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.estimators.registry import load_spec, make_agent
from aerial_loc_env.sensors.flight import FlightConfig
from aerial_loc_env.world.maps.io import load_orthomap
from aerial_loc_env.world.maps.orthomap import Orthomap

REPO = Path(__file__).resolve().parents[1]
LATIN1 = "description = \"caf\xe9\"\n".encode("latin-1")   # a file saved in Latin-1, not UTF-8


def _grid(**kw) -> dict:
    return {"name": "t", "agents": ["dead-reckoning"], "scenarios": ["AerialLoc/Small-v1"], "seeds": 1, **kw}


# ------------------------------------------------------------------------------------ configs
def test_numpy_scalars_are_numbers():
    cfg = build_config(FlightConfig, {"altitude_m": np.float32(120), "min_steps": np.int64(4)})
    assert cfg.altitude_m == 120.0 and type(cfg.altitude_m) is float
    assert cfg.min_steps == 4 and type(cfg.min_steps) is int
    env = gym.make("AerialLoc/Small-v1", altitude_m=np.float32(110.0))
    assert env.unwrapped.scenario.flight.altitude_m == 110.0
    env.close()


def test_section_given_a_non_table_says_so():
    with pytest.raises(ConfigError, match=r"section 'flight'.*table.*got 5") as err:
        scenarios.split_overrides({"flight": 5})
    assert "unknown key" not in str(err.value)


def test_duration_too_short_for_any_track_names_duration_not_the_map():
    with pytest.raises(ConfigError, match=r"duration_s.*min_steps") as err:
        build_config(FlightConfig, {"duration_s": 1.0, "rate_hz": 4.0, "min_steps": 8}, where="spec [flight]")
    assert "map too small" not in str(err.value)


# ------------------------------------------------------------------------------------ spec files
def test_non_utf8_scenario_spec_is_a_clear_error(tmp_path):
    p = tmp_path / "latin.toml"
    p.write_bytes(LATIN1)
    with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
        scenarios._read(p)


def test_non_utf8_agent_spec_is_a_clear_error(tmp_path):
    p = tmp_path / "latin.toml"
    p.write_bytes(LATIN1)
    with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
        load_spec(p)


def test_non_utf8_experiment_is_a_clear_error(tmp_path):
    p = tmp_path / "latin.toml"
    p.write_bytes(LATIN1)
    with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
        load_grid(p)


def test_one_broken_spec_does_not_take_the_others_down(tmp_path, monkeypatch, capsys):
    folder = tmp_path / "envs"
    folder.mkdir()
    shutil.copy(REPO / "envs" / "small.toml", folder / "small.toml")
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


# ------------------------------------------------------------------------------------ experiments
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


def test_env_reset_refuses_a_boolean_seed():
    env = gym.make("AerialLoc/Small-v1")
    with pytest.raises((ConfigError, ValueError), match="seed"):
        env.reset(seed=True)
    env.close()


# ------------------------------------------------------------------------------------ maps
def test_image_over_opencvs_pixel_limit_is_a_map_error(tmp_path):
    png = tmp_path / "big.png"
    cv2.imwrite(str(png), np.full((40, 50, 3), 128, np.uint8))
    code = ("import sys\nfrom aerial_loc_env.world.maps.io import load_orthomap\nfrom aerial_loc_env.errors import "
            "MapError\ntry:\n    load_orthomap(sys.argv[1], gsd_m=1.0)\nexcept MapError as e:\n"
            "    print('MAPERROR', e)\n")
    env = {**os.environ, "OPENCV_IO_MAX_IMAGE_PIXELS": "1000", "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-c", code, str(png)], capture_output=True, text=True, env=env,
                         timeout=120)
    assert "Traceback" not in res.stderr, res.stderr[-2000:]
    assert "MAPERROR" in res.stdout and "big.png" in res.stdout and "2000" in res.stdout, res.stdout


@pytest.mark.parametrize("layers", [[1, 2], {"rgb": "x.npy"}, {"rgb": {"file": "rgb.npy"}}, "rgb"])
def test_bundle_with_malformed_layers_is_a_map_error(tmp_path, layers):
    om = Orthomap(np.zeros((20, 30, 3), np.uint8), 1.0, 1.0,
                  __import__("aerial_loc_env.world.maps.geo", fromlist=["x"]).LocalTangentGeoref.centered(
                      0.0, 0.0, 30, 20, 1.0, 1.0), name="m")
    path = om.save_bundle(tmp_path / "m.alm")
    meta = json.loads((Path(path) / "meta.json").read_text())
    meta["layers"] = layers
    (Path(path) / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(MapError, match=r"meta\.json.*layers"):
        Orthomap.load_bundle(path)


@pytest.mark.parametrize("pixel, crs", [(1e9, "EPSG:32633"), (1e-7, "EPSG:32633"), (5.0, "EPSG:4326")])
def test_world_file_pixel_size_absurd_for_its_crs(tmp_path, pixel, crs):
    png = tmp_path / "m.png"
    cv2.imwrite(str(png), np.full((40, 50, 3), 128, np.uint8))
    north = 5_000_000.0 if crs != "EPSG:4326" else 45.0
    east = 500_000.0 if crs != "EPSG:4326" else 10.0
    (tmp_path / "m.pgw").write_text(f"{pixel}\n0\n0\n{-pixel}\n{east}\n{north}\n")
    with pytest.raises(MapError, match=r"m\.pgw.*pixel size"):
        load_orthomap(png, crs=crs)


# ------------------------------------------------------------------------------------ agents
@pytest.mark.parametrize("agent", ["template-ncc", "features-orb", "mcl-ssd"])
def test_agent_fed_another_scenarios_frames_says_what_differs(agent):
    a = gym.make("AerialLoc/Small-v1")
    b = gym.make("AerialLoc/Small-v1", observation={"width_px": 48, "height_px": 32})
    _, info = a.reset(seed=0)
    obs_b, _ = b.reset(seed=0)
    est = make_agent(agent, **({"n_particles": 50} if agent.startswith("mcl") else {}))
    est.reset(a.unwrapped.briefing, seed=0)
    with pytest.raises(ConfigError, match=r"48 x 32.*64 x 64"):
        est.step(obs_b)
    a.close()
    b.close()


# ------------------------------------------------------------------------------------ CLIs
def test_bench_out_that_cannot_be_created(tmp_path, capsys):
    from aerial_loc_env.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("x")
    rc = main(["bench", "--quiet", "--no-plots", "--seeds", "1", "--out", str(blocker / "sub")])
    err = capsys.readouterr().err
    assert rc != 0 and "Traceback" not in err and "--out" in err and str(blocker / "sub") in err, err


def test_bench_refuses_unusable_map_before_running(tmp_path, capsys):
    from aerial_loc_env.cli import main

    exp = tmp_path / "exp.toml"
    exp.write_text('name = "m"\nagents = ["dead-reckoning"]\nseeds = 2\n[[scenarios]]\nid = "AerialLoc/RealMap-v1"\n'
                   'overrides = {"map.path" = "nowhere.tif"}\n')
    rc = main(["bench", str(exp), "--quiet", "--no-plots", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc != 0 and "nowhere.tif" in err and "Traceback" not in err, err
    assert not (tmp_path / "out" / "trials.jsonl").exists()


def test_relative_map_path_resolves_against_the_experiment_file(tmp_path, monkeypatch):
    (tmp_path / "maps").mkdir()
    exp = tmp_path / "exp.toml"
    exp.write_text('name = "m"\nagents = ["dead-reckoning"]\nseeds = 1\n[[scenarios]]\nid = "AerialLoc/RealMap-v1"\n'
                   'overrides = {"map.path" = "maps/tile.tif"}\n[[scenarios]]\nid = "AerialLoc/RealMap-v1"\n'
                   'label = "b"\noverrides = {map = {path = "maps/other.tif"}}\n')
    monkeypatch.chdir(REPO)
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


@pytest.mark.parametrize("name", available_experiments())
def test_every_shipped_experiment_builds_its_scenarios_from_the_repository_root(name, monkeypatch):
    """What `aerial-loc bench NAME` checks before any trial: each scenario's env builds (spec, overrides, map)."""
    monkeypatch.chdir(REPO)
    grid = load_grid(name)
    if not SHARED_DATA.is_dir() and any("map" in scenarios.split_overrides(s.overrides) for s in grid.scenarios):
        pytest.skip(f"experiment '{name}' reads a real tile from {SHARED_DATA}, which is absent (it lives beside "
                    "the project, see ../shared/data/README.md)")
    check_scenarios(grid)


rl = pytest.importorskip  # keep the SB3 cases below skippable without the rl extra


def test_train_out_that_is_a_file(tmp_path):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.train import train

    blocker = tmp_path / "out"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match=r"--out.*is a file"):
        train("ppo-local-registration", blocker, total_timesteps=1, progress_bar=False)
    assert blocker.read_text() == "x"


def test_train_resume_from_a_corrupt_zip(tmp_path):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.train import train

    bad = tmp_path / "ckpt.zip"
    bad.write_bytes(b"PK\x03\x04 this is not really a zip")
    with pytest.raises(ConfigError, match=r"--resume.*ckpt\.zip.*not a model"):
        train("ppo-local-registration", tmp_path / "out", resume=bad, progress_bar=False)


@pytest.mark.parametrize("hyper, words", [
    ({"learning_rate": "fast"}, ["learning_rate", "'fast'", "number"]),
    ({"batch_size": 0}, ["batch_size", "0", ">= 1"]),
    ({"n_steps": 1.5}, ["n_steps", "integer"]),
    ({"gamma": 2.0}, ["gamma", "[0, 1]"]),
])
def test_sb3_hyperparameter_values_are_validated(hyper, words):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.recipes import recipe_from_table

    with pytest.raises(ConfigError) as err:
        recipe_from_table({"hyperparameters": hyper}, "r.toml")
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_recipe_scenario_that_does_not_exist():
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.recipes import recipe_from_table

    with pytest.raises(ConfigError, match=r"r\.toml.*scenario.*AerialLoc/Nope-v0.*registered"):
        recipe_from_table({"scenario": "AerialLoc/Nope-v0"}, "r.toml")


@pytest.mark.parametrize("text", ["timesteps,rmse_m\n10,abc\n", "garbage\x00\x01\n", "a,b\n1,2\n"])
def test_curve_with_a_malformed_eval_csv(tmp_path, text):
    pytest.importorskip("matplotlib")
    from aerial_loc_env.learning.plots import learning_curve

    (tmp_path / "eval.csv").write_text(text)
    with pytest.raises(ConfigError, match=r"eval\.csv"):
        learning_curve(tmp_path, tmp_path / "c.png")


def test_truncated_model_zip_is_a_clear_error(tmp_path):
    pytest.importorskip("stable_baselines3")
    src = REPO / "aerial_loc_env" / "models" / "ppo-local-registration"
    if not (src / "model.zip").is_file():
        pytest.skip("the shipped model is absent")
    shutil.copy(src / "training.json", tmp_path / "training.json")
    data = (src / "model.zip").read_bytes()
    (tmp_path / "model.zip").write_bytes(data[: len(data) // 2])
    with pytest.raises(ConfigError, match=r"model\.zip.*(truncated|corrupt)"):
        make_agent("ppo-local-registration", model=str(tmp_path / "model.zip"))
    with zipfile.ZipFile(src / "model.zip") as zin, zipfile.ZipFile(tmp_path / "m2.zip", "w") as zout:
        for item in zin.infolist():
            if item.filename != "policy.pth":
                zout.writestr(item, zin.read(item.filename))
    shutil.copy(tmp_path / "m2.zip", tmp_path / "model.zip")
    with pytest.raises(ConfigError, match=r"model\.zip"):
        make_agent("ppo-local-registration", model=str(tmp_path / "model.zip"))
