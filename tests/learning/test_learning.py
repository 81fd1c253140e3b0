"""Learned policies: recipes (bad fields are clear errors), the local-registration observation (zero
correction = dead reckoning, corrections in the vehicle frame), a tiny training run end to end (files, refuse
overwrite, resume), save/reload with identical predictions, and the loaded agent in the benchmark harness."""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env import world_to_action
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.dead_reckoning import DeadReckoningAgent
from aerial_loc_env.estimators.registry import make_agent

pytest.importorskip("stable_baselines3")
pytest.importorskip("torch")

from aerial_loc_env.learning.observations import LocalRegistration, LocalRegistrationWrapper  # noqa: E402
from aerial_loc_env.learning.recipes import ObservationParams, RewardParams, recipe_from_table  # noqa: E402
from aerial_loc_env.learning.train import train  # noqa: E402

SHORT = {"flight.duration_s": 2.0}   # 8 steps per episode: keeps the end-to-end runs to seconds

TINY_RECIPE = """
description = "tiny test recipe"
class = "LearnedAgent"
[params]
model = "{model}"
[train]
algo = "{algo}"
scenario = "AerialLoc/Small-v3"
scenario_overrides = {{"flight.duration_s" = 2.0}}
observation = "{observation}"
total_timesteps = {steps}
n_envs = 2
subproc = false
eval_freq = 64
eval_episodes = 1
checkpoint_freq = 64
[train.observation_params]
image_px = {image_px}
[train.hyperparameters]
{hyper}
[train.policy]
cnn = "{cnn}"
features_dim = 32
net_arch = [16]
"""
PPO_HYPER = "n_steps = 32\nbatch_size = 32\nn_epochs = 1"


def write_recipe(folder: Path, name: str, *, algo: str = "PPO", observation: str = "local_registration",
                 cnn: str = "correlation", steps: int = 64, hyper: str = PPO_HYPER, model: str = "",
                 image_px: int = 32) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(TINY_RECIPE.format(algo=algo, observation=observation, cnn=cnn, steps=steps, hyper=hyper,
                                       image_px=image_px,
                                       model=model or str(folder / name / "model.zip")))
    return path


# ------------------------------------------------------------------------------------ recipes
@pytest.mark.parametrize("table, words", [
    ({"algo": "DQN"}, ["'algo'", "PPO"]),
    ({"learning_rate": 0.1}, ["unknown key", "learning_rate", "allowed keys"]),
    ({"hyperparameters": {"n_step": 64}}, ["[train.hyperparameters]", "n_step", "n_steps"]),
    ({"observation_params": {"image_px": 8}}, ["[train.observation_params]", "image_px", "[16, 256]"]),
    ({"observation_params": {"max_correction_m": 0.0}}, ["max_correction_m", "(0.1"]),
    ({"reward": {"kind": "bonus"}}, ["[train.reward]", "improvement"]),
    ({"policy": {"net_arch": [64, 0]}}, ["[train.policy]", "net_arch", "[1, 4096]"]),
    ({"policy": "big"}, ["[train.policy] must be a table"]),
    ({"observation": "map_memorization"}, ["correlation", "nature"]),
    ({"observation": "map_memorization", "policy": {"cnn": "nature"}, "observation_params": {"image_px": 32}},
     ["image_px", "36"]),
    ({"eval_seed": 1, "n_envs": 4}, ["eval_seed", "held-out"]),
    ({"total_timesteps": 0}, ["total_timesteps", "[1,"]),
])
def test_bad_recipe_fields_are_clear_errors(table: dict, words: list[str]) -> None:
    with pytest.raises(ConfigError) as exc:
        recipe_from_table(table, "agents/x.toml")
    msg = str(exc.value)
    assert "agents/x.toml" in msg
    for w in words:
        assert w in msg, (w, msg)


def test_recipe_round_trips_through_its_dict() -> None:
    from aerial_loc_env.learning.recipes import recipe_to_dict

    r = recipe_from_table({"algo": "SAC", "observation": "map_memorization", "policy": {"cnn": "nature",
                           "net_arch": [64, 32]}, "hyperparameters": {"buffer_size": 1000},
                           "reward": {"scale_m": 2.0}}, "x")
    assert recipe_from_table(json.loads(json.dumps(recipe_to_dict(r))), "y") == r


