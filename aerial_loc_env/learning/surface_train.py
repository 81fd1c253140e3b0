"""Training of the learned-registration policy (``learning.surface``): behaviour cloning on the simulator's offsets,
then PPO fine-tuning with stable-baselines3, on the procedural worlds of the train split at full camera resolution.

The worlds: ``splits.worlds("train", n)`` (never a benchmark city, never the real pairs), each with the realistic
gap drawn as the supervised sampler draws it (``dataset.ExampleSampler``: the world's epoch, map sensor and map
sun; per episode the sun, clouds, altitude, camera errors, exposure, haze, perspective), flown as short tracking
episodes at the preset's full-resolution camera (600 x 400). Validation flies the val split's worlds the same way.

1. **Behaviour cloning** (``collect`` then ``behaviour_cloning``): the episodes are flown with the true position
   as the estimate; at each frame the surface is read around ``n_offsets`` positions offset from the truth (a
   mixture of small offsets, as when tracking, and large ones, as at the start from the 15 m prior), and the
   policy's mean action is regressed on the correction that brings each back to the truth (``-offset``, over
   ``max_correction_m``), mean squared error, Adam. The offsets: ``small_offset_std_m`` per axis (tracking), and a
   ``large_offset_share`` of them large (``large_offsets``: uniform over the surface's reach, or as the prior's
   error): the regression's answer to an ambiguous surface is the mean correction under that mixture.
2. **PPO** (``fine_tune``): SB3's PPO from the cloned weights on ``RegistrationEnv`` (closed loop: the policy's
   own corrections move the next prediction), reward the error reduction the correction achieved (as the
   local-registration wrapper's ``improvement``), with held-out validation episodes every ``eval_freq`` steps. The
   critic learns alone for ``critic_warmup_timesteps`` (the cloned actor frozen), so that the first updates'
   advantages come from a fitted value function.

Both stages are scored on the same validation episodes (closed loop, the RMSE of the estimates); the one with the
lower RMSE is exported as the shipped ``policy.npz`` (``learning.surface.SurfacePolicy``, NumPy inference).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from aerial_loc_env.config import build_config, config_to_dict, rng
from aerial_loc_env.env import world_to_action
from aerial_loc_env.errors import ConfigError, require_extra
from aerial_loc_env.learning.surface import (
    POLICY_FORMAT,
    SurfaceParams,
    SurfacePolicy,
    SurfaceRegistration,
    write_policy,
)
from aerial_loc_env.learning.train import training_machine, training_versions

RECIPE_KIND = "learned_registration"


@dataclass(frozen=True)
class RegistrationRecipe:
    """The ``[train]`` table of ``agents/ppo-learned-registration.toml`` (``kind = "learned_registration"``)."""

    kind: str = RECIPE_KIND
    seed: int = field(default=0, metadata=rng(0, 2**31 - 1))
    # the worlds (the embedding's train / validation splits)
    n_train_worlds: int = field(default=16, metadata=rng(1, 10000))
    n_val_worlds: int = field(default=4, metadata=rng(1, 10000))
    city_size_m: float = field(default=400.0, metadata=rng(300.0, 8000.0))
    # the flights over them
    altitude_min_m: float = field(default=150.0, metadata=rng(20.0, 2000.0))
    altitude_max_m: float = field(default=250.0, metadata=rng(20.0, 2000.0))
    speed_min_mps: float = field(default=5.0, metadata=rng(0.5, 100.0))
    speed_max_mps: float = field(default=20.0, metadata=rng(0.5, 100.0))
    duration_s: float = field(default=15.0, metadata=rng(1.0, 600.0, doc="one episode's track"))
    prior_std_m: float = field(default=15.0, metadata=rng(0.0, 200.0))
    # the observation
    half_cells: int = field(default=16, metadata=rng(1, 64))
    step_m: float = field(default=2.5, metadata=rng(0.1, 50.0))
    max_correction_m: float = field(default=40.0, metadata=rng(0.1, 500.0, lo_open=True))
    encoder: str = "models/mcl-learned/weights.npz"
    # the network
    conv_channels: tuple[int, ...] = (8, 8)
    conv_kernels: tuple[int, ...] = (5, 3)
    pool: int = field(default=3, metadata=rng(1, 16))
    net_arch: tuple[int, ...] = (64,)
    # behaviour cloning
    bc_episodes: int = field(default=96, metadata=rng(1, 10**6, doc="episodes flown for the cloning data"))
    bc_frame_stride: int = field(default=2, metadata=rng(1, 1000, doc="every n-th frame of an episode"))
    n_offsets: int = field(default=6, metadata=rng(1, 256))
    small_offset_std_m: float = field(default=3.0, metadata=rng(0.0, 100.0))
    large_offset_share: float = field(default=0.4, metadata=rng(0.0, 1.0))
    large_offsets: str = field(default="uniform", metadata=rng(choices=("uniform", "prior")))
    bc_epochs: int = field(default=30, metadata=rng(0, 10000))
    bc_batch: int = field(default=256, metadata=rng(1, 65536))
    bc_learning_rate: float = field(default=0.002, metadata=rng(0.0, 1.0, lo_open=True))
    # PPO fine-tuning
    ppo_timesteps: int = field(default=8192, metadata=rng(0, 10**9))
    n_envs: int = field(default=2, metadata=rng(1, 64))
    n_steps: int = field(default=256, metadata=rng(2, 100000))
    batch_size: int = field(default=128, metadata=rng(2, 100000))
    n_epochs: int = field(default=4, metadata=rng(1, 1000))
    learning_rate: float = field(default=0.00005, metadata=rng(0.0, 1.0, lo_open=True))
    gamma: float = field(default=0.8, metadata=rng(0.0, 1.0))
    gae_lambda: float = field(default=0.9, metadata=rng(0.0, 1.0))
    clip_range: float = field(default=0.1, metadata=rng(0.0, 10.0, lo_open=True))
    log_std_init: float = field(default=-4.0, metadata=rng(-10.0, 2.0))
    share_features_extractor: bool = True
    critic_warmup_timesteps: int = field(default=2048, metadata=rng(0, 10**9, doc=(
        "PPO's first timesteps train the value function only (the cloned actor frozen)")))
    reward_scale_m: float = field(default=4.0, metadata=rng(0.01, 1000.0))
    error_weight: float = field(default=0.1, metadata=rng(0.0, 100.0))
    start_std_m: float = field(default=15.0, metadata=rng(0.0, 1000.0, doc="PPO episodes start N(truth, std^2)"))
    eval_freq: int = field(default=2048, metadata=rng(1, 10**9))
    val_episodes: int = field(default=8, metadata=rng(1, 10000))
    # machine
    threads: int = field(default=1, metadata=rng(1, 256))
    workers: int = field(default=2, metadata=rng(1, 64))
    max_wall_s: float = field(default=1740.0, metadata=rng(1.0, 10**7))

    def validate(self, where: str) -> None:
        if self.kind != RECIPE_KIND:
            raise ConfigError(f"{where}: kind = {self.kind!r}; this recipe kind is {RECIPE_KIND!r}")
        if self.altitude_min_m > self.altitude_max_m or self.speed_min_mps > self.speed_max_mps:
            raise ConfigError(f"{where}: altitude_min_m <= altitude_max_m and speed_min_mps <= speed_max_mps needed")
        if len(self.conv_channels) != len(self.conv_kernels) or not self.conv_channels:
            raise ConfigError(f"{where}: conv_channels and conv_kernels must be non-empty lists of one length")
        if any(k % 2 != 1 for k in self.conv_kernels):
            raise ConfigError(f"{where}: conv_kernels must be odd, got {list(self.conv_kernels)}")
        if (2 * self.half_cells + 1) < self.pool:
            raise ConfigError(f"{where}: pool = {self.pool} exceeds the surface's side {2 * self.half_cells + 1}")

    @property
    def surface(self) -> SurfaceParams:
        return SurfaceParams(self.half_cells, self.step_m, self.max_correction_m, self.encoder)


def is_registration_recipe(name: str) -> bool:
    """Whether the agent spec ``name`` holds a learned-registration recipe (``[train] kind``)."""
    from aerial_loc_env.estimators.registry import load_spec

    try:
        spec = load_spec(name)
    except ConfigError:
        return False
    return isinstance(spec.extra.get("train"), dict) and spec.extra["train"].get("kind") == RECIPE_KIND


def read_recipe(name: str, **overrides: Any) -> RegistrationRecipe:
    """The recipe of agent spec ``name`` with ``overrides`` applied (checked like the file)."""
    from aerial_loc_env.estimators.registry import load_spec

    spec = load_spec(name)
    table = dict(spec.extra.get("train", {}))
    table.update(overrides)
    return build_config(RegistrationRecipe, table, where=f"{spec.where} [train]")


# ---------------------------------------------------------------------- the worlds' episodes
class EpisodeMaker:
    """Tracking episodes over a split's worlds, each a pure function of its seed (``make(seed)``: the env and
    its reset's observation and info)."""

    def __init__(self, recipe: RegistrationRecipe, split: str, n_worlds: int) -> None:
        from aerial_loc_env.learning.dataset import ExampleSampler

        self.recipe = recipe
        self.sampler = ExampleSampler(split, n_worlds=n_worlds, city_size_m=recipe.city_size_m, n_offsets=0,
                                      randomization={"altitude_m": (recipe.altitude_min_m, recipe.altitude_max_m)})
        self._env: Any = None

    def scenario(self, seed: int) -> Any:
        from aerial_loc_env.env.scenarios import build_scenario

        g = np.random.default_rng([int(seed), 31])
        world = self.sampler.worlds[int(g.integers(len(self.sampler.worlds)))]
        sc = self.sampler.scenario(world, self.sampler.randomization.draw_frame(g))
        raw = sc.to_dict()
        r = self.recipe
        raw["id"] = "AerialLoc/TrainingRegistration-v1"
        raw["flight"] = {**raw["flight"], "duration_s": r.duration_s, "min_steps": 8, "margin_m": 45.0,
                         "speed_mps": float(g.uniform(r.speed_min_mps, r.speed_max_mps)), "min_leg_m": 100.0}
        raw["episode"] = {**raw.get("episode", {}), "start": "tracking", "prior_std_m": r.prior_std_m}
        return build_scenario(raw, where=f"learned registration episode over world {world.name}")

    def make(self, seed: int) -> tuple[Any, dict, dict]:
        from aerial_loc_env.env.aerial_loc_env import AerialLocEnv

        if self._env is not None:
            self._env.close()
        self._env = AerialLocEnv(self.scenario(seed))
        obs, info = self._env.reset(seed=int(seed))
        return self._env, obs, info


