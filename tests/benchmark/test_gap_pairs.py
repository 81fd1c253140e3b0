"""The gap report on real pairs as they come (benchmark/gap.py): each pair at its own georeference and sampling,
anisotropic pixels squared, sub-pixel grid offsets honoured, the footer's sampling true, and a --window-m option
where the report advises a smaller window."""

from __future__ import annotations

import json
import re

import cv2
import numpy as np
import pytest
from synthetic_pairs import write_pair

from aerial_loc_env.benchmark import gap
from aerial_loc_env.cli import main
from aerial_loc_env.errors import ConfigError


def test_pairs_at_different_samplings_go_in_one_run(tmp_path, capsys):
    """A LEVIR-like folder (PNGs without georeference, 0.5 m given after the folder) and a georeferenced pair with
    0.600 x 0.674 m pixels, in one run: each read at its own sampling (one --pair-gsd for all refused the second),
    the anisotropic one on square pixels, and the footer names both samplings (it said 0.5 m/px for all)."""
    write_pair(tmp_path / "levir", "t.png", world_file=False)
    a, b = write_pair(tmp_path / "aniso", "q.png", size_px=600, gsd_m=0.6, b_gsd_xy_m=(0.6, 0.674))
    out = tmp_path / "gap.json"
    rc = main(["gap", "--pairs-dir", str(tmp_path / "levir"), "0.5", "--pair", str(a), str(b), "--json", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    data = json.loads(out.read_text())
    levir, aniso = data["pairs"]["levir/t.png"], data["pairs"]["aniso/q.png"]
    assert levir["analysis_gsd_m"] == 0.5 and aniso["analysis_gsd_m"] == pytest.approx(0.6 / 0.9996, rel=1e-3)
    assert aniso["pair_gsd_m"] == pytest.approx(0.6 / 0.9996, rel=1e-3)
    # 150 x 100 m windows on 0.6 m square pixels over B's 360 x 360 m (600 x 534 px of 0.600 x 0.674 m): a 600 x
    # 600 px grid, 250 x 167 px windows and a +-17 px search: 2 x 3 (B's own grid, and A's, differ: they were
    # refused as not sharing one pixel grid)
    assert aniso["summary"]["ncc"]["n"] == 6
    assert "at each source's sampling (aniso/q.png 0.6, levir/t.png 0.5 m/px)" in text
    assert "aniso/q.png: misregistration" in text
    # the georeferenced pair with a --pair-gsd that does not match it: its own georeference wins (was an error)
    assert main(["gap", "--pair", str(a), str(b), "--pair-gsd", "0.5"]) == 0
    assert "at 0.6 m/px" in capsys.readouterr().out


def test_a_sub_pixel_offset_between_the_grids_is_not_compared_pixel_for_pixel(tmp_path):
    """B's grid starts 1.08 px (0.54 m) east of A's, its content where its georeference says: on one grid the
    epochs are alike (NCC ~1); pixel for pixel they would differ by the offset."""
    a, b = write_pair(tmp_path, b_offset_px=(1.08, 0.0))
    measured = gap.measure_pair(a, b)
    assert gap.summarize(measured.windows)["ncc"]["median"] > 0.995
    assert "misregistration -0.0" in measured.registration or "misregistration +0.0" in measured.registration
    raw = [cv2.imread(str(p))[..., ::-1] for p in (a, b)]
    cfg = gap.GapConfig()
    naive = [gap.window_stats(c, d, cfg, 0.5) for c, d in gap.pair_windows(raw[0], raw[1], cfg, 0.5)]
    assert gap.summarize(naive)["ncc"]["median"] < 0.99


def test_a_misregistered_pair_is_refused_or_measured_only(tmp_path, capsys):
    a, b = write_pair(tmp_path, shift_m=(2.5, 0.0))
    assert main(["gap", "--pair", str(a), str(b)]) == 2
    assert "misregistered by 2." in capsys.readouterr().err
    assert main(["gap", "--pair", str(a), str(b), "--max-shift-m", "0"]) == 0
    assert "/p.png: misregistration +5.0" in capsys.readouterr().out


def test_a_tile_too_small_for_one_window_names_the_option_that_fixes_it(tmp_path, capsys):
    a, b = write_pair(tmp_path, size_px=200)          # 100 m: no room for a 150 x 100 m window and the search
    assert main(["gap", "--pair", str(a), str(b)]) == 2
    err = capsys.readouterr().err
    assert "use a smaller window (aerial-loc gap --window-m W H, at most 80 x 80 m here" in err
    assert main(["gap", "--pair", str(a), str(b), "--window-m", "60", "40"]) == 0
    assert re.search(r"^\| \S+/p\.png \| 2 \|", capsys.readouterr().out, flags=re.MULTILINE)


def test_bad_pair_arguments_are_clear_errors(tmp_path):
    a, b = write_pair(tmp_path)
    with pytest.raises(ConfigError, match=r"--pair .*: give EARLIER LATER \[GSD\]"):
        gap.main(["--pair", str(a)])
    with pytest.raises(ConfigError, match=r"--pair .* GSD: 'fine' is not a ground sampling"):
        gap.main(["--pair", str(a), str(b), "fine"])
    with pytest.raises(ConfigError, match=r"--pairs-dir .* extra: give DIR \[GSD\]"):
        gap.main(["--pairs-dir", str(tmp_path), "0.5", "extra"])
    (tmp_path / "taken.json").write_text("{}")
    with pytest.raises(ConfigError, match=r"--json .*taken\.json exists"):
        gap.main(["--pair", str(a), str(b), "--json", str(tmp_path / "taken.json")])
    assert np.isfinite(gap.measure_pair(a, b).pair_gsd_m)