def test_shipped_recipes_are_valid() -> None:
    from aerial_loc_env.estimators.registry import list_specs
    from aerial_loc_env.learning.embedding import read_recipe
    from aerial_loc_env.learning.surface_train import read_recipe as read_registration_recipe
    from aerial_loc_env.learning.train import recipe_of

    specs = [s for s in list_specs() if "train" in s.extra]
    assert {s.name for s in specs} >= {"ppo-local-registration", "mcl-learned", "ppo-learned-registration"}
    for s in specs:
        if s.extra["train"].get("kind") == "embedding":     # the learned MCL model's encoder (learning/embedding.py)
            read_recipe(s.name)
        elif s.extra["train"].get("kind") == "learned_registration":     # learning/surface_train.py
            read_registration_recipe(s.name)
        else:
            recipe_of(s)


# ------------------------------------------------------------------------------------ observation design
def test_zero_correction_is_dead_reckoning_and_corrections_are_in_the_vehicle_frame() -> None:
    env = gym.make("AerialLoc/Small-v3", **SHORT)
    obs, info = env.reset(seed=3)
    briefing = env.unwrapped.briefing
    core, dr = LocalRegistration(ObservationParams(image_px=32, max_correction_m=4.0)), DeadReckoningAgent()
    core.reset(briefing)
    dr.reset(briefing)
    done = False
    while not done:
        view = core.observe(obs)
        assert view["image"].shape == view["map"].shape == (32, 32, 3)
        est = dr.step(obs)
        np.testing.assert_allclose(core.correct(np.zeros(2)), [est.x_m, est.y_m], atol=1e-9)
        obs, _r, term, trunc, info = env.step(env.action_space.sample() * 0)
        done = term or trunc
    # one full forward correction moves the estimate max_correction_m along the heading; "right" is clockwise
    before = core.xy
    core.predicted = before.copy()
    fwd = core.correct(np.array([1.0, 0.0])) - before
    core.predicted = before.copy()
    right = core.correct(np.array([0.0, 1.0])) - before
    assert math.hypot(*fwd) == pytest.approx(4.0)
    assert math.atan2(fwd[1], fwd[0]) == pytest.approx(core.yaw, abs=1e-9)
    assert fwd[0] * right[1] - fwd[1] * right[0] < 0  # right of the heading (clockwise)


def test_wrapper_reward_pays_the_error_reduction() -> None:
    env = LocalRegistrationWrapper(gym.make("AerialLoc/Small-v3", **SHORT), ObservationParams(image_px=32),
                                   RewardParams(kind="improvement", scale_m=2.0, error_weight=0.0))
    env.reset(seed=5)
    truth = env._truth.copy()
    before = float(np.hypot(*(env.core.predicted - truth)))
    # the action that points straight at the truth (in the vehicle frame), clipped to the bound
    d = truth - env.core.predicted
    c, s = math.cos(env.core.yaw), math.sin(env.core.yaw)
    a = np.clip(np.array([d @ [c, s], d @ [s, -c]]) / env.core.params.max_correction_m, -1, 1)
    _obs, reward, _te, _tr, info = env.step(a.astype(np.float32))
    assert reward == pytest.approx((before - info["registration_error_m"]) / 2.0)
    assert info["registration_error_m"] < before


def test_curriculum_start_replaces_the_prior_offset_and_evaluation_keeps_the_prior() -> None:
    from aerial_loc_env.learning.recipes import recipe_from_table
    from aerial_loc_env.learning.train import make_env

    recipe = recipe_from_table({"start_std_m": 0.5, "scenario_overrides": SHORT,
                                "observation_params": {"image_px": 32}}, "x")
    offsets = {}
    for training in (True, False):
        wrapped = make_env(recipe, training=training)
        errs = []
        for seed in range(20):
            _obs, info = wrapped.reset(seed=seed)
            start = wrapped.get_wrapper_attr("core").predicted
            errs.append(float(np.hypot(*(start - info["true_pose"][:2]))))
        offsets[training] = math.sqrt(np.mean(np.square(errs)))
    # RMS radial offset: sqrt(2) * std, i.e. 0.71 m for the curriculum, 21 m for the 15 m prior
    assert offsets[True] < 2.0 < 10.0 < offsets[False]