def _offsets(recipe: RegistrationRecipe, g: np.random.Generator, n: int) -> np.ndarray:
    """(n, 2) offsets of the prediction from the truth: small (tracking) or large (the start, a lost track):
    uniform over the surface's reach, or as the prior's error (``large_offsets``)."""
    reach = recipe.max_correction_m * 0.95
    large = g.random(n) < recipe.large_offset_share
    out = g.normal(0.0, recipe.small_offset_std_m, (n, 2))
    k = int(large.sum())
    out[large] = g.uniform(-reach, reach, (k, 2)) if recipe.large_offsets == "uniform" \
        else g.normal(0.0, recipe.prior_std_m, (k, 2))
    return np.clip(out, -reach, reach)


def _collect_work(args: tuple[RegistrationRecipe, str, int, list[int]]) -> tuple[np.ndarray, np.ndarray]:
    recipe, split, n_worlds, seeds = args
    import cv2

    cv2.setNumThreads(1)
    maker = EpisodeMaker(recipe, split, n_worlds)
    core = SurfaceRegistration(recipe.surface)
    xs, ys = [], []
    for seed in seeds:
        g = np.random.default_rng([seed, 37])
        env, obs, info = maker.make(seed)
        core.reset(env.briefing)
        t = 0
        while True:
            truth = np.asarray(info["true_pose"][:2], dtype=float)
            if t % recipe.bc_frame_stride == 0:
                core.prepare(obs)
                off = _offsets(recipe, g, recipe.n_offsets)
                xs.append(core.surfaces(truth[None] + off))
                ys.append((-off / recipe.max_correction_m).astype(np.float32))
            obs, _r, term, trunc, info = env.step(np.clip(world_to_action(env.briefing.orthomap, *truth), -1, 1))
            t += 1
            if term or trunc:
                break
    return np.concatenate(xs), np.concatenate(ys)


