"""Train a recipe with stable-baselines3.

Vectorized envs (seeded ``seed, seed + 1, ...``), periodic deterministic evaluation on held-out seeds
(``eval_seed, eval_seed + 1, ...``, the same episodes every time, with dead reckoning's RMSE on them for
comparison), checkpoints, CSV + TensorBoard logs, a progress bar, resume from a checkpoint, and a saved model
with its recipe (``recipe.toml``), the resolved scenario spec (``scenario.json``) and ``training.json`` beside
it. An existing model is never overwritten unless asked.

Output folder layout::

    model.zip  recipe.toml  scenario.json  training.json  eval.csv
    best/model.zip           (lowest evaluation RMSE)
    checkpoints/model_<steps>_steps.zip
    logs/progress.csv  logs/events.out.tfevents.*  monitor/<rank>.monitor.csv
"""

from __future__ import annotations

import csv
import dataclasses
import importlib.util
import json
import math
import os
import platform
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from aerial_loc_env.errors import ConfigError, require_extra
from aerial_loc_env.estimators.registry import AgentSpec, load_spec
from aerial_loc_env.learning.recipes import Recipe, algo_class, recipe_from_table, recipe_to_dict

MODEL_FILE = "model.zip"
#: per-episode figures the wrappers put in ``info`` at an episode's end, kept in the Monitor files
EPISODE_KEYS = ("episode_rmse_m", "dead_reckoning_rmse_m")


def recipe_of(spec: AgentSpec) -> Recipe:
    """The training recipe of an agent spec (its ``[train]`` table)."""
    if "train" not in spec.extra:
        raise ConfigError(f"{spec.where}: this agent spec has no [train] table, so it is not a recipe")
    return recipe_from_table(dict(spec.extra["train"]), spec.where)


def make_env(recipe: Recipe, *, training: bool = True, monitor_file: str | None = None) -> gym.Env:
    """The env of a recipe: the scenario, the observation design (with the curriculum only when
    ``training``), SB3's Monitor."""
    import aerial_loc_env.env  # noqa: F401  (registers the scenarios in subprocess workers)
    from aerial_loc_env.learning.observations import wrap

    env = gym.make(recipe.scenario, **recipe.scenario_overrides)
    env = wrap(env, recipe.observation, recipe.observation_params, recipe.reward,
               recipe.start_std_m if training else 0.0)
    monitor = require_extra("stable_baselines3.common.monitor", "rl", "Training")
    keys = EPISODE_KEYS if recipe.observation == "local_registration" else ()
    return monitor.Monitor(env, monitor_file, info_keywords=keys)


def _vec_env(recipe: Recipe, out: Path | None) -> Any:
    """The recipe's training envs, seeded ``seed, seed + 1, ...``, stepped as ``recipe.vec_env`` says
    (``recipes.VECTORIZATIONS``)."""
    vec = require_extra("stable_baselines3.common.vec_env", "rl", "Training")
    if out is not None:
        (out / "monitor").mkdir(parents=True, exist_ok=True)
    kind = recipe.vec_env

    def factory(rank: int):
        def make() -> gym.Env:
            if kind == "subproc":  # a worker process: one thread, the cores are shared
                import cv2

                cv2.setNumThreads(1)
            return make_env(recipe, monitor_file=str(out / "monitor" / str(rank)) if out else None)

        return make

    fns = [factory(i) for i in range(recipe.n_envs)]
    if kind == "vector":
        from aerial_loc_env.learning.vec_env import ShardVecEnv

        env = ShardVecEnv(fns)
    else:
        env = vec.SubprocVecEnv(fns) if kind == "subproc" else vec.DummyVecEnv(fns)
    env.seed(recipe.seed)
    return env


def policy_kwargs(recipe: Recipe) -> dict:
    """SB3 ``policy_kwargs`` of the recipe's network."""
    kwargs: dict = {"net_arch": list(recipe.policy.net_arch), "log_std_init": recipe.policy.log_std_init}
    if recipe.policy.cnn in ("paired", "correlation"):
        from aerial_loc_env.learning.networks import EXTRACTORS

        kwargs["features_extractor_class"] = EXTRACTORS[recipe.policy.cnn]
        kwargs["features_extractor_kwargs"] = {"features_dim": recipe.policy.features_dim}
        if recipe.policy.cnn == "correlation":
            kwargs["features_extractor_kwargs"].update(max_shift=recipe.policy.max_shift,
                                                       channels=recipe.policy.channels)
    else:
        kwargs["features_extractor_kwargs"] = {"cnn_output_dim": recipe.policy.features_dim}
    return kwargs