# ------------------------------------------------------------------------------------ training end to end
@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("learn")
    res = train(write_recipe(folder, "tiny"), folder / "tiny", progress_bar=False)
    assert res.timesteps >= 64
    return res.model_path


@pytest.mark.slow
def test_training_writes_model_recipe_scenario_logs_and_checkpoints(tiny_model: Path) -> None:
    out = tiny_model.parent
    for name in ("model.zip", "recipe.toml", "scenario.json", "training.json", "eval.csv", "best/model.zip",
                 "logs/progress.csv", "monitor/0.monitor.csv"):
        assert (out / name).is_file(), name
    assert list((out / "checkpoints").glob("model_*_steps.zip"))
    if importlib.util.find_spec("tensorboard"):   # the rl extra has it; TensorBoard-compatible event files
        assert list((out / "logs").glob("events.out.tfevents.*"))
    meta = json.loads((out / "training.json").read_text())
    assert meta["recipe"]["observation"] == "local_registration"
    assert meta["scenario"]["id"] == "AerialLoc/Small-v3"
    assert meta["scenario"]["flight"]["duration_s"] == 2.0
    rows = (out / "eval.csv").read_text().splitlines()
    assert rows[0].startswith("timesteps") and "dead_reckoning_rmse_m" in rows[0] and len(rows) >= 2


@pytest.mark.slow
def test_existing_model_is_not_overwritten_and_resume_continues(tiny_model: Path) -> None:
    out = tiny_model.parent
    recipe = out.parent / "tiny.toml"
    stamp = tiny_model.stat().st_mtime_ns
    with pytest.raises(ConfigError, match="already exists"):
        train(recipe, out, progress_bar=False)
    assert tiny_model.stat().st_mtime_ns == stamp
    with pytest.raises(ConfigError, match="does not exist"):
        train(recipe, out / "other", resume=out / "nope.zip", progress_bar=False)
    ckpt = sorted((out / "checkpoints").glob("model_*_steps.zip"))[0]
    res = train(recipe, out / "resumed", resume=ckpt, total_timesteps=128, progress_bar=False)
    assert res.timesteps >= 128
    assert json.loads((out / "resumed" / "training.json").read_text())["resumed_at_timesteps"] > 0


@pytest.mark.slow
def test_saved_agent_reloads_with_identical_deterministic_predictions(tiny_model: Path) -> None:
    from aerial_loc_env.learning import agent as agent_mod

    env = gym.make("AerialLoc/Small-v3", **SHORT)

    def episode() -> list[tuple[float, float]]:
        agent_mod._MODELS.clear()   # a fresh load from disk each time
        agent = make_agent(tiny_model.parent.parent / "tiny.toml")
        obs, _ = env.reset(seed=11)
        agent.reset(env.unwrapped.briefing, seed=11)
        out, done = [], False
        while not done:
            est = agent.step(obs)
            out.append((est.x_m, est.y_m))
            obs, _r, te, tr, _ = env.step(np.clip(world_to_action(env.unwrapped.orthomap, est.x_m, est.y_m),
                                                  -1, 1))
            done = te or tr
        return out

    first, second = episode(), episode()
    assert first == second
    assert len(first) == 8


@pytest.mark.slow
def test_loaded_agent_runs_in_the_benchmark_harness(tiny_model: Path, tmp_path: Path) -> None:
    from aerial_loc_env.benchmark.grid import make_grid
    from aerial_loc_env.benchmark.runner import run_grid

    spec = tiny_model.parent.parent / "tiny.toml"
    grid = make_grid("learned", [str(spec), "dead-reckoning"],
                     [{"id": "AerialLoc/Small-v3", "overrides": SHORT}], seeds=[10_000, 10_001])
    rows = run_grid(grid, str(tmp_path / "bench"), progress=False)
    assert len(rows) == 4
    assert not (tmp_path / "bench" / "failures.jsonl").exists() or \
        not (tmp_path / "bench" / "failures.jsonl").read_text().strip()
    assert all(math.isfinite(r["rmse_m"]) for r in rows)


