"""The env's documentation is true: AerialLocEnv's docstring has Gymnasium's sections, in Gymnasium's order, and
they say what the env does; the README's examples of "Using the environment" run as written and print what the
README says they print."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

from aerial_loc_env.env import AerialLocEnv, load_scenario
from aerial_loc_env.env.scenarios import SECTIONS

README = Path(__file__).resolve().parents[2] / "README.md"

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
    return AerialLocEnv("AerialLoc/Small-v3", flight={"duration_s": 2.0})


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


# ----------------------------------------------------------------------------------------- the README's examples
def _readme_usage() -> tuple[list[str], list[str]]:
    """The python blocks and the text blocks of the README's "Using the environment" section, in order."""
    section = README.read_text(encoding="utf-8").split("## Using the environment\n", 1)[1].split("\n## ", 1)[0]
    section = section.split("\n### ", 1)[0]
    return (re.findall(r"^```python\n(.*?)^```", section, flags=re.MULTILINE | re.DOTALL),
            re.findall(r"^```text\n(.*?)^```", section, flags=re.MULTILINE | re.DOTALL))


def _run_as_a_user(code: str, cwd: Path) -> str:
    """``code`` as a script in a fresh interpreter, outside the repository; its stdout."""
    script = cwd / "example.py"
    script.write_text(code, encoding="utf-8")
    done = subprocess.run([sys.executable, str(script)], cwd=cwd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return done.stdout


_LINE = re.compile(r"t=\s*([\d.]+) s  error=\s*([\d.]+) m  (\w+)")


def test_the_readme_has_the_two_examples_and_the_printed_lines():
    code, printed = _readme_usage()
    assert len(code) == 2 and len(printed) == 1
    assert "import aerial_loc_env as ale" in code[0] and "ale.EpisodeDriver" in code[0]
    assert "ale.MetresAction" in code[1]
    assert all(_LINE.fullmatch(line) for line in printed[0].splitlines())


def test_the_readme_driver_example_prints_what_the_readme_shows(tmp_path):
    """Same lines at the same times; the errors may differ in the last digits between CPUs, so they are checked
    against the scenario: from the time the README says the agent has locked on, every one is well inside the
    prior's sigma."""
    code, printed = _readme_usage()
    locked = re.search(r"has\s+locked on by t = (\d+) s", README.read_text(encoding="utf-8"))
    assert locked, "the README no longer says when the agent locks on"
    shown = [_LINE.fullmatch(line).groups() for line in printed[0].splitlines()]
    got = [_LINE.fullmatch(line) for line in _run_as_a_user(code[0], tmp_path).splitlines()]
    assert all(got), got
    got = [m.groups() for m in got]
    assert [t for t, _e, _s in got] == [t for t, _e, _s in shown]
    prior_std_m = load_scenario("AerialLoc/PaperShadows-v2").episode.prior_std_m
    errors = [float(e) for _t, e, _s in got]
    assert all(math.isfinite(e) for e in errors)
    after_lock = [float(e) for t, e, _s in got if float(t) >= float(locked.group(1))]
    assert after_lock and max(after_lock) < prior_std_m / 5, got
    assert [s for _t, _e, s in got][-1] == "ok"


def test_the_readme_gymnasium_loop_runs_the_whole_track(tmp_path):
    code, _printed = _readme_usage()
    said = re.search(r"# (\d+) steps, last error ([\d.]+) m", code[1])
    out = _run_as_a_user(code[1], tmp_path)
    got = re.fullmatch(r"(\d+) steps, last error ([\d.]+) m\n", out)
    assert said and got, out
    sc = load_scenario("AerialLoc/PaperShadows-v2")
    assert int(got.group(1)) == int(said.group(1)) == round(sc.flight.duration_s * sc.flight.rate_hz)
    assert float(got.group(2)) < sc.episode.prior_std_m / 5