def collect(recipe: RegistrationRecipe, split: str, n_worlds: int, seeds: list[int],
            workers: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Behaviour-cloning data: (surfaces (n, side, side) float32, target actions (n, 2) float32) over the
    episodes of ``seeds`` (the same for any ``workers``)."""
    chunks = [seeds[k::workers] for k in range(workers)]
    if workers == 1:
        parts = [_collect_work((recipe, split, n_worlds, seeds))]
    else:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            parts = pool.map(_collect_work, [(recipe, split, n_worlds, c) for c in chunks])
    # back in seed order: chunk k holds seeds k, k + workers, ... (each episode's rows stay together)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


class RegistrationEnv(gym.Env):
    """The closed loop for PPO: each reset flies a new episode of the split's worlds (seeded), the policy's action
    corrects the dead-reckoned prediction, the reward is the error reduction (module doc). ``info`` gains
    ``registration_error_m``; at the end ``episode_rmse_m``."""

    metadata: dict = {"render_modes": []}

    def __init__(self, recipe: RegistrationRecipe, split: str = "train", n_worlds: int | None = None,
                 start_std_m: float = 0.0) -> None:
        super().__init__()
        import cv2

        cv2.setNumThreads(1)
        self.recipe = recipe
        self.maker = EpisodeMaker(recipe, split, n_worlds or recipe.n_train_worlds)
        self.core = SurfaceRegistration(recipe.surface)
        side = recipe.surface.side
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (1, side, side), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.start_std_m = start_std_m
        self._seed = 0
        self._sq: list[float] = []

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        if seed is not None:
            self._seed = int(seed)
        else:
            self._seed += 1000
        self.env, obs, info = self.maker.make(self._seed)
        truth = np.asarray(info["true_pose"][:2], dtype=float)
        start = None
        if self.start_std_m > 0:
            start = truth + np.random.default_rng([self._seed, 7]).normal(0.0, self.start_std_m, 2)
        self.core.reset(self.env.briefing, start)
        self._truth = truth
        self._sq = []
        return self.core.observe(obs), {}

    def step(self, action):
        before = float(np.hypot(*(self.core.predicted - self._truth)))
        xy = self.core.correct(action)
        error = float(np.hypot(*(xy - self._truth)))
        self._sq.append(error ** 2)
        obs, _r, term, trunc, info = self.env.step(np.clip(world_to_action(self.env.briefing.orthomap, *xy), -1, 1))
        self._truth = np.asarray(info["true_pose"][:2], dtype=float)
        out = {"registration_error_m": error}
        if term or trunc:
            out["episode_rmse_m"] = math.sqrt(float(np.mean(self._sq)))
        r = self.recipe
        reward = (before - error - r.error_weight * error) / r.reward_scale_m
        return self.core.observe(obs), float(reward), term, trunc, out


# ---------------------------------------------------------------------- evaluation
def evaluate(policy: Any, recipe: RegistrationRecipe, seeds: list[int], split: str = "val",
             n_worlds: int | None = None) -> dict[str, float]:
    """Closed-loop episodes from the prior (``policy(surface) -> action``; a zero action is dead reckoning):
    pooled and median-episode RMSE of the estimates."""
    env = RegistrationEnv(recipe, split, n_worlds or recipe.n_val_worlds)
    rmses, sq = [], []
    for seed in seeds:
        obs, _ = env.reset(seed=seed)
        done, ep = False, []
        while not done:
            obs, _r, term, trunc, info = env.step(policy(obs))
            ep.append(info["registration_error_m"] ** 2)
            done = term or trunc
        sq += ep
        rmses.append(math.sqrt(float(np.mean(ep))))
    return {"rmse_m": math.sqrt(float(np.mean(sq))), "median_episode_rmse_m": float(np.median(rmses)),
            "episodes": len(seeds)}


# ---------------------------------------------------------------------- the SB3 model, cloning, export
def make_model(recipe: RegistrationRecipe, env: Any) -> Any:
    """SB3 PPO with ``SurfaceCNN`` as its features extractor and the recipe's hyperparameters (with
    ``share_features_extractor = false`` the critic has its own extractor, whose gradients never move the actor's
    cloned features)."""
    sb3 = require_extra("stable_baselines3", "rl", "Training the learned registration")
    th = require_extra("torch", "rl", "Training the learned registration")
    from aerial_loc_env.learning.networks import SurfaceCNN

    r = recipe
    kwargs = {"features_extractor_class": SurfaceCNN,
              "features_extractor_kwargs": {"channels": tuple(r.conv_channels), "kernels": tuple(r.conv_kernels),
                                            "pool": r.pool},
              "net_arch": {"pi": list(r.net_arch), "vf": list(r.net_arch)}, "activation_fn": th.nn.Tanh,
              "log_std_init": r.log_std_init, "share_features_extractor": r.share_features_extractor}
    return sb3.PPO("MlpPolicy", env, policy_kwargs=kwargs, seed=r.seed, device="cpu", n_steps=r.n_steps,
                   batch_size=r.batch_size, n_epochs=r.n_epochs, learning_rate=r.learning_rate, gamma=r.gamma,
                   gae_lambda=r.gae_lambda, clip_range=r.clip_range, ent_coef=0.0, max_grad_norm=0.5, verbose=0)


def mean_action(policy: Any, obs: Any) -> Any:
    """The policy's Gaussian mean (its deterministic action before clipping) for a batch of surfaces."""
    features = policy.pi_features_extractor(obs.float())     # a float Box: SB3's preprocessing is the cast
    return policy.action_net(policy.mlp_extractor.forward_actor(features))