@pytest.mark.slow
@pytest.mark.parametrize("algo, observation, cnn, hyper", [
    ("SAC", "local_registration", "paired", "buffer_size = 64\nlearning_starts = 16\nbatch_size = 8"),
    ("PPO", "map_memorization", "nature", PPO_HYPER),
])
def test_other_algorithms_and_designs_train(tmp_path: Path, algo: str, observation: str, cnn: str,
                                            hyper: str) -> None:
    recipe = write_recipe(tmp_path, "other", algo=algo, observation=observation, cnn=cnn, steps=32,
                          hyper=hyper, image_px=40)
    res = train(recipe, tmp_path / "other", progress_bar=False)
    agent = make_agent(recipe)
    env = gym.make("AerialLoc/Small-v3", **SHORT)
    obs, _ = env.reset(seed=1)
    agent.reset(env.unwrapped.briefing)
    est = agent.step(obs)
    assert res.model_path.is_file() and math.isfinite(est.x_m) and math.isfinite(est.y_m)


def test_missing_model_is_a_clear_error(tmp_path: Path) -> None:
    recipe = write_recipe(tmp_path, "absent", model=str(tmp_path / "nowhere" / "model.zip"))
    with pytest.raises(ConfigError, match="does not exist.*aerial-loc train"):
        make_agent(recipe)


def test_correlation_cost_volume_finds_a_known_shift() -> None:
    """Database crop = camera view shifted by 8 px right and 4 px down: the cost volume (even with random
    encoder weights, which still compare like with like) peaks at dx = -2, dy = -1 feature pixels (stride 4),
    and equals the naive per-shift correlation."""
    import torch

    from aerial_loc_env.learning.networks import CorrelationCNN

    torch.manual_seed(0)
    space = gym.spaces.Dict({k: gym.spaces.Box(0, 255, (3, 64, 64), np.uint8) for k in ("image", "map")})
    net = CorrelationCNN(space, features_dim=16, max_shift=4)
    scene = torch.rand(2, 3, 80, 80)
    cam, db = scene[:, :, 8:72, 8:72], scene[:, :, 12:76, 16:80]
    with torch.no_grad():
        vol = net.cost_volume(cam, db)
        a, b = net._features(cam), net._features(db)
    s, side = net.max_shift, 2 * net.max_shift + 1
    for k in range(2):
        best = int(vol[k].argmax())
        assert (best // side - s, best % side - s) == (-1, -2)
    bp = torch.nn.functional.pad(b, (s, s, s, s))
    h, w = a.shape[2:]
    naive = torch.stack([(a * bp[:, :, s + dy:s + dy + h, s + dx:s + dx + w]).sum(1).mean((1, 2))
                         for dy in range(-s, s + 1) for dx in range(-s, s + 1)], dim=1)
    torch.testing.assert_close(vol, naive, rtol=1e-4, atol=1e-5)


@pytest.mark.slow
def test_shipped_model_loads_anywhere_and_beats_dead_reckoning(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """The committed model (package data) resolves relative to the package, not the working directory, and on
    held-out seeds of its scenario walks the estimate in from the prior: its RMSE is below dead reckoning's,
    whose error is dominated by the 15 m prior offset the policy is trained to remove."""
    monkeypatch.chdir(tmp_path)
    env = gym.make("AerialLoc/Small-v3")
    sq, sq_dr = [], []
    for seed in (50_000, 50_001, 50_002):
        learned, dr = make_agent("ppo-local-registration"), make_agent("dead-reckoning")
        obs, info = env.reset(seed=seed)
        for agent in (learned, dr):
            agent.reset(env.unwrapped.briefing, seed=seed)
        done = False
        while not done:
            truth = info["true_pose"][:2]
            est, est_dr = learned.step(obs), dr.step(obs)
            sq.append((est.x_m - truth[0]) ** 2 + (est.y_m - truth[1]) ** 2)
            sq_dr.append((est_dr.x_m - truth[0]) ** 2 + (est_dr.y_m - truth[1]) ** 2)
            action = np.clip(world_to_action(env.unwrapped.orthomap, est_dr.x_m, est_dr.y_m), -1, 1)
            obs, _r, te, tr, info = env.step(action)
            done = te or tr
    assert math.sqrt(np.mean(sq)) < math.sqrt(np.mean(sq_dr))
