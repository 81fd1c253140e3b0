"""The realistic presets stay calibrated (issue 11): every statistic of ``aerial-loc gap`` of each realistic
scenario lies inside the spread of the real two-epoch pairs in ../shared/data/pairs/, up to the sampling error
of the few frames measured here.

The full report (5 seeds x every 20th frame) takes minutes; this measures the first frame of ``FRAMES`` seeds
per scenario (frames i.i.d. over seeds) and widens nothing by hand: the scenario's headline figure (the median;
the fraction for template matching) gets its distribution-free ``CONFIDENCE`` interval from the frames
themselves (``gap.median_interval``: order statistics; ``gap.proportion_interval``: Clopper-Pearson), and the
test fails when that interval misses the real spread (min..max of the pairs' headline figures, computed here
from the pairs: the imagery's licence keeps it out of the repository). A preset that fails is out of
calibration: report it, and change its world only under a new id version (the issue: results are what they are).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from shared_helpers import SHARED_DATA

from aerial_loc_env.benchmark import gap
from aerial_loc_env.errors import ConfigError

PAIRS = SHARED_DATA / "pairs" / "levir-cd"
REALISTIC = ("AerialLoc/RealisticPaper-v3", "AerialLoc/SeasonChange-v3", "AerialLoc/Downtown-v3")
#: frames per scenario (the first frame of seeds 0..FRAMES-1) and the confidence of each statistic's interval
FRAMES = 24
CONFIDENCE = 0.99


# ------------------------------------------------------------------------------------------ the intervals
def test_median_interval_is_the_binomial_order_statistic():
    """n = 24 at 99 %: P(Bin(24, 1/2) <= 5) = 55455 / 2^24 = 0.0033 <= 0.005 < P(<= 6) = 0.0113, so the
    bounds are the 6th smallest and the 6th largest value (of 0..23: 5 and 18). At 50 %: P(<= 9) = 0.154 <=
    0.25 < P(<= 10) = 0.271, the 10th smallest and largest (9 and 14)."""
    assert sum(math.comb(24, i) for i in range(6)) == 55455
    values = np.random.default_rng(0).permutation(np.arange(24.0))
    assert gap.median_interval(values, 0.99) == (5.0, 18.0)
    assert gap.median_interval(values, 0.5) == (9.0, 14.0)
    with pytest.raises(ConfigError, match="at least 8"):
        gap.median_interval(np.arange(7.0), 0.99)             # 2^-7 = 0.0078 > 0.005: no order statistic


def test_median_interval_covers_the_true_median():
    """Coverage over 4000 skewed samples of 24 is at least 1 - 2 * 0.0033 = 0.9934 (exact, any continuous
    law); the estimate's std is sqrt(0.0066 * 0.9934 / 4000) = 0.0013: 4 sigma below the bound still holds."""
    gen = np.random.default_rng(1)
    samples = gen.exponential(1.0, (4000, FRAMES))
    bounds = np.array([gap.median_interval(s, CONFIDENCE) for s in samples])
    covered = np.mean((bounds[:, 0] <= math.log(2.0)) & (math.log(2.0) <= bounds[:, 1]))
    assert covered >= 0.9934 - 4 * 0.0013


@pytest.mark.parametrize("k", [0, 1, 7, 12, 24])
def test_proportion_interval_solves_the_binomial_tails(k):
    n, tail = 24, (1.0 - CONFIDENCE) / 2.0
    lo, hi = gap.proportion_interval(k, n, CONFIDENCE)

    def cdf(j: int, p: float) -> float:
        return sum(math.comb(n, i) * p ** i * (1 - p) ** (n - i) for i in range(j + 1))

    assert 0.0 <= lo <= k / n <= hi <= 1.0
    if k == 0:
        assert lo == 0.0 and hi == pytest.approx(1.0 - tail ** (1.0 / n), abs=1e-9)
    if k == n:
        assert hi == 1.0 and lo == pytest.approx(tail ** (1.0 / n), abs=1e-9)
    if 0 < k:
        assert 1.0 - cdf(k - 1, lo) == pytest.approx(tail, abs=1e-9)
    if k < n:
        assert cdf(k, hi) == pytest.approx(tail, abs=1e-9)
    assert gap.proportion_interval(n - k, n, CONFIDENCE) == pytest.approx((1.0 - hi, 1.0 - lo), abs=1e-9)
    with pytest.raises(ConfigError, match="not a proportion"):
        gap.proportion_interval(n + 1, n)


def test_frames_per_seed_stops_each_episode():
    windows = gap.scenario_gap("AerialLoc/Small-v3", seeds=[0, 1], stride=5, frames_per_seed=2)
    assert len(windows) == 4        # frames 0 and 5 of each seed, not the whole 61-frame episodes
    with pytest.raises(ConfigError, match="frames_per_seed"):
        gap.scenario_gap("AerialLoc/Small-v3", frames_per_seed=0)


# ------------------------------------------------------------------------------------------ the presets
@pytest.fixture(scope="module")
def real_spread() -> dict[str, tuple[float, float]]:
    if not PAIRS.is_dir():
        pytest.skip(f"real two-epoch pairs not available ({PAIRS} is absent: they live beside the project, "
                    "never in it; see ../shared/data/pairs/README.md)")
    return gap.spread(gap.summarize(gap.pair_gap(a, b, gsd_m=0.5)) for a, b in gap.pairs_in(PAIRS))


def _calibration(scenario: str, real: dict[str, tuple[float, float]]) -> tuple[list[str], list[str]]:
    """The statistics that miss the real spread even at their sampling error, and a printable table."""
    windows = gap.scenario_gap(scenario, seeds=range(FRAMES), frames_per_seed=1)
    assert len(windows) == FRAMES
    summary = gap.summarize(windows)
    lines, outside = [f"{scenario}: {FRAMES} frames, {CONFIDENCE:.0%} intervals; real pairs' spread"], []
    for stat in gap.STATS:
        figure = gap.headline(summary, stat)
        lo, hi = gap.headline_interval(windows, stat, CONFIDENCE)
        real_lo, real_hi = real[stat]
        inside = hi >= real_lo and lo <= real_hi
        lines.append(f"  {stat:16s} {figure:7.3f} (-{figure - lo:.3f} +{hi - figure:.3f})   real "
                     f"{real_lo:.3f}..{real_hi:.3f}   {'inside' if inside else 'OUTSIDE'}")
        if not inside:
            outside.append(stat)
    print("\n".join(lines))
    return outside, lines


@pytest.mark.slow
@pytest.mark.parametrize("scenario", REALISTIC)
def test_realistic_preset_gap_lies_inside_the_real_pairs_spread(scenario, real_spread):
    outside, lines = _calibration(scenario, real_spread)
    assert not outside, (f"{scenario} is out of calibration in {', '.join(outside)} (issue 11: report it; a "
                         "change of its world needs a new id version):\n" + "\n".join(lines))


@pytest.mark.slow
def test_the_paper_setting_is_caught_outside(real_spread):
    """The check has power: the paper's scenario (the map re-projected plus shadows: NCC ~0.8, bits ~0.8 on
    the full report) is outside the real spread on the statistics the gap is about, margins included."""
    outside, _ = _calibration("AerialLoc/PaperShadows-v2", real_spread)
    assert {"ncc", "bit_agreement", "peak_margin", "orb_inlier_ratio"} <= set(outside)