def behaviour_cloning(model: Any, data: tuple[np.ndarray, np.ndarray], val: tuple[np.ndarray, np.ndarray],
                      recipe: RegistrationRecipe, deadline: float) -> list[dict]:
    """Regress the policy's mean action on the targets (MSE, Adam); one row per epoch (train and val loss, and
    the val loss in metres of correction)."""
    th = require_extra("torch", "rl", "Training the learned registration")
    policy = model.policy
    params = [*policy.features_extractor.parameters(), *policy.mlp_extractor.policy_net.parameters(),
              *policy.action_net.parameters()]
    opt = th.optim.Adam(params, lr=recipe.bc_learning_rate)
    sched = th.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(recipe.bc_epochs, 1))
    x, y = th.from_numpy(data[0][:, None]), th.from_numpy(data[1])
    xv, yv = th.from_numpy(val[0][:, None]), th.from_numpy(val[1])
    g = th.Generator().manual_seed(recipe.seed)
    rows = []
    t0 = time.perf_counter()
    for epoch in range(1, recipe.bc_epochs + 1):
        policy.train()
        order = th.randperm(len(x), generator=g)
        total = 0.0
        for i in range(0, len(x), recipe.bc_batch):
            idx = order[i:i + recipe.bc_batch]
            loss = ((mean_action(policy, x[idx]) - y[idx]) ** 2).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += float(loss.detach()) * len(idx)
        sched.step()
        policy.eval()
        with th.no_grad():
            val_sq = ((mean_action(policy, xv).clamp(-1, 1) - yv) ** 2).sum(1)
        rows.append({"epoch": epoch, "wall_s": round(time.perf_counter() - t0, 1), "train_mse": total / len(x),
                     "val_mse": float(val_sq.mean() / 2),
                     "val_rms_m": float(val_sq.mean().sqrt()) * recipe.max_correction_m})
        if time.perf_counter() > deadline:
            break
    return rows


