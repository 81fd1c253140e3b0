"""Shared test fixtures: the repository root and the real imagery beside the project (../shared/data)."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
REAL_TILES = ("manila_pasig_river.tif", "valencia_orchard.tif")


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The project root (holds pyproject.toml, envs/, agents/)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data with the real GeoTIFF tiles; skips where that folder (or a tile) is absent."""
    missing = [t for t in REAL_TILES if not (SHARED_DATA / t).is_file()]
    if missing:
        pytest.skip(f"real imagery not available: {SHARED_DATA} lacks {', '.join(missing)} "
                    "(the tiles live beside the project, never in it)")
    return SHARED_DATA
