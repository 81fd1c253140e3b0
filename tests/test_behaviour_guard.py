"""The behaviour guard: digests of what every registered scenario renders and what every shipped agent estimates.

A refactoring (files moved, kernels renamed, the world assembled elsewhere) must leave frames, measurements and
estimates bit-identical. The digests in ``tests/data/behaviour_digests.json`` were written by this file's main;
a deliberate change of the world, the renderer or an agent writes them again (``python tests/test_behaviour_guard.py``)
in the same commit that bumps the ids it changes.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

DIGESTS = Path(__file__).parent / "data" / "behaviour_digests.json"
#: every registered id that needs no user file, flown for two seconds (three frames hashed), otherwise as shipped
SCENARIOS = ("AerialLoc/PaperShadows-v2", "AerialLoc/PaperNoShadows-v2", "AerialLoc/GlobalLocalization-v2",
             "AerialLoc/CloudShadows-v2", "AerialLoc/MavicPro-v2", "AerialLoc/Small-v3",
             "AerialLoc/RealisticPaper-v3", "AerialLoc/SeasonChange-v3", "AerialLoc/Downtown-v3",
             "AerialLoc/Crosswind-v3")
#: every shipped classical agent spec on the paper's camera for 4 s (oracles get the shadow mask)
AGENT_SCENARIO = {"id": "AerialLoc/PaperShadows-v2",
                  "overrides": {"flight.duration_s": 4.0, "observation.info_shadow_mask": True}}
#: the learned agents with weights in the package, on the scenario they were trained for (the other learned
#: specs point at models a user trains)
SHIPPED_MODELS = {"ppo-local-registration": {"id": "AerialLoc/Small-v3", "overrides": {"flight.duration_s": 4.0}}}


def _hash_obs(h, obs: dict, info: dict) -> None:
    for key in sorted(obs):
        h.update(key.encode())
        h.update(np.ascontiguousarray(obs[key]).tobytes())
    h.update(np.asarray(info["true_pose"], np.float64).tobytes())


def scenario_digest(env_id: str) -> str:
    import gymnasium as gym

    import aerial_loc_env  # noqa: F401

    h = hashlib.sha256()
    env = gym.make(env_id, **{"flight.duration_s": 2.0})
    obs, info = env.reset(seed=3)
    _hash_obs(h, obs, info)
    briefing = env.unwrapped.briefing            # what agents are handed: the database and the prior
    h.update(np.ascontiguousarray(briefing.orthomap.rgb).tobytes())
    h.update(repr(briefing.prior).encode())
    for _ in range(2):
        obs, _r, _te, _tr, info = env.step(np.zeros(2, np.float32))
        _hash_obs(h, obs, info)
    env.close()
    return h.hexdigest()


def agent_names() -> list[str]:
    from aerial_loc_env.estimators.registry import list_specs

    return sorted(s.name for s in list_specs() if s.class_ref != "LearnedAgent") + sorted(SHIPPED_MODELS)


def agent_digest(name: str) -> str:
    import gymnasium as gym

    import aerial_loc_env  # noqa: F401
    from aerial_loc_env.estimators.episode import EpisodeDriver
    from aerial_loc_env.estimators.registry import make_agent

    where = SHIPPED_MODELS.get(name, AGENT_SCENARIO)
    env = gym.make(where["id"], **where["overrides"])
    h = hashlib.sha256()
    with EpisodeDriver(env, [make_agent(name)]) as driver:
        for record in driver.run(5):
            est = record.estimates[0]
            h.update(np.asarray([est.x_m, est.y_m], np.float64).tobytes())
    env.close()
    return h.hexdigest()


def _digests() -> dict[str, dict[str, str]]:
    return {"scenarios": {s: scenario_digest(s) for s in SCENARIOS},
            "agents": {a: agent_digest(a) for a in agent_names()}}


def _expected() -> dict[str, dict[str, str]]:
    return json.loads(DIGESTS.read_text())


@pytest.mark.parametrize("env_id", SCENARIOS)
def test_scenario_frames_unchanged(env_id):
    assert scenario_digest(env_id) == _expected()["scenarios"][env_id], (
        f"{env_id} renders other frames than {DIGESTS.name} records: bump the id and rewrite the digests")


def test_every_agent_has_a_digest():
    assert sorted(_expected()["agents"]) == sorted(agent_names())


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(json.loads(DIGESTS.read_text())["agents"]) if DIGESTS.exists() else [])
def test_agent_estimates_unchanged(name):
    assert agent_digest(name) == _expected()["agents"][name], (
        f"agent {name} estimates other positions than {DIGESTS.name} records")


if __name__ == "__main__":
    DIGESTS.write_text(json.dumps(_digests(), indent=1, sort_keys=True) + "\n")
    print(f"wrote {DIGESTS}", file=sys.stderr)
