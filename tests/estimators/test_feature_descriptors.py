"""estimators/feature_matching.py with the trained descriptors of OpenCV's contrib module (BEBLID, TEBLID, VGG,
BoostDesc): the agents build offline, fix on a PaperShadows frame, and an unknown or missing descriptor is a
clear error."""

from __future__ import annotations

import math

import cv2
import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.config import build_config
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.feature_matching import (
    DESCRIPTORS,
    FeatureMatchingAgent,
    FeatureMatchingParams,
    make_descriptor,
)
from aerial_loc_env.estimators.registry import make_agent


def test_opencv_is_the_contrib_build_with_every_trained_descriptor():
    for name, (factory, _norm) in DESCRIPTORS.items():
        assert hasattr(cv2.xfeatures2d, factory), name


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(DESCRIPTORS))
def test_each_descriptor_describes_the_detectors_keypoints(name):
    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 256, (200, 300), dtype=np.uint8), (5, 5), 1.5)
    agent = FeatureMatchingAgent(build_config(FeatureMatchingParams, {"detector": "orb", "descriptor": name}))
    keypoints, descriptors = agent._features(image)
    assert len(keypoints) > 50 and descriptors.shape[0] == len(keypoints)
    binary = DESCRIPTORS[name][1] == cv2.NORM_HAMMING
    assert descriptors.dtype == (np.uint8 if binary else np.float32)


def test_teblid_agent_fixes_on_a_paper_shadows_frame():
    env = gym.make("AerialLoc/PaperShadows-v2", **{"flight.duration_s": 2.0})
    obs, info = env.reset(seed=0)
    agent = make_agent("features-teblid")
    assert agent.params.descriptor == "teblid" and agent.extractor is not None
    start = agent.reset(env.unwrapped.briefing, seed=0)
    truth = info["true_pose"]
    est = agent.step(obs)
    env.close()
    assert est.status == "ok", est.extras
    assert math.hypot(est.x_m - truth[0], est.y_m - truth[1]) < 1.5
    assert math.hypot(start.x_m - truth[0], start.y_m - truth[1]) > 5.0     # the prior was off: the fix did it


def test_unknown_descriptor_is_a_clear_error():
    with pytest.raises(ConfigError, match="field 'descriptor' = 'sift2' is not allowed; use one of 'beblid', "
                                          "'teblid', 'vgg', 'boostdesc'"):
        make_agent("features-orb", descriptor="sift2")
    with pytest.raises(ConfigError, match="unknown descriptor 'latch'; use one of beblid, teblid, vgg, boostdesc"):
        make_descriptor("latch", "orb")


def test_opencv_without_contrib_names_the_package(monkeypatch):
    monkeypatch.delattr(cv2, "xfeatures2d")
    with pytest.raises(ConfigError, match="'teblid' needs OpenCV's contrib module.*opencv-contrib-python-headless"):
        make_agent("features-teblid")
