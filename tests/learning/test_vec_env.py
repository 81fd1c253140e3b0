"""stable-baselines3's VecEnv over the vectorized env (``learning/vec_env.py``): the same observations, rewards,
dones and infos as SB3's own VecEnvs for the same seeds across episode ends (rewards float64 as SubprocVecEnv's),
SB3's attribute and method calls, and a recipe trains the same model with ``vectorization = "vector"`` as with
``"subproc"``."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import data_equivalence

import aerial_loc_env  # noqa: F401  (registers the scenarios)

pytest.importorskip("stable_baselines3")
pytest.importorskip("torch")

from stable_baselines3.common.monitor import Monitor  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: E402

from aerial_loc_env.learning.recipes import recipe_from_table  # noqa: E402
from aerial_loc_env.learning.train import make_env, train  # noqa: E402
from aerial_loc_env.learning.vec_env import ShardVecEnv  # noqa: E402

RECIPE = {"scenario_overrides": {"flight.duration_s": 2.0}, "observation_params": {"image_px": 32}}


def _fns(n: int) -> list:
    recipe = recipe_from_table(RECIPE, "test recipe")
    return [functools.partial(make_env, recipe)] * n


def _without_episode_time(info: dict) -> dict:
    """Monitor's episode summary holds the wall time since it started: equal runs differ there only."""
    if "episode" not in info:
        return info
    return {**info, "episode": {k: v for k, v in info["episode"].items() if k != "t"}}


@pytest.mark.slow
def test_shard_vec_env_steps_as_sb3s_vec_envs_across_episode_ends() -> None:
    ours, ref = ShardVecEnv(_fns(3), processes=2), DummyVecEnv(_fns(3))
    try:
        assert ours.processes == 2
        ours.seed(7)
        ref.seed(7)
        # SubprocVecEnv's dict, Dummy's OrderedDict
        assert data_equivalence(ours.reset(), dict(ref.reset()), exact=True)
        assert data_equivalence(ours.reset_infos, ref.reset_infos, exact=True)
        rng = np.random.default_rng(1)
        dones = 0
        for k in range(19):
            actions = rng.uniform(-1.0, 1.0, (3, 2)).astype(np.float32)
            if k % 3 == 2:       # (float32 actions travel through the shared actions, others as they are)
                actions = actions.astype(np.float64) + 1e-9
            obs, rewards, done, infos = ours.step(actions)
            obs_r, rewards_r, done_r, infos_r = ref.step(actions)
            assert data_equivalence(obs, dict(obs_r), exact=True), f"step {k}"
            assert rewards.dtype == np.float64 and np.array_equal(rewards.astype(np.float32), rewards_r)
            assert np.array_equal(done, done_r)
            assert data_equivalence([_without_episode_time(i) for i in infos],
                                    [_without_episode_time(i) for i in infos_r], exact=True), f"step {k}"
            dones += int(done.sum())
        assert dones == 6
        assert data_equivalence(ours.reset_infos, ref.reset_infos, exact=True)
        assert ours.get_attr("render_mode") == [None] * 3
        assert ours.env_is_wrapped(Monitor) == [True] * 3 and ours.has_attr("core")
        assert ours.env_method("get_episode_rewards", indices=[2]) == ref.env_method("get_episode_rewards",
                                                                                      indices=[2])
    finally:
        ours.close()
        ref.close()


@pytest.mark.slow
def test_vector_and_subproc_train_the_same_model(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    params = {}
    for kind in ("vector", "subproc"):
        spec = tmp_path / f"{kind}.toml"
        spec.write_text(f"""
class = "LearnedAgent"
[params]
model = "{tmp_path / kind / 'model.zip'}"
[train]
scenario = "AerialLoc/Small-v3"
scenario_overrides = {{"flight.duration_s" = 2.0}}
total_timesteps = 64
n_envs = 2
vectorization = "{kind}"
eval_freq = 1000
eval_episodes = 1
[train.observation_params]
image_px = 32
[train.hyperparameters]
n_steps = 32
batch_size = 32
n_epochs = 1
[train.policy]
features_dim = 32
net_arch = [16]
""")
        res = train(spec, tmp_path / kind, progress_bar=False)
        from stable_baselines3 import PPO

        params[kind] = PPO.load(str(res.model_path), device="cpu").policy.state_dict()
    assert params["vector"].keys() == params["subproc"].keys()
    for key, value in params["vector"].items():
        assert torch.equal(value, params["subproc"][key]), key
