"""What the SITL tests share: the real binaries of ../shared/sitl/ (skipped with the reason where absent) and a
fake SITL folder whose 'binaries' are shell scripts that say when they were run."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest

SITL_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "sitl"


@pytest.fixture
def real_sitl() -> Callable[[str], Path]:
    """``real_sitl('arducopter')``: the folder of the real SITL binaries, or a skip naming what is missing."""

    def get(binary: str) -> Path:
        if not (SITL_DIR / binary).is_file():
            pytest.skip(f"ArduPilot SITL not found at {SITL_DIR} (see ../shared/sitl/README.md)")
        return SITL_DIR

    return get


@pytest.fixture
def mission_sitl(real_sitl: Callable[[str], Path]) -> Callable[[str], Path]:
    """A mission's SITL: ``real_sitl``, skipped (with the reason) without the agents too."""

    def get(binary: str) -> Path:
        folder = real_sitl(binary)
        pytest.importorskip("aerial_loc_env.estimators.registry", reason="the agents are not available")
        return folder

    return get


@pytest.fixture
def long_mission(mission_sitl: Callable[[str], Path]) -> Callable[[str, str], Path]:
    """The long SITL missions: skipped (with the reason) without the binary, the agents, or AERIAL_LOC_SITL_ALL=1
    (CI's time budget)."""

    def get(binary: str, duration: str) -> Path:
        folder = mission_sitl(binary)
        if os.environ.get("AERIAL_LOC_SITL_ALL") != "1":
            pytest.skip(f"the long SITL missions (copter ExternalNav and GNSS denial, plane GNSS denial and crosswind) "
                        f"run with AERIAL_LOC_SITL_ALL=1 ({duration})")
        return folder

    return get


@pytest.fixture
def fake_sitl(tmp_path: Path) -> Path:
    """A SITL folder whose arducopter / arduplane are shell scripts: each run appends a line to ``runs`` in the
    folder, then sleeps (a SITL that runs); the parameter files are empty."""
    folder = tmp_path / "fake_sitl"
    folder.mkdir()
    for exe, parm in (("arducopter", "copter.parm"), ("arduplane", "plane.parm")):
        (folder / parm).write_text("")
        script = folder / exe
        script.write_text(f"#!/bin/sh\necho run >> {folder}/runs\necho 'SITL starting'\nexec sleep 30\n")
        script.chmod(0o755)
    return folder
