"""The wheel carries the scenario specs: build it, install it in a fresh virtual environment, gym.make each id.

Marked slow (a wheel build and a venv; about 3 s here). The fresh venv gets the wheel with ``--no-deps`` and borrows the
dependencies (numpy, OpenCV, Gymnasium, ...) from the test interpreter's site-packages through a ``.pth`` path
line, which adds that folder to ``sys.path`` without running its ``.pth`` files: so the source checkout's
editable install stays invisible and ``aerial_loc_env`` comes from the wheel. Run from a folder outside the
checkout so that the current directory cannot shadow it either.
"""

from __future__ import annotations

import os
import site
import subprocess
import sys
import venv
from pathlib import Path

import pytest
from shared_helpers import REPO_ROOT, SHARED_DATA

SCRIPT = r"""
import sys, pathlib, gymnasium as gym, aerial_loc_env
from aerial_loc_env.paths import spec_dir
from aerial_loc_env.errors import ConfigError
pkg = pathlib.Path(aerial_loc_env.__file__).resolve().parent
assert pkg.is_relative_to(pathlib.Path(sys.prefix).resolve()), f"not the wheel's package: {pkg}"
assert spec_dir("envs") == pkg / "_specs" / "envs", spec_dir("envs")
ids = sorted(s for s in gym.registry if s.startswith("AerialLoc/"))
tile = sys.argv[1]
for sid in ids:
    kw = {}
    if sid == "AerialLoc/RealPair-v2":
        try:
            gym.make(sid)
        except ConfigError:
            print("ok", sid, "(no pair: missing paths are a ConfigError)")
            continue
        raise SystemExit("RealPair without paths did not raise ConfigError")
    if sid == "AerialLoc/RealMap-v2":
        if not tile:
            try:
                gym.make(sid)
            except ConfigError:
                print("ok", sid, "(no tile: missing path is a ConfigError)")
                continue
            raise SystemExit("RealMap without a path did not raise ConfigError")
        kw["path"] = tile
    env = gym.make(sid, **kw)
    obs, info = env.reset(seed=0)
    env.step(env.action_space.sample())
    env.close()
    print("ok", sid)
print("ids", len(ids))
"""


@pytest.mark.slow
def test_wheel_in_fresh_venv_makes_every_id(tmp_path):
    wheel_dir = tmp_path / "wheel"
    build = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(wheel_dir),
                            str(REPO_ROOT)], capture_output=True, text=True, timeout=300)
    if build.returncode != 0:
        pytest.skip(f"cannot build the wheel here (no network for the build backend?): {build.stderr[-500:]}")
    wheel = next(wheel_dir.glob("aerial_loc_env-*.whl"))
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    Path(purelib, "_borrowed_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    install = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "--no-deps", "-q",
                              str(wheel)], capture_output=True, text=True, timeout=300)
    assert install.returncode == 0, install.stderr[-2000:]
    tile = SHARED_DATA / "manila_pasig_river.tif"
    run = subprocess.run([str(py), "-c", SCRIPT, str(tile) if tile.is_file() else ""], cwd=tmp_path,
                         capture_output=True, text=True, timeout=600,
                         env={**os.environ, "PYTHONPATH": "", "OMP_NUM_THREADS": "1"})
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    n = len(list((REPO_ROOT / "envs").glob("*.toml")))
    assert f"ids {n}\n" in run.stdout and run.stdout.count("ok AerialLoc/") == n, run.stdout