def export_policy(model: Any, recipe: RegistrationRecipe) -> tuple[dict[str, np.ndarray], dict]:
    """The policy's actor as NumPy arrays and metadata (``learning.surface.SurfacePolicy`` reads them)."""
    p = model.policy
    ext = p.features_extractor
    arrays: dict[str, np.ndarray] = {}
    convs = [*ext.hidden, ext.out]
    for i, conv in enumerate(convs):
        arrays[f"conv{i}_w"] = conv.weight.detach().numpy().copy()
        arrays[f"conv{i}_b"] = conv.bias.detach().numpy().copy()
    linears = [m for m in p.mlp_extractor.policy_net if hasattr(m, "weight")]
    for i, lin in enumerate(linears):
        arrays[f"mlp{i}_w"] = lin.weight.detach().numpy().copy()
        arrays[f"mlp{i}_b"] = lin.bias.detach().numpy().copy()
    arrays["action_w"] = p.action_net.weight.detach().numpy().copy()
    arrays["action_b"] = p.action_net.bias.detach().numpy().copy()
    s = recipe.surface
    meta = {"format": POLICY_FORMAT, "n_conv": len(convs), "n_mlp": len(linears), "pool": recipe.pool,
            "surface": {"half_cells": s.half_cells, "step_m": s.step_m, "max_correction_m": s.max_correction_m,
                        "encoder": s.encoder}}
    return arrays, meta