# ------------------------------------------------------------------------------------ evaluation
def evaluate(model: Any, recipe: Recipe, seeds: list[int], env: gym.Env | None = None) -> dict[str, float]:
    """Deterministic episodes on ``seeds``: mean return, pooled RMSE of the estimates (all steps of all
    episodes) and, for local registration, dead reckoning's pooled RMSE on the same episodes."""
    own = env is None
    env = env or make_env(recipe, training=False)
    sq: list[float] = []
    sq_dr: list[float] = []
    returns: list[float] = []
    try:
        for seed in seeds:
            obs, _info = env.reset(seed=int(seed))
            done, ret = False, 0.0
            while not done:
                action, _ = model.predict(obs, deterministic=True)
                obs, reward, terminated, truncated, info = env.step(action)
                ret += float(reward)
                sq.append(float(info["position_error_m"]) ** 2)
                if "dead_reckoning_error_m" in info:
                    sq_dr.append(float(info["dead_reckoning_error_m"]) ** 2)
                done = terminated or truncated
            returns.append(ret)
    finally:
        if own:
            env.close()
    out = {"mean_return": float(np.mean(returns)), "rmse_m": math.sqrt(float(np.mean(sq))),
           "episodes": len(seeds)}
    if sq_dr:
        out["dead_reckoning_rmse_m"] = math.sqrt(float(np.mean(sq_dr)))
    return out


def _eval_callback(recipe: Recipe, out: Path) -> Any:
    callbacks = require_extra("stable_baselines3.common.callbacks", "rl", "Training")

    class HeldOutEval(callbacks.BaseCallback):
        """Every ``eval_freq`` timesteps: ``evaluate`` on the held-out seeds, logged (eval/*), appended to
        eval.csv, and the best model (lowest RMSE) saved to best/model.zip."""

        def __init__(self) -> None:
            super().__init__()
            self.env = make_env(recipe, training=False)
            self.seeds = [recipe.eval_seed + k for k in range(recipe.eval_episodes)]
            self.best = math.inf
            self.last = -1
            self.csv_path = out / "eval.csv"
            self.t0 = time.monotonic()

        def _on_training_start(self) -> None:
            self.t0 = time.monotonic()
            self.last = self.num_timesteps
            self.best = _best_so_far(self.csv_path)
            if self.num_timesteps == 0:  # the untrained policy: where the learning curve starts
                self.run()

        def _on_step(self) -> bool:
            if self.num_timesteps - self.last >= recipe.eval_freq:
                self.run()
            return True

        def run(self) -> dict[str, float]:
            self.last = self.num_timesteps
            res = evaluate(self.model, recipe, self.seeds, self.env)
            for k, v in res.items():
                self.logger.record(f"eval/{k}", v)
            self.logger.dump(self.num_timesteps)
            row = {"timesteps": self.num_timesteps, "wall_s": round(time.monotonic() - self.t0, 1), **res}
            new = not self.csv_path.exists()
            with open(self.csv_path, "a", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=list(row))
                if new:
                    w.writeheader()
                w.writerow(row)
            if res["rmse_m"] < self.best:
                self.best = res["rmse_m"]
                (out / "best").mkdir(exist_ok=True)
                self.model.save(str(out / "best" / "model"))
            return res

        def _on_training_end(self) -> None:
            if self.last != self.num_timesteps:
                self.run()
            self.env.close()

    return HeldOutEval()


def _wall_budget_callback(max_wall_s: float) -> Any:
    callbacks = require_extra("stable_baselines3.common.callbacks", "rl", "Training")

    class WallBudget(callbacks.BaseCallback):
        """Stops training once ``max_wall_s`` seconds have passed since it started."""

        def _on_training_start(self) -> None:
            self.t0 = time.monotonic()

        def _on_step(self) -> bool:
            return time.monotonic() - self.t0 < max_wall_s

    return WallBudget()


