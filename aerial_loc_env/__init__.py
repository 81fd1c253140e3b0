"""aerial_loc_env: a Gymnasium benchmark for image-based absolute localization of drones without GNSS.

Importing the package registers the scenarios of ``envs/`` with Gymnasium (``AerialLoc/<Name>-v<N>``), so
``import aerial_loc_env; gym.make("AerialLoc/PaperShadows-v2")`` works; so does
``gym.make("aerial_loc_env:AerialLoc/PaperShadows-v2")`` without the explicit import.

The public API, one import deep (``import aerial_loc_env as ale``):

- ``Briefing``: what an agent may know of an episode (``env.unwrapped.briefing``);
- ``world_to_action`` / ``action_to_world``: world metres <-> the env's normalized action; ``MetresAction``: a
  wrapper whose action is the estimate in world metres;
- ``Agent``, ``Estimate``: the agent protocol; ``make_agent("mcl-shadow-aware")``: an agent from its spec
  (``agents/<name>.toml``), a dotted class path or an ``Agent`` subclass;
- ``EpisodeDriver``: the one loop that runs agents on episodes of an env (one record per frame);
- ``run_experiment``, ``make_grid``: the benchmark (``aerial-loc bench`` from Python).

The package root is the top layer (docs/ARCHITECTURE.md): the env's names are imported here, the layers above
the env (estimators, benchmark) only when one of their names is first used, so that importing a lower module
(``aerial_loc_env.world``) never loads them.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from aerial_loc_env.env import Briefing, MetresAction, action_to_world, world_to_action  # registers the ids
from aerial_loc_env.version import __version__

if TYPE_CHECKING:  # the names loaded on first use (below); listed here for type checkers and the layer test
    from aerial_loc_env.benchmark import make_grid, run_experiment
    from aerial_loc_env.estimators.episode import EpisodeDriver
    from aerial_loc_env.estimators.protocol import Agent, Estimate
    from aerial_loc_env.estimators.registry import make_agent

#: name -> the module that defines it, imported on first use (PEP 562)
_LAZY: dict[str, str] = {
    "Agent": "aerial_loc_env.estimators.protocol",
    "Estimate": "aerial_loc_env.estimators.protocol",
    "EpisodeDriver": "aerial_loc_env.estimators.episode",
    "make_agent": "aerial_loc_env.estimators.registry",
    "make_grid": "aerial_loc_env.benchmark",
    "run_experiment": "aerial_loc_env.benchmark",
}

__all__ = ["Agent", "Briefing", "EpisodeDriver", "Estimate", "MetresAction", "__version__", "action_to_world",
           "make_agent", "make_grid", "run_experiment", "world_to_action"]


def __getattr__(name: str) -> Any:
    """A name of the layers above the env, imported on its first use."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'aerial_loc_env' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value   # later lookups skip this function
    return value


def __dir__() -> list[str]:
    """The public names (``dir(ale)``, tab completion), the lazy ones included."""
    return sorted(__all__)
