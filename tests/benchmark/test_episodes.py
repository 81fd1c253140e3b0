"""One benchmark episode (``benchmark/episodes.py``): the shadow detector's mask quality (a grid's
``detector_quality``) scored against the simulator's masks, in the rows, the CSV and the report."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from aerial_loc_env.benchmark.episodes import DETECTOR_COLUMNS, run_episode
from aerial_loc_env.benchmark.grid import grid_from_dict, make_grid
from aerial_loc_env.benchmark.report import markdown_report
from aerial_loc_env.benchmark.runner import plan
from aerial_loc_env.benchmark.store import write_summaries
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.shadow_detection import ShadowDetector, mask_quality

TINY = {"id": "AerialLoc/Small-v3", "overrides": {"flight.duration_s": 2.0}, "label": "tiny"}


def _rows(detector_quality: bool) -> list[dict]:
    grid = make_grid("d", ["dead-reckoning", "mcl-ssd"], [TINY], seeds=[3], detector_quality=detector_quality)
    (task,) = plan(grid, set())
    rows, failures = run_episode(task)
    assert not failures
    return rows


@pytest.fixture(scope="module")
def both() -> tuple[list[dict], list[dict]]:
    return _rows(False), _rows(True)


def test_detector_columns_are_the_frames_mean_mask_quality(both) -> None:
    """The columns are the means over the episode's frames of mask_quality(detect(frame), true mask), the same
    for every agent of the episode."""
    _without, rows = both
    env = gym.make(TINY["id"], **{**TINY["overrides"], "observation.info_shadow_mask": True})
    obs, info = env.reset(seed=3)
    detector, quality, done = ShadowDetector(), [], False
    while True:
        quality.append(mask_quality(detector.detect(obs["image"]).full(), info["shadow_mask"]))
        if done:
            break
        obs, _r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        done = terminated or truncated
    env.close()
    assert len(quality) == rows[0]["steps"]
    for key, column in DETECTOR_COLUMNS.items():
        expected = float(np.mean([q[key] for q in quality]))
        assert [r[column] for r in rows] == [pytest.approx(expected, abs=1e-12)] * len(rows), column
    assert 0.0 < rows[0]["shadow_fraction_true"] < 1.0


def test_without_the_option_the_rows_are_as_before(both) -> None:
    without, rows = both
    timing = {"step_time_median_ms", "step_time_p95_ms", "compute_time_total_s", "cpu_time_total_s",
              "episode_render_cpu_s"}
    assert not any(c in r for r in without for c in DETECTOR_COLUMNS.values())
    for a, b in zip(without, rows, strict=True):
        same_a = {k: v for k, v in a.items() if k not in timing}
        same_b = {k: v for k, v in b.items() if k not in timing and k not in DETECTOR_COLUMNS.values()}
        assert json.dumps(same_a, sort_keys=True) == json.dumps(same_b, sort_keys=True)   # NaN as NaN


def test_the_csv_and_the_report_show_the_detector_only_when_scored(both, tmp_path: Path) -> None:
    for rows, scored in zip(both, (False, True), strict=True):
        csv_path, _json = write_summaries(rows, tmp_path)
        header = next(csv.reader(csv_path.open()))
        assert ("detector_iou" in header) is scored and ("shadow_fraction_detected" in header) is scored
        report = markdown_report("d", "", rows, "test machine")
        assert ("## Shadow detector against the true masks" in report) is scored
    assert "| tiny | 1 | " in report            # one episode, however many agents ran on it


def test_the_option_must_be_true_or_false() -> None:
    assert grid_from_dict({"agents": ["a"], "scenarios": ["s"], "seeds": 1, "detector_quality": True}).detector_quality
    with pytest.raises(ConfigError, match="detector_quality = 'yes' must be true or false"):
        grid_from_dict({"agents": ["a"], "scenarios": ["s"], "seeds": 1, "detector_quality": "yes"})
