"""AerialLocEnv's docstring has Gymnasium's sections, in Gymnasium's order, and they say what the env does."""

from __future__ import annotations

import re

import pytest

from aerial_loc_env.env import AerialLocEnv
from aerial_loc_env.env.scenarios import SECTIONS

GYMNASIUM_SECTIONS = ["Description", "Action Space", "Observation Space", "Rewards", "Starting State",
                      "Episode End", "Arguments", "Version History"]


def _sections() -> dict[str, str]:
    doc = AerialLocEnv.__doc__ or ""
    parts = re.split(r"^\s*## (.+?)\s*$", doc, flags=re.MULTILINE)
    return {title: body.strip() for title, body in zip(parts[1::2], parts[2::2], strict=True)}


def test_the_sections_are_gymnasiums_in_order_and_none_is_empty():
    sections = _sections()
    assert list(sections) == GYMNASIUM_SECTIONS
    assert all(len(body) > 80 for body in sections.values()), {k: len(v) for k, v in sections.items()}


@pytest.fixture(scope="module")
def env():
    return AerialLocEnv("AerialLoc/Small-v1", flight={"duration_s": 2.0})


def test_the_spaces_are_documented_as_built(env):
    sections = _sections()
    documented = set(re.findall(r"^\s*\| ``(\w+)`` \|", sections["Observation Space"], flags=re.MULTILINE))
    assert documented == set(env.observation_space.spaces)
    a = env.action_space
    assert f"Box(-1, 1, {a.shape}, {a.dtype})" in sections["Action Space"]


def test_every_spec_section_is_listed_among_the_arguments():
    missing = [name for name in SECTIONS if f"``{name}``" not in _sections()["Arguments"]]
    assert not missing, f"add the spec section(s) {missing} to the Arguments section of AerialLocEnv's docstring"


def test_version_history_lists_versions():
    assert re.search(r"^\s*\* v\d+:", _sections()["Version History"], flags=re.MULTILINE)
