"""The learned-registration policy (learning/surface.py, learning/surface_train.py): the observation's geometry, the
NumPy twin of the SB3 network, the shipped policy without torch, and the recipe end to end on a tiny budget."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env.env  # noqa: F401
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.dead_reckoning import DeadReckoningAgent
from aerial_loc_env.learning.surface import (
    DEFAULT_POLICY,
    SurfaceParams,
    SurfaceRegistration,
    conv2d,
    load_policy,
    write_policy,
)

REPO = Path(__file__).resolve().parents[2]
SHORT = {"flight.duration_s": 3.0}


def test_grid_rows_go_north_and_columns_east() -> None:
    p = SurfaceParams(half_cells=2, step_m=1.5)
    g = p.grid_m().reshape(p.side, p.side, 2)
    assert g.shape == (5, 5, 2)
    np.testing.assert_allclose(g[2, 2], [0.0, 0.0])
    np.testing.assert_allclose(g[2, 4], [3.0, 0.0])    # column +2: 3 m east
    np.testing.assert_allclose(g[0, 2], [0.0, -3.0])   # row 0: 3 m south of the centre row's north offset 0
    assert np.all(np.diff(g[:, 0, 1]) > 0) and np.all(np.diff(g[0, :, 0]) > 0)


def test_zero_correction_is_dead_reckoning_and_corrections_are_east_north() -> None:
    env = gym.make("AerialLoc/RealisticPaper-v3", **SHORT)
    obs, _ = env.reset(seed=2)
    briefing = env.unwrapped.briefing
    core, dr = SurfaceRegistration(SurfaceParams(half_cells=3)), DeadReckoningAgent()
    core.reset(briefing)
    dr.reset(briefing)
    for _ in range(4):
        surface = core.observe(obs)
        assert surface.shape == (1, 7, 7) and surface.dtype == np.float32
        assert np.all(surface >= -1.0) and np.all(surface <= 1.0)
        est = dr.step(obs)
        np.testing.assert_allclose(core.correct(np.zeros(2)), [est.x_m, est.y_m])
        obs, *_ = env.step(np.zeros(2, np.float32))
    core.observe(obs)
    before = core.predicted.copy()
    np.testing.assert_allclose(core.correct([0.5, -0.25]) - before, [20.0, -10.0])    # 40 m per unit, (east, north)
    env.close()


def test_the_surface_peaks_at_the_true_position_on_a_simulated_frame() -> None:
    """The encoder's surface around a prediction offset from the truth peaks near the offset that undoes it (the
    policy's cue); on the paper's gap-free scene with the shipped encoder, at three offsets."""
    env = gym.make("AerialLoc/PaperNoShadows-v2", **SHORT)
    obs, info = env.reset(seed=1)
    core = SurfaceRegistration(SurfaceParams(half_cells=8))
    core.reset(env.unwrapped.briefing)
    core.prepare(obs)
    truth = np.asarray(info["true_pose"][:2])
    offsets = np.array([[7.5, -5.0], [-10.0, 0.0], [0.0, 12.5]])
    for off, s in zip(offsets, core.surfaces(truth + offsets), strict=True):
        i, j = np.unravel_index(int(np.argmax(s)), s.shape)
        found = (np.array([j, i]) - 8) * 2.5
        assert np.hypot(*(found + off)) <= 2.5 * math.sqrt(2) + 1e-9, (off, found)
    env.close()


def test_conv2d_matches_torch() -> None:
    th = pytest.importorskip("torch")
    g = np.random.default_rng(0)
    x = g.normal(size=(3, 9, 11)).astype(np.float32)
    w = g.normal(size=(4, 3, 5, 5)).astype(np.float32)
    b = g.normal(size=4).astype(np.float32)
    ref = th.nn.functional.conv2d(th.from_numpy(x)[None], th.from_numpy(w), th.from_numpy(b), padding=2)[0].numpy()
    np.testing.assert_allclose(conv2d(x, w, b), ref, rtol=1e-4, atol=1e-4)


class _SurfaceSpaces(gym.Env):
    """Only the spaces (SB3 reads them to build a model)."""

    observation_space = gym.spaces.Box(-1.0, 1.0, (1, 33, 33), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        return np.zeros((1, 33, 33), np.float32), {}

    def step(self, action):
        return np.zeros((1, 33, 33), np.float32), 0.0, False, True, {}


def test_numpy_policy_is_the_sb3_policy_mean(tmp_path: Path) -> None:
    th = pytest.importorskip("torch")
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.surface_train import RegistrationRecipe, export_policy, make_model, mean_action

    recipe = RegistrationRecipe(seed=3)
    model = make_model(recipe, _SurfaceSpaces())
    with th.no_grad():      # a non-trivial head: the initial action net is near zero
        model.policy.action_net.weight.normal_(0.0, 0.5, generator=th.Generator().manual_seed(0))
    arrays, meta = export_policy(model, recipe)
    path = write_policy(arrays, meta, tmp_path / "p.npz")
    policy = load_policy(str(path))
    x = np.random.default_rng(1).uniform(-0.4, 0.9, (6, 1, 33, 33)).astype(np.float32)
    with th.no_grad():
        ref = mean_action(model.policy, th.from_numpy(x)).clamp(-1, 1).numpy()
    got = np.stack([policy(s) for s in x])
    assert np.abs(ref).max() > 0.05
    np.testing.assert_allclose(got, ref, atol=1e-5)
    with pytest.raises(ConfigError, match="exists"):
        write_policy(arrays, meta, path)


def test_a_bad_policy_file_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ConfigError, match="not a policy archive"):
        load_policy(str(bad))
    with pytest.raises(ConfigError, match="ppo-learned-registration"):
        load_policy(str(tmp_path / "missing.npz"))


def test_the_shipped_policy_runs_without_torch() -> None:
    """The agent loads the shipped policy offline and flies an episode with torch unimportable."""
    code = textwrap.dedent("""
        import sys
        sys.modules["torch"] = None          # any import of torch fails
        import gymnasium as gym, numpy as np
        import aerial_loc_env.env
        from aerial_loc_env.estimators.episode import EpisodeDriver
        from aerial_loc_env.estimators.registry import make_agent
        env = gym.make("AerialLoc/RealisticPaper-v3", **{"flight.duration_s": 3.0})
        agent = make_agent("ppo-learned-registration")
        with EpisodeDriver(env, [agent]) as driver:
            errors = [rec.error_m(0) for rec in driver.episode(4)]
        assert "torch" not in sys.modules or sys.modules["torch"] is None
        print(len(errors), float(np.isfinite(errors).all()))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300,
                         env={**__import__("os").environ, "PYTHONPATH": str(REPO)})
    assert out.returncode == 0, out.stderr[-2000:]
    n, finite = out.stdout.split()
    assert int(n) == 13 and float(finite) == 1.0


