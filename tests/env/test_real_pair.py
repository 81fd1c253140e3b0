"""AerialLoc/RealPair-v2: a real two-epoch pair given by path (map = epoch A, camera over epoch B), through
Gymnasium's and SB3's env checkers, deterministic for a seed, and clear errors for what a user may get wrong."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from shared_helpers import SHARED_DATA, check_env_silently
from synthetic_pairs import write_pair

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.errors import ConfigError, MapError

SID = "AerialLoc/RealPair-v2"
LEVIR = SHARED_DATA / "pairs" / "levir-cd"


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A 512 m tile at 0.5 m/px (the scenario's geometry), B 0.3 m off A and on a grid 0.25 px away."""
    a, b = write_pair(tmp_path_factory.mktemp("pair"), size_px=1024, shift_m=(0.3, -0.2), b_offset_px=(0.25, 0.0))
    return {"path_a": str(a), "path_b": str(b)}


def test_checkers_pass_on_a_synthetic_pair(synthetic):
    check_env_silently(SID, duration_s=2.0, **synthetic)


def test_the_map_is_epoch_a_and_the_camera_flies_over_epoch_b(synthetic):
    env = gym.make(SID, duration_s=2.0, **synthetic).unwrapped
    world = env.world
    assert env.database is world.surveyed and env.orthomap is world.ground
    assert world.surveyed.rgb.shape == world.ground.rgb.shape
    assert not np.array_equal(world.surveyed.rgb, world.ground.rgb)
    assert "pair epoch B" in world.ground.source and "misregistration" in world.ground.source
    obs, info = env.reset(seed=0)
    assert obs["image"].shape == (400, 600, 3)
    # the flight fits the 512 m tile: a full 60 s track at 5 m/s (241 poses), footprints inside the map
    full = gym.make(SID, **synthetic).unwrapped
    full.reset(seed=1)
    assert len(full._track) == 241 and full._track.length_m == pytest.approx(300.0, rel=0.05)


def test_same_seed_same_frames(synthetic):
    runs = []
    for _ in range(2):
        env = gym.make(SID, duration_s=2.0, **synthetic)
        obs, info = env.reset(seed=5)
        frames = [obs["image"].copy()]
        for _ in range(4):
            obs, *_ = env.step(np.zeros(2, np.float32))
            frames.append(obs["image"].copy())
        runs.append((frames, info["true_pose"].copy()))
        env.close()
    assert all(np.array_equal(x, y) for x, y in zip(runs[0][0], runs[1][0], strict=True))
    assert np.array_equal(runs[0][1], runs[1][1])
    other = gym.make(SID, duration_s=2.0, **synthetic)
    obs, _ = other.reset(seed=6)
    assert not np.array_equal(obs["image"], runs[0][0][0])


def test_missing_paths_are_a_clear_error():
    with pytest.raises(ConfigError, match=r"map\.kind = 'pair' needs map\.path_a .* map\.path_a and map\.path_b "
                                          r"missing: e\.g\. gym\.make\('AerialLoc/RealPair-v2', path_a="):
        gym.make(SID)
    with pytest.raises(ConfigError, match=r"map\.path_b missing"):
        gym.make(SID, path_a="A/x.png")


@pytest.mark.slow
def test_a_missing_image_a_misregistered_pair_and_an_epoch_are_refused(tmp_path, synthetic):
    with pytest.raises(MapError, match=r"map\.path_b '.*nowhere\.png' \(epoch B, the camera's ground\) does not "
                                       r"exist"):
        gym.make(SID, path_a=synthetic["path_a"], path_b=str(tmp_path / "nowhere.png"))
    a, b = write_pair(tmp_path / "far", size_px=1024, shift_m=(2.5, 0.0))
    with pytest.raises(MapError, match=r"^AerialLoc/RealPair-v2: p\.png \(A\) and p\.png \(B\) are misregistered "
                                       r"by 2\.\d\d m"):
        gym.make(SID, path_a=str(a), path_b=str(b))
    env = gym.make(SID, path_a=str(a), path_b=str(b), map={"correct_shift": True}, duration_s=2.0).unwrapped
    assert env.world.ground.source.count("after removing a constant shift of +5.0") == 1
    with pytest.raises(ConfigError, match=r"\[epoch\] simulates one .* leave \[epoch\] at its defaults"):
        gym.make(SID, epoch={"built": 0.1}, **synthetic)
    with pytest.raises(ConfigError, match=r"perspective\.enabled = true .* has no height model"):
        gym.make(SID, perspective={"enabled": True}, **synthetic)
    with pytest.raises(ConfigError, match=r"map\.path_a is only used with map\.kind = 'pair'"):
        gym.make("AerialLoc/Small-v3", path_a=synthetic["path_a"])


@pytest.mark.parametrize("name", ["test_1.png", "test_4.png"])
def test_a_real_levir_pair_passes_the_checkers(name):
    if not (LEVIR / "A" / name).is_file():
        pytest.skip(f"real image pairs not available: {LEVIR} (../shared/data/pairs, beside the project)")
    check_env_silently(SID, path_a=str(LEVIR / "A" / name), path_b=str(LEVIR / "B" / name), map={"gsd_m": 0.5},
                       duration_s=2.0)
