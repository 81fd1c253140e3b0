"""Every registered scenario passes Gymnasium's and stable-baselines3's env checkers without a warning.

The real-map scenario runs on each tile of ../shared/data (skipped where that folder is absent). Nothing is
overridden: the checkers see the scenarios exactly as users get them.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import pytest
from conftest import REAL_TILES
from gymnasium.utils.env_checker import check_env

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env.scenarios import specs

IDS = [sid for sid in specs() if sid != "AerialLoc/RealMap-v0"]


def _check_silently(sid: str, **kwargs) -> None:
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(sid, render_mode="rgb_array", **kwargs).unwrapped)
        sb3_checker.check_env(gym.make(sid, **kwargs).unwrapped, warn=True)
    assert [str(w.message) for w in caught] == []


@pytest.mark.parametrize("sid", IDS)
def test_checkers_pass_without_warnings(sid):
    _check_silently(sid)


@pytest.mark.parametrize("tile", REAL_TILES)
def test_real_map_checkers_pass_on_the_shared_tiles(shared_data, tile):
    _check_silently("AerialLoc/RealMap-v0", path=str(shared_data / tile))


@pytest.mark.parametrize("tile", REAL_TILES)
def test_real_map_tracks_avoid_nodata(shared_data, tile):
    env = gym.make("AerialLoc/RealMap-v0", path=str(shared_data / tile)).unwrapped
    om = env.orthomap
    assert om.nodata is not None and om.nodata.any()
    for seed in range(3):
        env.reset(seed=seed)
        track = env._track
        # every footprint is rendered strictly (FootprintError on no-data); check it explicitly too
        for k in range(0, len(track), 10):
            assert env._renderer.footprint_status(env._pose(k)) == "valid"
