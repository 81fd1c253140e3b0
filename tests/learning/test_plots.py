"""Learning curves (``learning/plots.py``): a malformed eval.csv is a clear error naming the file."""

from __future__ import annotations

import pytest

from aerial_loc_env.errors import ConfigError


@pytest.mark.parametrize("text", ["timesteps,rmse_m\n10,abc\n", "garbage\x00\x01\n", "a,b\n1,2\n"])
def test_curve_with_a_malformed_eval_csv(tmp_path, text):
    pytest.importorskip("matplotlib")
    from aerial_loc_env.learning.plots import learning_curve

    (tmp_path / "eval.csv").write_text(text)
    with pytest.raises(ConfigError, match=r"eval\.csv"):
        learning_curve(tmp_path, tmp_path / "c.png")
