"""Layer 3: the Gymnasium environment, the agent briefing, the scenario specs and wrappers.

Importing this package registers every scenario of ``envs/`` with Gymnasium (``AerialLoc/<Name>-v<N>``): a
module of the package that needs the ids imports ``aerial_loc_env.env`` (the package root does too, so
``import aerial_loc_env`` is enough for a user). Then ``gym.make("AerialLoc/PaperShadows-v2", altitude_m=150)``.
``world_to_action`` / ``action_to_world`` convert metres <-> the normalized action; ``env.unwrapped.briefing`` is
what an estimator may know.
"""

from aerial_loc_env.env.aerial_loc_env import AerialLocEnv, InvalidActionError, action_to_world, world_to_action
from aerial_loc_env.env.briefing import Briefing, OdometryNoise, Prior
from aerial_loc_env.env.scenarios import Scenario, load_scenario, register_all, scenario_spec_dict
from aerial_loc_env.env.wrappers import EpisodeErrorStats, MetresAction

__all__ = ["AerialLocEnv", "Briefing", "EpisodeErrorStats", "InvalidActionError", "MetresAction", "OdometryNoise",
           "Prior", "Scenario", "action_to_world", "load_scenario", "register_all", "scenario_spec_dict",
           "world_to_action"]

register_all()
