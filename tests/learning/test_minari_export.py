"""learning/minari_export.py: recorded episodes round-trip through Minari (load, replay with the recorded seeds
and actions, the same observations, rewards and ground truth), ids are versioned like env ids, and an existing
dataset is never overwritten."""

from __future__ import annotations

import json

import minari
import numpy as np
import pytest

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.learning.minari_export import INFO_KEYS, check_dataset_id, default_dataset_id, export_episodes, main

SHORT = {"flight.duration_s": 3.0}     # Small-v3: 12 steps of 64 x 64 frames


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("minari")
    res = export_episodes("AerialLoc/Small-v3", "dead-reckoning", 2, root=root, seed=5, overrides=SHORT)
    return root, res


def _load(root, dataset_id, monkeypatch):
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return minari.load_dataset(dataset_id)


def test_ids_are_versioned_like_env_ids():
    assert default_dataset_id("AerialLoc/Small-v3", "mcl-ncc") == "aerial-loc/small-mcl-ncc-v3"
    assert default_dataset_id("AerialLoc/RealisticPaper-v3", "agents/features-sift.toml") == \
        "aerial-loc/realistic-paper-features-sift-v3"
    assert check_dataset_id("aerial-loc/mine-v3") == "aerial-loc/mine-v3"
    with pytest.raises(ConfigError, match="not a versioned dataset id.*-v<version>"):
        check_dataset_id("aerial-loc/mine")
    with pytest.raises(ConfigError, match="not a scenario id like 'AerialLoc/Small-v3'"):
        default_dataset_id("Small", "mcl-ncc")


def test_export_round_trips_load_replay_same_observations(exported, monkeypatch):
    import gymnasium as gym

    root, res = exported
    assert res.dataset_id == "aerial-loc/small-dead-reckoning-v3" and res.episodes == 2 and res.steps == 24
    dataset = _load(root, res.dataset_id, monkeypatch)
    assert dataset.total_episodes == 2 and dataset.total_steps == 24
    meta = json.loads(dataset.storage.metadata["aerial_loc"])
    assert meta["seeds"] == [5, 6] and meta["agent"] == "dead-reckoning" and meta["overrides"] == SHORT
    seeds = [m["seed"] for m in dataset.storage.get_episode_metadata([0, 1])]
    assert seeds == [5, 6]
    env = dataset.recover_environment()       # gym.make of the recorded scenario (overrides and info wrapper)
    for episode, seed in zip(dataset.iterate_episodes(), seeds, strict=True):
        assert set(episode.infos) == set(INFO_KEYS)
        obs, info = env.reset(seed=seed)
        images, rewards, poses = [obs["image"]], [], [info["true_pose"]]
        for action in episode.actions:
            obs, reward, _term, trunc, info = env.step(action)
            images.append(obs["image"])
            rewards.append(reward)
            poses.append(info["true_pose"])
        assert trunc and episode.truncations[-1]
        assert np.array_equal(episode.observations["image"], np.stack(images))   # lossless, bit for bit
        assert np.allclose(episode.rewards, rewards, rtol=0, atol=1e-12)
        assert np.array_equal(episode.infos["true_pose"], np.stack(poses))
        assert np.isnan(episode.infos["position_error_m"][0]) and np.all(episode.infos["position_error_m"][1:] > 0)
    env.close()
    # the scenario the user asked for, not a registry default
    assert gym.spec("AerialLoc/Small-v3").kwargs.get("flight.duration_s") is None
    assert dataset.env_spec.kwargs["flight.duration_s"] == 3.0


def test_existing_dataset_is_refused_before_any_episode_and_kept(exported, monkeypatch):
    root, res = exported
    before = sorted((p.relative_to(root), p.stat().st_mtime_ns) for p in root.rglob("*"))
    with pytest.raises(ConfigError, match="'aerial-loc/small-dead-reckoning-v3' already exists at .*never overwritten"):
        export_episodes("AerialLoc/Small-v3", "dead-reckoning", 1, root=root, overrides=SHORT)
    assert sorted((p.relative_to(root), p.stat().st_mtime_ns) for p in root.rglob("*")) == before
    assert _load(root, res.dataset_id, monkeypatch).total_episodes == 2


def test_cli_export_and_its_errors(tmp_path, capsys):
    from aerial_loc_env.cli import main as cli

    assert main(["export", "--env", "AerialLoc/Small-v3", "--agent", "dead-reckoning", "--episodes", "1",
                 "--out", str(tmp_path), "--id", "aerial-loc/tiny-v2", "--set", "flight.duration_s=2"]) == 0
    out = capsys.readouterr().out
    assert "dataset aerial-loc/tiny-v2: 1 episodes, 8 steps" in out and f"MINARI_DATASETS_PATH={tmp_path}" in out
    assert cli(["dataset", "export", "--env", "AerialLoc/Small-v3", "--agent", "dead-reckoning", "--episodes", "1",
                "--out", str(tmp_path), "--id", "aerial-loc/tiny-v2"]) == 2
    assert "aerial-loc/tiny-v2' already exists" in capsys.readouterr().err
    assert cli(["dataset", "export", "--env", "AerialLoc/Small-v3", "--agent", "no-such-agent", "--episodes", "1",
                "--out", str(tmp_path)]) == 2
    assert "unknown agent spec 'no-such-agent'" in capsys.readouterr().err
    assert cli(["dataset", "export", "--env", "AerialLoc/Small-v3", "--agent", "dead-reckoning", "--episodes", "0",
                "--out", str(tmp_path)]) == 2
    assert "--episodes 0 must be a positive integer" in capsys.readouterr().err
    assert not (tmp_path / "aerial-loc" / "small-dead-reckoning-v3").exists()


def test_without_minari_the_error_names_the_extra(monkeypatch, tmp_path):
    import sys

    from aerial_loc_env.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, "minari", None)     # as if minari were not installed
    with pytest.raises(MissingExtraError, match=r"Minari dataset.*pip install 'aerial-loc-env\[data\]'"):
        export_episodes("AerialLoc/Small-v3", "dead-reckoning", 1, root=tmp_path)
    assert not any(tmp_path.iterdir())
