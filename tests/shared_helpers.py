"""Constants and helpers that test files of several layers share.

A plain module rather than conftest.py: ``from conftest import ...`` finds whichever conftest.py pytest loaded
last (tests/sitl/ has its own), while this module is always this one."""

from __future__ import annotations

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO_ROOT.parent / "shared" / "data"
REAL_TILES = ("manila_pasig_river.tif", "valencia_orchard.tif")
LATIN1 = "description = \"caf\xe9\"\n".encode("latin-1")   # a file saved in Latin-1, not UTF-8


def crop_png(om, folder: Path, size: int = 512) -> tuple[Path, float, float]:
    """The centre crop of ``om`` as a PNG; returns it with the crop centre's lat/lon."""
    import cv2
    import numpy as np

    v0 = u0 = (om.width_px - size) // 2 + min(200, (om.width_px - size) // 2)    # off the no-data wedge
    png = folder / "crop.png"
    cv2.imwrite(str(png), np.ascontiguousarray(np.asarray(om.rgb)[v0:v0 + size, u0:u0 + size, ::-1]))
    lat, lon = om.georef.pixel_to_latlon(u0 + (size - 1) / 2.0, v0 + (size - 1) / 2.0)
    return png, float(np.ravel(lat)[0]), float(np.ravel(lon)[0])


def check_env_silently(sid: str, **kwargs) -> None:
    """Gymnasium's and SB3's env checkers on ``gym.make(sid, **kwargs)``, failing on any warning either gives
    (earlier tests' garbage collected first: its ResourceWarnings are not the checkers')."""
    import gc
    import warnings

    import gymnasium as gym
    import pytest
    from gymnasium.utils.env_checker import check_env

    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    gc.collect()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(gym.make(sid, render_mode="rgb_array", **kwargs).unwrapped)
        sb3_checker.check_env(gym.make(sid, **kwargs).unwrapped, warn=True)
    assert [str(w.message) for w in caught] == []


def host_env() -> dict[str, str]:
    """This process's environment without the variables that pick a CPU's code paths (those ``sysinfo.avx2_env``
    sets, and ``perf --avx2``'s marker): a subprocess started with it computes as the host does."""
    import os

    from aerial_loc_env.sysinfo import avx2_env

    chosen = set(avx2_env("")) | {"AERIAL_LOC_AVX2"}
    return {k: v for k, v in os.environ.items() if k not in chosen}