def test_shipped_policy_metadata() -> None:
    policy = load_policy(DEFAULT_POLICY)
    assert policy.params == SurfaceParams(**policy.meta["surface"])
    assert policy.meta["recipe"]["kind"] == "learned_registration"
    assert policy.meta["training"]["chosen"].split("@")[0] in ("bc", "bc+ppo")


def test_recipe_end_to_end_on_a_tiny_budget(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`aerial-loc train` on the recipe with a tiny budget: cloning data, cloning, PPO steps, the policy written
    (and refused over without --overwrite), and it runs as the agent; SB3's default logger folder never made."""
    pytest.importorskip("stable_baselines3")
    monkeypatch.setenv("SB3_LOGDIR", str(tmp_path / "sb3-default-logger"))     # where SB3's default would write
    from aerial_loc_env.learning.cli import main

    text = (REPO / "agents" / "ppo-learned-registration.toml").read_text()
    tiny = {"n_train_worlds": 1, "n_val_worlds": 1, "bc_episodes": 2, "duration_s": 3.0, "bc_epochs": 2,
            "ppo_timesteps": 16, "n_envs": 1, "n_steps": 8, "batch_size": 8, "n_epochs": 1, "eval_freq": 8,
            "val_episodes": 1, "workers": 1}
    lines = [ln for ln in text.splitlines() if ln.split("=")[0].strip() not in tiny]
    spec = tmp_path / "tiny.toml"
    spec.write_text("\n".join(lines + [f"{k} = {v}" for k, v in tiny.items()]) + "\n")
    out = tmp_path / "run"
    assert main([str(spec), "--out", str(out)]) == 0
    meta = json.loads((out / "training.json").read_text())
    assert meta["training"]["ppo_timesteps"] == 16 and meta["training"]["bc_surfaces"] > 0
    assert (out / "bc_curve.csv").read_text().count("\n") == 3          # header + 2 epochs
    assert (out / "ppo_curve.csv").read_text().count("\n") >= 3         # header, the cloned policy, PPO evaluations
    policy = load_policy(str(out / "policy.npz"))
    assert policy.meta["training"]["chosen"] == meta["training"]["chosen"]
    with pytest.raises(ConfigError, match="exists"):
        main([str(spec), "--out", str(out)])
    assert not (tmp_path / "sb3-default-logger").exists()
