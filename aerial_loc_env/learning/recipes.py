"""Training recipes: the ``[train]`` table of an agent spec (in the spirit of the RL Zoo's hyperparameters).

A recipe names the algorithm, the scenario it trains on, the observation design, the reward, the
hyperparameters, the policy network and the budget. Unknown keys and out-of-range values are clear errors
naming the spec file and table::

    class = "LearnedAgent"
    [params]
    model = "models/ppo-local-registration/model.zip"   # relative to the package (see agent.py)
    [train]
    algo = "PPO"                       # or "SAC"
    scenario = "AerialLoc/Small-v3"
    observation = "local_registration" # or "map_memorization"
    total_timesteps = 200000
    n_envs = 2
    vectorization = "vector"           # or "subproc", "dummy" (see VECTORIZATIONS)
    [train.observation_params]
    image_px = 64
    [train.reward]                     # local_registration only
    kind = "improvement"
    [train.hyperparameters]            # passed to the SB3 algorithm (names checked against its signature)
    n_steps = 256
    [train.policy]                     # policy network
    net_arch = [128, 128]
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from aerial_loc_env.config import build_config, config_to_dict, rng
from aerial_loc_env.env.scenarios import load_scenario
from aerial_loc_env.errors import ConfigError, require_extra

ALGOS = ("PPO", "SAC")
OBSERVATIONS = ("local_registration", "map_memorization")
REWARDS = ("improvement", "error")
#: how the training envs are stepped: ``vector`` (``learning.vec_env.ShardVecEnv``: one process per core, the
#: learner's included), ``subproc`` (SB3's SubprocVecEnv: one process per env), ``dummy`` (SB3's DummyVecEnv: all
#: in the learner's process). ``vector`` and ``subproc`` give the same model for the same seed; ``dummy`` may differ
#: in the last bits (its rewards are float32).
VECTORIZATIONS = ("vector", "subproc", "dummy")
DEFAULT_VECTORIZATION = "vector"
#: SB3 constructor arguments the recipe sets through its own fields, never through [train.hyperparameters]
_RESERVED = {"self", "policy", "env", "policy_kwargs", "seed", "device", "tensorboard_log", "verbose",
             "_init_setup_model"}


@dataclass(frozen=True)
class ObservationParams:
    """How the policy sees the world (see observations.py)."""

    image_px: int = field(default=64, metadata=rng(16, 256, doc="square side of the policy's images"))
    grayscale: bool = False
    max_correction_m: float = field(default=6.0, metadata=rng(0.1, 500.0, lo_open=True,
                                                                doc="largest correction per step (metres)"))


@dataclass(frozen=True)
class RewardParams:
    """The training reward of the local-registration wrapper (see observations.py)."""

    kind: str = field(default="improvement", metadata=rng(choices=REWARDS))
    scale_m: float = field(default=5.0, metadata=rng(0.01, 1000.0, doc="metres per unit of reward"))
    error_weight: float = field(default=0.1, metadata=rng(0.0, 100.0, doc="weight of the remaining error"))


@dataclass(frozen=True)
class PolicyParams:
    """The policy network: SB3 ``net_arch`` after the features extractor: ``correlation`` (siamese CNN +
    cost volume) or ``paired`` (stacked channels) for local registration (networks.py), else SB3's
    ``nature``."""

    net_arch: tuple[int, ...] = (128, 128)
    features_dim: int = field(default=256, metadata=rng(8, 4096))
    cnn: str = field(default="correlation", metadata=rng(choices=("correlation", "paired", "nature")))
    max_shift: int = field(default=6, metadata=rng(1, 32, doc="correlation: shifts searched (feature px)"))
    channels: int = field(default=32, metadata=rng(2, 256, doc="correlation: feature channels compared"))
    log_std_init: float = field(default=-1.0, metadata=rng(-10.0, 2.0, doc=(
        "initial log std of the Gaussian policy: exploration noise in action units (1 = max correction)")))

    def validate(self, where: str) -> None:
        if not self.net_arch or any(isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 4096
                                    for n in self.net_arch):
            raise ConfigError(f"{where}: field 'net_arch' = {list(self.net_arch)!r} must be a non-empty list "
                              "of layer widths, integers in [1, 4096]")


@dataclass(frozen=True)
class Recipe:
    """One training run: what to train, on what, for how long, and how to evaluate it."""

    algo: str = field(default="PPO", metadata=rng(choices=ALGOS))
    scenario: str = "AerialLoc/Small-v3"
    scenario_overrides: dict = field(default_factory=dict)
    observation: str = field(default="local_registration", metadata=rng(choices=OBSERVATIONS))
    observation_params: ObservationParams = ObservationParams()
    reward: RewardParams = RewardParams()
    start_std_m: float = field(default=0.0, metadata=rng(0.0, 1000.0, doc=(
        "training only: if > 0, start the estimate at N(truth, std^2) instead of the prior's mean")))
    hyperparameters: dict = field(default_factory=dict)
    policy: PolicyParams = PolicyParams()
    total_timesteps: int = field(default=200_000, metadata=rng(1, 10**9))
    max_wall_s: float = field(default=0.0, metadata=rng(0.0, 10**7, doc=(
        "stop training after this wall time (seconds; 0 = no limit): a budget that holds on any machine")))
    n_envs: int = field(default=2, metadata=rng(1, 256))
    vectorization: str | None = field(default=None, metadata=rng(choices=VECTORIZATIONS, doc=(
        "how the n_envs envs are stepped (VECTORIZATIONS); unset: from subproc, else DEFAULT_VECTORIZATION")))
    subproc: bool | None = None      # the older spelling: true = "subproc", false = "dummy"
    seed: int = field(default=0, metadata=rng(0, 2**31 - 1))
    eval_freq: int = field(default=10_000, metadata=rng(1, 10**9, doc="timesteps between evaluations"))
    eval_episodes: int = field(default=4, metadata=rng(1, 1000))
    eval_seed: int = field(default=10_000, metadata=rng(0, 2**31 - 1, doc="first held-out evaluation seed"))
    checkpoint_freq: int = field(default=50_000, metadata=rng(1, 10**9))
    device: str = field(default="cpu", metadata=rng(choices=("cpu", "cuda", "auto")))
    torch_threads: int = field(default=1, metadata=rng(0, 256, doc=(
        "torch intra-op threads of the learner (0 = torch's default); 1 beats 2 by 2.5x on 2 busy cores")))

    @property
    def vec_env(self) -> str:
        """The vectorization in effect (``vectorization``, else the older ``subproc``, else the default)."""
        if self.vectorization is not None:
            return self.vectorization
        if self.subproc is not None:
            return "subproc" if self.subproc and self.n_envs > 1 else "dummy"
        return DEFAULT_VECTORIZATION

    def validate(self, where: str) -> None:
        if self.subproc is not None and self.vectorization is not None \
                and self.vectorization != ("subproc" if self.subproc else "dummy"):
            raise ConfigError(f"{where}: 'subproc' = {str(self.subproc).lower()} and 'vectorization' = "
                              f"{self.vectorization!r} disagree; subproc is the older spelling of vectorization = "
                              "'subproc' (true) or 'dummy' (false): keep only vectorization")
        if self.eval_seed < self.seed + self.n_envs:
            raise ConfigError(f"{where}: field 'eval_seed' = {self.eval_seed} overlaps the training seeds "
                              f"[{self.seed}, {self.seed + self.n_envs}); evaluation needs held-out seeds")
        for key in ("scenario_overrides", "hyperparameters"):
            if not isinstance(getattr(self, key), Mapping):
                raise ConfigError(f"{where}: '{key}' must be a table")


_NESTED = {"observation_params": ObservationParams, "reward": RewardParams, "policy": PolicyParams}


def recipe_from_table(table: Mapping[str, Any], where: str, *, check_scenario: bool = True) -> Recipe:
    """Build a Recipe from a spec's [train] table, validating nested tables and the SB3 hyperparameters.

    ``check_scenario=False`` for a trained model's saved recipe: its scenario records what the model was trained
    on (possibly an id's older version) and is not built when the model runs."""
    if not isinstance(table, Mapping):
        raise ConfigError(f"{where}: [train] must be a table")
    table = dict(table)
    nested: dict[str, Any] = {}
    for key, cls in _NESTED.items():
        raw = table.pop(key, {})
        if not isinstance(raw, Mapping):
            raise ConfigError(f"{where}: [train.{key}] must be a table, got {raw!r}")
        nested[key] = build_config(cls, raw, where=f"{where} [train.{key}]")
    recipe = build_config(Recipe, table, where=f"{where} [train]")
    recipe = dataclasses.replace(recipe, **nested)
    if recipe.policy.cnn != "nature" and recipe.observation != "local_registration":
        raise ConfigError(f"{where} [train.policy]: cnn = '{recipe.policy.cnn}' compares the camera image "
                          "with the database crop, which only the local_registration observation has; use "
                          f"cnn = 'nature' for {recipe.observation}")
    if recipe.policy.cnn == "nature" and recipe.observation_params.image_px < 36:
        raise ConfigError(f"{where} [train.observation_params]: image_px = "
                          f"{recipe.observation_params.image_px} is too small for SB3's nature CNN "
                          "(8x8/4, 4x4/2, 3x3/1 needs >= 36 px)")
    check_hyperparameters(recipe, where)
    if not check_scenario:
        return recipe
    try:   # here, not after the workers' start inside a subprocess
        load_scenario(recipe.scenario, recipe.scenario_overrides)
    except ConfigError as exc:
        raise ConfigError(f"{where} [train]: scenario = {recipe.scenario!r} with scenario_overrides "
                          f"{dict(recipe.scenario_overrides)}: {exc}") from None
    return recipe


def algo_class(name: str) -> type:
    """The SB3 algorithm class (stable-baselines3 is the optional extra ``rl``)."""
    sb3 = require_extra("stable_baselines3", "rl", "Training and running learned policies")
    return getattr(sb3, name)


def check_hyperparameters(recipe: Recipe, where: str) -> None:
    """Refuse hyperparameters the SB3 algorithm does not take (a typo would otherwise be silently ignored)."""
    cls = algo_class(recipe.algo)
    allowed = set(inspect.signature(cls.__init__).parameters) - _RESERVED
    unknown = sorted(set(recipe.hyperparameters) - allowed)
    if unknown:
        raise ConfigError(f"{where} [train.hyperparameters]: {recipe.algo} has no parameter(s) {unknown}; "
                          f"allowed: {', '.join(sorted(allowed))}")
    params = inspect.signature(cls.__init__).parameters
    for key, value in recipe.hyperparameters.items():
        if isinstance(value, Mapping) and key != "replay_buffer_kwargs":
            raise ConfigError(f"{where} [train.hyperparameters]: '{key}' must be a value, not a table")
        _check_hyperparameter(key, value, params[key].annotation, f"{where} [train.hyperparameters]")
    if recipe.algo == "PPO":
        n_steps = int(recipe.hyperparameters.get("n_steps", params["n_steps"].default))
        if n_steps * recipe.n_envs < 2:
            raise ConfigError(f"{where} [train.hyperparameters]: PPO needs n_steps * n_envs > 1 "
                              f"(got {n_steps} * {recipe.n_envs}); raise n_steps")


#: value ranges of the SB3 hyperparameters (lo, hi, lo_open); SB3 itself fails late or not at all on these
HYPER_RANGES: dict[str, tuple[float | None, float | None, bool]] = {
    "learning_rate": (0.0, None, True), "n_steps": (1, None, False), "batch_size": (1, None, False),
    "n_epochs": (1, None, False), "gamma": (0.0, 1.0, False), "gae_lambda": (0.0, 1.0, False),
    "clip_range": (0.0, None, True), "clip_range_vf": (0.0, None, True), "ent_coef": (0.0, None, False),
    "vf_coef": (0.0, None, False), "max_grad_norm": (0.0, None, True), "target_kl": (0.0, None, True),
    "buffer_size": (1, None, False), "learning_starts": (0, None, False), "tau": (0.0, 1.0, False),
    "stats_window_size": (1, None, False), "target_update_interval": (1, None, False),
    "sde_sample_freq": (-1, None, False), "train_freq": (1, None, False),
}


def _check_hyperparameter(key: str, value: Any, annotation: Any, where: str) -> None:
    """``value`` against the SB3 signature's type (int, float, bool, str) and HYPER_RANGES."""
    text = str(annotation)
    takes = {t for t in ("int", "float", "bool", "str", "None", "tuple", "dict") if t in text}
    if annotation in (int, float, bool, str):
        takes = {annotation.__name__}
    if key == "ent_coef" and "str" in takes and isinstance(value, str):
        if value != "auto" and not value.startswith("auto_"):
            raise ConfigError(f"{where}: '{key}' = {value!r} must be a number >= 0, 'auto' or 'auto_<init>'")
        return
    if isinstance(value, bool):
        ok = "bool" in takes
    elif isinstance(value, int):
        ok = bool(takes & {"int", "float"})
    elif isinstance(value, float):
        ok = "float" in takes
    elif isinstance(value, str):
        ok = "str" in takes
    else:
        ok = isinstance(value, list) and "tuple" in takes or isinstance(value, Mapping) and "dict" in takes
    if not ok and takes & {"int", "float", "bool", "str"}:
        kind = ("an integer" if takes & {"int", "float"} == {"int"} else "a number") \
            if takes & {"int", "float"} else ("true or false" if "bool" in takes else "a string")
        raise ConfigError(f"{where}: '{key}' = {value!r} must be {kind}")
    if key in HYPER_RANGES and isinstance(value, (int, float)) and not isinstance(value, bool):
        lo, hi, lo_open = HYPER_RANGES[key]
        bad = lo is not None and (value <= lo if lo_open else value < lo) or hi is not None and value > hi
        if bad or value != value:
            allowed = f"in [{lo:g}, {hi:g}]" if hi is not None else f"{'>' if lo_open else '>='} {lo:g}"
            raise ConfigError(f"{where}: '{key}' = {value!r} is out of range; it must be {allowed}")


def recipe_to_dict(recipe: Recipe) -> dict:
    """The recipe as a plain dict that ``recipe_from_table`` reads back (saved in training.json)."""
    return config_to_dict(recipe)
