"""The measurement-model plug-in of the MCL core: p(z | x, m) as log-likelihoods over all particles at once.

A model is reset once per episode with the briefing (per-map precomputation), prepares each camera frame once
(``prepare``: descriptors, shadow masks, anything that does not depend on the particle), then scores every
particle in one vectorized call (``log_likelihood``). Log-likelihoods only need to be right up to a constant
shared by all particles of a frame; the core normalizes them. Keep ``prepare`` free of particle loops and
``log_likelihood`` free of Python loops over particles.

Write a new model (SSD, NCC, MI, abBRIEF, edges, ...) by subclassing ``MeasurementModel`` with a frozen
``Config`` dataclass and registering it in ``MODELS`` with ``register_model`` so that MCL specs can name it.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError

if TYPE_CHECKING:
    from aerial_loc_env.env.briefing import Briefing


class MeasurementModel(ABC):
    """Base class of the MCL measurement models.

    ``Config`` is the frozen dataclass of the model's parameters (``None`` for none); ``uses_ground_truth``
    marks oracles (the agent then asks the runner for ``info``). ``last_stats`` holds per-frame figures for
    the reports, e.g. ``{"K": 70, "shadow_pairs": 12}``.
    """

    Config: ClassVar[type | None] = None
    uses_ground_truth: bool = False

    def __init__(self, config: Any = None) -> None:
        self.config = config
        self.last_stats: dict[str, Any] = {}

    @abstractmethod
    def reset(self, briefing: Briefing, rng: np.random.Generator) -> None:
        """Per-episode (per-map) precomputation."""

    @abstractmethod
    def prepare(self, observation: Mapping[str, np.ndarray], rng: np.random.Generator,
                info: Mapping[str, Any] | None = None) -> object:
        """Per-frame work on the camera image, done once for all particles; returns what
        ``log_likelihood`` needs. ``info`` is given only when ``uses_ground_truth`` is True."""

    @abstractmethod
    def log_likelihood(self, prepared: object, states: np.ndarray, altitude_m: float) -> np.ndarray:
        """``states`` (N, 3) = [x_m, y_m, yaw_rad] -> (N,) float64 log-likelihoods (up to a constant)."""


#: name -> factory(config mapping, where) for the models an MCL spec can name in ``measurement = "..."``
MODELS: dict[str, Callable[[Mapping[str, Any], str], MeasurementModel]] = {}


def register_model(name: str, cls: type[MeasurementModel], **defaults: Any) -> None:
    """Make ``cls`` (with ``defaults`` under the spec's own keys) available to MCL specs as ``name``."""
    if name in MODELS:
        raise ConfigError(f"measurement model {name!r} is already registered")

    def factory(mapping: Mapping[str, Any], where: str) -> MeasurementModel:
        merged = {**defaults, **dict(mapping)}
        if cls.Config is None:
            if merged:
                raise ConfigError(f"{where}: measurement model {name!r} takes no parameters, "
                                  f"got {sorted(merged)}")
            return cls()
        return cls(build_config(cls.Config, merged, where=where))

    MODELS[name] = factory


#: modules imported (late, to avoid cycles) to register the built-in models
BUILTIN_MODULES: tuple[str, ...] = ("aerial_loc_env.estimators.mcl.intensity_pairs",
                                    "aerial_loc_env.estimators.mcl.dense",
                                    "aerial_loc_env.estimators.mcl.abbrief",
                                    "aerial_loc_env.estimators.mcl.edges")


def make_model(name: str, mapping: Mapping[str, Any] | None = None, *,
               where: str = "measurement") -> MeasurementModel:
    """Build the measurement model ``name``: a registered name, or a dotted path ``package.module:Class``."""
    import importlib

    for module in BUILTIN_MODULES:
        importlib.import_module(module)
    if name not in MODELS and ":" in name:
        from aerial_loc_env.estimators.registry import resolve_dotted

        cls = resolve_dotted(name, where=where)
        if not (isinstance(cls, type) and issubclass(cls, MeasurementModel)):
            raise ConfigError(f"{where}: {name!r} is not a MeasurementModel subclass")
        register_model(name, cls)
    if name not in MODELS:
        raise ConfigError(f"{where}: unknown measurement model {name!r}; known: {', '.join(sorted(MODELS))} "
                          "(or give a dotted path 'package.module:Class')")
    return MODELS[name](mapping or {}, where)
