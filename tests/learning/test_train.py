"""Training (``learning/train.py``): an output folder that is a file, and a checkpoint to resume from that is
no model, are clear errors before any training."""

from __future__ import annotations

import pytest

from aerial_loc_env.errors import ConfigError


def test_train_out_that_is_a_file(tmp_path):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.train import train

    blocker = tmp_path / "out"
    blocker.write_text("x")
    with pytest.raises(ConfigError, match=r"--out.*is a file"):
        train("ppo-local-registration", blocker, total_timesteps=1, progress_bar=False)
    assert blocker.read_text() == "x"


def test_train_resume_from_a_corrupt_zip(tmp_path):
    pytest.importorskip("stable_baselines3")
    from aerial_loc_env.learning.train import train

    bad = tmp_path / "ckpt.zip"
    bad.write_bytes(b"PK\x03\x04 this is not really a zip")
    with pytest.raises(ConfigError, match=r"--resume.*ckpt\.zip.*not a model"):
        train("ppo-local-registration", tmp_path / "out", resume=bad, progress_bar=False)
