"""The scenario presets: the paper's ids keep the paper's setting, the realistic ids fly the same setting with
every part of the realistic gap switched on."""

from __future__ import annotations

import pytest

from aerial_loc_env.env import load_scenario

PAPER = ("AerialLoc/PaperShadows-v2", "AerialLoc/PaperNoShadows-v2")
REALISTIC = ("AerialLoc/RealisticPaper-v3", "AerialLoc/SeasonChange-v3", "AerialLoc/Downtown-v3")
SETTING = ("flight", "camera", "odometry", "observation", "episode", "reward")


@pytest.mark.parametrize("sid", PAPER)
def test_paper_ids_keep_the_papers_setting(sid):
    """Shadow-free database of the same epoch, the affine camera: Table 5 still means what it meant."""
    sc = load_scenario(sid)
    assert sc.epoch.is_identity and sc.database.is_identity
    assert not sc.perspective.enabled and sc.shadows.database_sun_deg is None
    assert sc.gimbal.roll_pitch_std_deg == 0 and sc.altimeter.bias_std_m == 0 and sc.exposure.strength == 0


@pytest.mark.parametrize("sid", REALISTIC)
def test_realistic_ids_switch_on_every_part_of_the_gap(sid):
    sc = load_scenario(sid)
    assert not sc.epoch.is_identity and not sc.database.is_identity
    assert sc.perspective.enabled and sc.shadows.database_sun_deg is not None
    assert sc.gimbal.roll_pitch_std_deg > 0 and sc.altimeter.bias_std_m > 0 and sc.exposure.strength > 0
    assert sc.haze.extinction_per_km > 0
    assert sc.database.gsd_m > sc.city.gsd_m          # the map's sensor is coarser than the drone's camera


def test_realistic_paper_is_the_paper_setting_plus_the_gap():
    paper, real = load_scenario(PAPER[0]).to_dict(), load_scenario(REALISTIC[0]).to_dict()
    for section in (*SETTING, "city"):
        assert real[section] == paper[section], section
    season = load_scenario(REALISTIC[1]).to_dict()
    for section in (*SETTING, "city", "database"):
        assert season[section] == real[section], section