def _best_so_far(csv_path: Path) -> float:
    if not csv_path.exists():
        return math.inf
    with open(csv_path, newline="") as fh:
        return min((float(r["rmse_m"]) for r in csv.DictReader(fh)), default=math.inf)


# ------------------------------------------------------------------------------------ training
@dataclass(frozen=True)
class TrainResult:
    model_path: Path
    out_dir: Path
    wall_time_s: float
    timesteps: int


def train(spec_name: str | os.PathLike, out_dir: str | os.PathLike | None = None, *, overwrite: bool = False,
          resume: str | os.PathLike | None = None, total_timesteps: int | None = None,
          progress_bar: bool = True, verbose: int = 0) -> TrainResult:
    """Train the recipe of agent spec ``spec_name`` (a name in agents/ or a TOML path) into ``out_dir``
    (default ``runs/<spec name>``). ``resume``: a checkpoint to continue from (its timesteps count towards
    the total). Refuses to replace an existing model unless ``overwrite``."""
    spec = load_spec(spec_name)
    recipe = recipe_of(spec)
    if total_timesteps is not None:
        if total_timesteps < 1:
            raise ConfigError(f"--timesteps must be >= 1, got {total_timesteps}")
        recipe = dataclasses.replace(recipe, total_timesteps=int(total_timesteps))
    out = Path(out_dir) if out_dir else Path("runs") / spec.name
    model_path = out / MODEL_FILE
    if model_path.exists() and not overwrite:
        raise ConfigError(f"model '{model_path}' already exists and would be overwritten; choose another "
                          "--out or pass --overwrite (with --resume to continue training it)")
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out '{out}' is a file, not a folder; choose a folder for the run (it is created "
                          "if missing)")
    if resume is not None and not Path(resume).is_file():
        raise ConfigError(f"--resume: checkpoint '{resume}' does not exist")
    if resume is not None:
        check_model_zip(resume, "--resume: checkpoint")
    if not resume and out.exists() and (out / "eval.csv").exists():
        if not overwrite:
            raise ConfigError(f"'{out}' holds an unfinished run (eval.csv, no model.zip); continue it with "
                              f"--resume {out}/checkpoints/<latest>.zip, or pass --overwrite to start afresh")
        (out / "eval.csv").unlink()
    out.mkdir(parents=True, exist_ok=True)
    # the spec as it was when training started (it may be edited while a long run goes on)
    spec_text = Path(spec.path).read_text() if spec.path is not None else None
    logger_mod = require_extra("stable_baselines3.common.logger", "rl", "Training")
    callbacks_mod = require_extra("stable_baselines3.common.callbacks", "rl", "Training")
    cls = algo_class(recipe.algo)
    if recipe.torch_threads > 0:
        require_extra("torch", "rl", "Training").set_num_threads(recipe.torch_threads)

    env = _vec_env(recipe, out)
    logger = None
    try:
        if resume is not None:
            model = cls.load(str(resume), env=env, device=recipe.device)
        else:
            model = cls("MultiInputPolicy", env, policy_kwargs=policy_kwargs(recipe), seed=recipe.seed,
                        device=recipe.device, verbose=verbose, **recipe.hyperparameters)
        done = int(model.num_timesteps)
        formats = ["csv"] + (["tensorboard"] if importlib.util.find_spec("tensorboard") else [])
        formats += ["stdout"] if verbose else []
        logger = logger_mod.configure(str(out / "logs"), formats)
        model.set_logger(logger)
        evaluator = _eval_callback(recipe, out)
        checkpoints = callbacks_mod.CheckpointCallback(max(recipe.checkpoint_freq // recipe.n_envs, 1),
                                                       str(out / "checkpoints"), name_prefix="model")
        use_bar = progress_bar and all(importlib.util.find_spec(m) for m in ("tqdm", "rich"))
        t0 = time.monotonic()
        remaining = max(recipe.total_timesteps - done, 0)
        if remaining:
            callbacks = [checkpoints, evaluator]
            if recipe.max_wall_s > 0:
                callbacks.append(_wall_budget_callback(recipe.max_wall_s))
            model.learn(remaining, callback=callbacks, progress_bar=use_bar,
                        reset_num_timesteps=resume is None)
        wall = time.monotonic() - t0
        tmp = out / ".model.tmp.zip"
        model.save(str(tmp))
        os.replace(tmp, model_path)
    finally:
        try:
            env.close()
        finally:
            if logger is not None:      # its files (progress.csv, the event files) closed, not left to the collector
                logger.close()
    if spec_text is not None:
        (out / "recipe.toml").write_text(spec_text)
    scenario = scenario_spec(recipe)
    (out / "scenario.json").write_text(json.dumps(scenario, indent=2, default=str))
    meta = {"spec": spec.name, "recipe": recipe_to_dict(recipe), "timesteps": int(model.num_timesteps),
            "resumed_from": str(resume) if resume else None, "resumed_at_timesteps": done,
            "wall_time_s": round(wall, 1), "machine": training_machine(), "versions": training_versions(),
            "best_eval_rmse_m": _best_so_far(out / "eval.csv"), "scenario": scenario}
    (out / "training.json").write_text(json.dumps(meta, indent=2, default=str))
    if (out / "best" / MODEL_FILE).is_file():  # the best model loads as an agent too
        for name in ("training.json", "recipe.toml", "scenario.json"):
            if (out / name).is_file():
                shutil.copyfile(out / name, out / "best" / name)
    return TrainResult(model_path, out, wall, int(model.num_timesteps))


def check_model_zip(path: str | os.PathLike, what: str) -> None:
    """Refuse a file that is not a complete SB3 model zip (truncated download, wrong file) with a clear error,
    before SB3 fails on it with a bare AssertionError or BadZipFile."""
    import zipfile

    problem = None
    try:
        with zipfile.ZipFile(path) as zf:
            names = set(zf.namelist())
            bad = zf.testzip()
        if bad is not None:
            problem = f"member {bad!r} fails its CRC check"
        elif not {"data", "policy.pth"} <= names:
            problem = f"it lacks {sorted({'data', 'policy.pth'} - names)}"
    except (zipfile.BadZipFile, OSError, EOFError) as exc:
        problem = f"{type(exc).__name__}: {exc}"
    if problem is not None:
        raise ConfigError(f"{what} '{path}' is not a model saved by stable-baselines3 ({problem}): the file is "
                          "truncated or corrupt; copy it again, or use another checkpoint")


def scenario_spec(recipe: Recipe) -> dict:
    """The resolved scenario spec the model was trained on (saved beside the model)."""
    from aerial_loc_env.env.scenarios import scenario_spec_dict

    return scenario_spec_dict(recipe.scenario, **recipe.scenario_overrides)


def training_machine() -> str:
    """The machine and torch's thread count, as a training run's record names them."""
    from aerial_loc_env.sysinfo import machine

    return f"{machine()}, torch threads {require_extra('torch', 'rl', 'Training').get_num_threads()}"


def training_versions() -> dict[str, str]:
    """The versions a trained model depends on, as a training run's record names them."""
    import stable_baselines3
    import torch

    from aerial_loc_env.version import __version__

    return {"aerial_loc_env": __version__, "stable_baselines3": stable_baselines3.__version__,
            "torch": torch.__version__, "gymnasium": gym.__version__, "python": platform.python_version()}


def load_training_meta(model_path: str | os.PathLike) -> tuple[Recipe, dict]:
    """The recipe (and the whole training.json) saved beside a model by ``train``."""
    model_path = Path(model_path)
    meta_path = model_path.parent / "training.json"
    if not meta_path.is_file():
        raise ConfigError(f"learned agent: '{meta_path}' (written by `aerial-loc train` beside the model) is "
                          "missing, so the model's observation design is unknown; retrain or restore it")
    try:
        meta = json.loads(meta_path.read_text())
        table = meta["recipe"]
    except (OSError, ValueError, KeyError) as exc:
        raise ConfigError(f"'{meta_path}': not a readable training.json with a 'recipe': {exc}") from exc
    return recipe_from_table(table, str(meta_path), check_scenario=False), meta