def numpy_policy(model: Any, recipe: RegistrationRecipe) -> SurfacePolicy:
    """The model's actor as the NumPy policy the agent runs."""
    arrays, meta = export_policy(model, recipe)
    return SurfacePolicy({k: v.astype(np.float32) for k, v in arrays.items()}, meta)


# ---------------------------------------------------------------------- the whole recipe
@dataclass
class RegistrationResult:
    path: Path | None
    chosen: str
    figures: dict
    bc_curve: list[dict]
    ppo_curve: list[dict]
    wall_s: float


def _vec_env(recipe: RegistrationRecipe) -> Any:
    vec = require_extra("stable_baselines3.common.vec_env", "rl", "Training the learned registration")

    def factory():
        return RegistrationEnv(recipe, "train", recipe.n_train_worlds, recipe.start_std_m)

    fns = [factory] * recipe.n_envs
    env = vec.SubprocVecEnv(fns, start_method="spawn") if recipe.n_envs > 1 else vec.DummyVecEnv(fns)
    env.seed(10**6 + recipe.seed)
    return env


def train_registration(recipe: RegistrationRecipe, out: str | Path | None = None, *, overwrite: bool = False,
                       verbose: bool = False) -> RegistrationResult:
    """Run the recipe (module doc): cloning data, cloning, PPO; write ``policy.npz`` (the better of the two on the
    validation episodes; ``policy_bc.npz`` and ``policy_ppo_last.npz`` the cloned one and PPO's last),
    ``training.json``, ``bc_curve.csv``, ``ppo_curve.csv`` and ``model.zip`` (the SB3 model of the last PPO step)
    into the folder ``out``."""
    th = require_extra("torch", "rl", "Training the learned registration")
    t0 = time.perf_counter()
    deadline = t0 + recipe.max_wall_s
    out_dir = Path(out) if out is not None else None
    if out_dir is not None and (out_dir / "policy.npz").exists() and not overwrite:
        raise ConfigError(f"learned registration: {out_dir / 'policy.npz'} exists; choose another --out or pass "
                          "--overwrite to replace it")
    th.set_num_threads(recipe.threads)
    th.manual_seed(recipe.seed)
    say = (lambda *a: print(*a, flush=True)) if verbose else (lambda *a: None)
    r = recipe
    seeds = [r.seed * 10**6 + k for k in range(r.bc_episodes)]
    data = collect(r, "train", r.n_train_worlds, seeds, r.workers)
    n_val_ep = max(1, r.bc_episodes // 8)
    val = collect(r, "val", r.n_val_worlds, [r.seed * 10**6 + k for k in range(n_val_ep)], min(r.workers, n_val_ep))
    t_data = time.perf_counter() - t0
    say(f"cloning data: {len(data[0])} train, {len(val[0])} val surfaces in {t_data:.0f} s")
    env = _vec_env(r)
    try:
        model = make_model(r, env)
        bc_curve = behaviour_cloning(model, data, val, r, deadline)
        say(f"cloning: {bc_curve[-1] if bc_curve else 'no epoch'}")
        val_seeds = [r.seed * 10**6 + 500_000 + k for k in range(r.val_episodes)]
        t_bc = time.perf_counter() - t0
        bc_eval = evaluate(numpy_policy(model, r), r, val_seeds)
        say(f"cloned policy on val episodes: {bc_eval}")
        best = bc = ("bc", bc_eval["rmse_m"], export_policy(model, r))
        ppo_curve = [{"timesteps": 0, "wall_s": round(time.perf_counter() - t0, 1), **bc_eval}]
        if r.ppo_timesteps > 0 and time.perf_counter() < deadline:
            best = _fine_tune(model, r, val_seeds, ppo_curve, best, deadline, t0, say)
    finally:
        env.close()
    wall = time.perf_counter() - t0
    ppo_rows = ppo_curve[1:]
    figures = {"bc_val_rmse_m": bc_eval["rmse_m"], "bc_val_median_episode_rmse_m": bc_eval["median_episode_rmse_m"],
               "ppo_best_val_rmse_m": min((row["rmse_m"] for row in ppo_rows), default=None),
               "ppo_timesteps": int(model.num_timesteps), "chosen": best[0], "chosen_val_rmse_m": best[1],
               "bc_surfaces": len(data[0]), "data_s": round(t_data, 1), "bc_done_s": round(t_bc, 1),
               "wall_s": round(wall, 1), "threads": r.threads, "workers": r.workers}
    path = None
    if out_dir is not None:
        # the chosen policy, and both stages' for comparison (the cloned one, PPO's last)
        for name, (arrays, meta) in (("policy.npz", best[2]), ("policy_bc.npz", bc[2]),
                                     ("policy_ppo_last.npz", export_policy(model, r))):
            meta = {**meta, "recipe": config_to_dict(r), "training": figures}
            written = write_policy(arrays, meta, out_dir / name, overwrite=True)
            path = written if name == "policy.npz" else path
        model.save(str(out_dir / "model.zip"))
        _write_csv(out_dir / "bc_curve.csv", bc_curve)
        _write_csv(out_dir / "ppo_curve.csv", ppo_curve)
        (out_dir / "training.json").write_text(json.dumps(
            {"recipe": config_to_dict(r), "training": figures, "machine": training_machine(),
             "versions": training_versions()}, indent=1, default=list))
    return RegistrationResult(path, best[0], figures, bc_curve, ppo_curve, wall)


def _fine_tune(model: Any, r: RegistrationRecipe, val_seeds: list[int], curve: list[dict], best: tuple,
               deadline: float, t0: float, say: Any) -> tuple:
    """PPO from the cloned weights, evaluated every ``eval_freq`` steps; returns the best (name, rmse, export)."""
    callbacks = require_extra("stable_baselines3.common.callbacks", "rl", "Training the learned registration")
    state = {"best": best, "last": 0}

    class ValEval(callbacks.BaseCallback):
        def _actor(self, trainable: bool) -> None:
            p = self.model.policy
            for part in (p.pi_features_extractor, p.mlp_extractor.policy_net, p.action_net):
                for q in part.parameters():
                    q.requires_grad_(trainable)
            p.log_std.requires_grad_(trainable)

        def _on_training_start(self) -> None:
            self._actor(r.critic_warmup_timesteps <= 0)

        def _on_rollout_end(self) -> None:    # before the update of the rollout just collected
            if self.num_timesteps > r.critic_warmup_timesteps:
                self._actor(True)

        def _on_step(self) -> bool:
            if self.num_timesteps - state["last"] >= r.eval_freq:
                self.run()
            return time.perf_counter() < deadline

        def run(self) -> None:
            state["last"] = self.num_timesteps
            res = evaluate(numpy_policy(self.model, r), r, val_seeds)
            curve.append({"timesteps": int(self.num_timesteps), "wall_s": round(time.perf_counter() - t0, 1), **res})
            say(f"PPO {self.num_timesteps}: {res}")
            if res["rmse_m"] < state["best"][1]:
                state["best"] = (f"bc+ppo@{self.num_timesteps}", res["rmse_m"], export_policy(self.model, r))

        def _on_training_end(self) -> None:
            if state["last"] != self.num_timesteps and time.perf_counter() < deadline + 120:
                self.run()

    # no SB3 output (the curve above is the record): its default logger would leave an SB3-<date> folder in /tmp
    model.set_logger(require_extra("stable_baselines3.common.logger", "rl", "Training the learned registration")
                     .Logger(None, []))
    model.learn(r.ppo_timesteps, callback=ValEval())
    return state["best"]


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    keys = list(dict.fromkeys(k for row in rows for k in row))
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m aerial_loc_env.learning.surface_train",
                                 description="Train the learned-registration policy from a recipe.")
    ap.add_argument("recipe", nargs="?", default="ppo-learned-registration")
    ap.add_argument("--out", required=True, help="the output folder")
    ap.add_argument("--overwrite", action="store_true")
    ap.add_argument("--timesteps", type=int, help="override the recipe's ppo_timesteps")
    args = ap.parse_args(argv)
    recipe = read_recipe(args.recipe, **({"ppo_timesteps": args.timesteps} if args.timesteps is not None else {}))
    res = train_registration(recipe, args.out, overwrite=args.overwrite, verbose=True)
    print(json.dumps(res.figures))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
