"""Every registered scenario passes Gymnasium's and stable-baselines3's env checkers without a warning.

The real-map scenario runs on each tile of ../shared/data (skipped where that folder is absent). Nothing is
overridden: the checkers see the scenarios exactly as users get them.
"""

from __future__ import annotations

import pickle

import gymnasium as gym
import numpy as np
import pytest
from shared_helpers import REAL_TILES, SHARED_DATA, check_env_silently

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env.scenarios import specs

#: the ids whose map the user names (RealMap: a file; RealPair: two images) have tests of their own
USER_MAPS = ("AerialLoc/RealMap-v2", "AerialLoc/RealPair-v2")
IDS = [sid for sid in specs() if sid not in USER_MAPS]


@pytest.mark.slow
@pytest.mark.parametrize("sid", IDS)
def test_checkers_pass_without_warnings(sid):
    check_env_silently(sid)


@pytest.mark.parametrize("tile", REAL_TILES)
def test_real_map_checkers_pass_on_the_shared_tiles(shared_data, tile):
    check_env_silently("AerialLoc/RealMap-v2", path=str(shared_data / tile))


@pytest.mark.parametrize("tile", REAL_TILES)
def test_real_map_tracks_avoid_nodata(shared_data, tile):
    env = gym.make("AerialLoc/RealMap-v2", path=str(shared_data / tile)).unwrapped
    om = env.orthomap
    assert om.nodata is not None and om.nodata.any()
    for seed in range(3):
        env.reset(seed=seed)
        track = env._track
        # every footprint is rendered strictly (FootprintError on no-data); check it explicitly too
        for k in range(0, len(track), 10):
            assert env._renderer.footprint_status(env._pose(k)) == "valid"


def _kwargs(sid: str, shared: bool) -> dict:
    """Short episodes (2 s, 8 steps) keep these tests fast; the real map flies over the Manila tile."""
    kw: dict = {"duration_s": 2.0}
    if sid == "AerialLoc/RealPair-v2":
        levir = SHARED_DATA / "pairs" / "levir-cd"
        if not shared or not (levir / "A" / "test_1.png").is_file():
            pytest.skip(f"real image pairs not available: {levir}")
        kw.update(path_a=str(levir / "A" / "test_1.png"), path_b=str(levir / "B" / "test_1.png"),
                  map={"gsd_m": 0.5})
    if sid == "AerialLoc/RealMap-v2":
        tile = SHARED_DATA / REAL_TILES[0]
        if not shared or not tile.is_file():
            pytest.skip(f"real imagery not available: {tile}")
        kw["path"] = str(tile)
    return kw


ALL_IDS = sorted(specs())


@pytest.mark.slow
@pytest.mark.parametrize("sid", ALL_IDS)
def test_same_seed_same_rollout_and_pickle_for_every_id(sid):
    kw = _kwargs(sid, shared=True)
    runs = []
    for _ in range(2):
        env = gym.make(sid, **kw)
        obs, info = env.reset(seed=7)
        trace = [(obs, 0.0, info["true_pose"])]
        done = False
        while not done:
            obs, r, term, trunc, info = env.step(np.full(2, 0.25, np.float32))
            trace.append((obs, r, info["true_pose"]))
            done = term or trunc
        runs.append(trace)
    assert len(runs[0]) == len(runs[1]) == 9
    for (oa, ra, pa), (ob, rb, pb) in zip(*runs, strict=True):
        assert ra == rb
        np.testing.assert_array_equal(pa, pb)
        for key in oa:
            np.testing.assert_array_equal(oa[key], ob[key])
    env = gym.make(sid, **kw).unwrapped
    env.reset(seed=3)
    clone = pickle.loads(pickle.dumps(env))
    a, b = env.step(np.zeros(2, np.float32)), clone.step(np.zeros(2, np.float32))
    np.testing.assert_array_equal(a[0]["image"], b[0]["image"])


@pytest.mark.slow
@pytest.mark.parametrize("sid", ALL_IDS)
def test_async_vector_env_for_every_id(sid):
    kw = _kwargs(sid, shared=True)
    envs = gym.vector.AsyncVectorEnv([lambda: gym.make(sid, **kw)] * 2)
    try:
        obs, info = envs.reset(seed=[0, 1])
        for _ in range(3):
            obs, reward, term, trunc, info = envs.step(np.zeros((2, 2), np.float32))
        assert obs["image"].shape[0] == 2 and reward.shape == (2,)
    finally:
        envs.close()


@pytest.mark.slow
def test_sb3_multi_input_policy_accepts_the_observation(tmp_path):
    sb3 = pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.logger import configure

    env = gym.make("AerialLoc/Small-v3", duration_s=2.0)
    model = sb3.PPO("MultiInputPolicy", env, n_steps=8, batch_size=8, n_epochs=1, device="cpu", seed=0)
    model.set_logger(configure(str(tmp_path), []))   # SB3's default logger leaves an SB3-<date> folder in /tmp
    model.learn(8)                                   # one rollout and one update through the policy
    obs, _ = env.reset(seed=0)
    action, _ = model.predict(obs, deterministic=True)
    assert env.action_space.contains(action)
