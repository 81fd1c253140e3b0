"""The learned agent (``learning/agent.py``): like every agent kind, it refuses frames of another scenario than
the one whose briefing it was reset with, instead of answering 'ok' with a camera model that does not fit."""

from __future__ import annotations

import shutil
import zipfile

import gymnasium as gym
import pytest
from shared_helpers import REPO_ROOT

import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.errors import ConfigError

pytest.importorskip("stable_baselines3")
pytest.importorskip("torch")

from aerial_loc_env.estimators.registry import make_agent  # noqa: E402


@pytest.fixture(scope="module")
def briefed():
    """The shipped model reset with Small-v3's briefing, and that env's first observation."""
    env = gym.make("AerialLoc/Small-v3")
    obs, _ = env.reset(seed=0)
    agent = make_agent("ppo-local-registration")
    agent.reset(env.unwrapped.briefing, seed=0)
    yield agent, env, obs
    env.close()


def _first_frame(**overrides):
    env = gym.make("AerialLoc/Small-v3", **overrides)
    obs, _ = env.reset(seed=0)
    env.close()
    return obs


def test_frames_of_the_briefed_scenario_are_estimated(briefed) -> None:
    agent, _env, obs = briefed
    assert agent.step(obs).status == "ok"


def test_frames_of_another_camera_are_refused(briefed) -> None:
    agent, _env, _obs = briefed
    with pytest.raises(ConfigError, match=r"48 x 32 px but the briefing's camera \(AerialLoc/Small-v3\) is 64 x 64"):
        agent.step(_first_frame(observation={"width_px": 48, "height_px": 32}))


def test_frames_of_another_altitude_are_refused(briefed) -> None:
    agent, _env, _obs = briefed
    with pytest.raises(ConfigError, match=r"altitude 2\d\d\.\d m is outside the 50\.0-200\.0 m LearnedAgent"):
        agent.step(_first_frame(altitude_m=230.0))


def test_truncated_model_zip_is_a_clear_error(tmp_path):
    pytest.importorskip("stable_baselines3")
    src = REPO_ROOT / "aerial_loc_env" / "models" / "ppo-local-registration"
    if not (src / "model.zip").is_file():
        pytest.skip("the shipped model is absent")
    shutil.copy(src / "training.json", tmp_path / "training.json")
    data = (src / "model.zip").read_bytes()
    (tmp_path / "model.zip").write_bytes(data[: len(data) // 2])
    with pytest.raises(ConfigError, match=r"model\.zip.*(truncated|corrupt)"):
        make_agent("ppo-local-registration", model=str(tmp_path / "model.zip"))
    with zipfile.ZipFile(src / "model.zip") as zin, zipfile.ZipFile(tmp_path / "m2.zip", "w") as zout:
        for item in zin.infolist():
            if item.filename != "policy.pth":
                zout.writestr(item, zin.read(item.filename))
    shutil.copy(tmp_path / "m2.zip", tmp_path / "model.zip")
    with pytest.raises(ConfigError, match=r"model\.zip"):
        make_agent("ppo-local-registration", model=str(tmp_path / "model.zip"))
