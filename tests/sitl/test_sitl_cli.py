"""``aerial-loc sitl``: every option checked before SITL starts, each bad value a one-line error naming the
option, the problem and the allowed values (exit status 2), with nothing run and nothing written."""

from __future__ import annotations

import subprocess
import sys

import pytest

from aerial_loc_env.cli import COMMANDS
from aerial_loc_env.cli import main as aerial_loc


def _sitl(argv: list[str], capsys) -> tuple[int, str]:
    rc = aerial_loc(["sitl", *argv])
    return rc, capsys.readouterr().err


CASES = {
    "speedup -1": (["--speedup", "-1"], r"--speedup -1.0: must be in [0.1, 20]"),
    "speedup 0": (["--speedup", "0"], r"--speedup 0.0: must be in [0.1, 20]"),
    "speedup nan": (["--speedup", "nan"], r"--speedup nan: must be in [0.1, 20]"),
    "speedup 50": (["--speedup", "50"], r"--speedup 50.0: must be in [0.1, 20]"),
    "ground nan": (["--ground-amsl-m", "nan"], "--ground-amsl-m nan: must be a finite height in [-500, 9000] m AMSL"),
    "ground 1e9": (["--ground-amsl-m", "1e9"], "--ground-amsl-m 1000000000.0: must be a finite height in [-500"),
    "old version": (["--scenario", "AerialLoc/Small-v0"], "this version of the package has 'AerialLoc/Small-v3'"),
    "map file": (["--scenario", "AerialLoc/RealMap-v2"], "`aerial-loc sitl` takes no map file; it flies the "
                                                          "procedural-city scenarios: AerialLoc/"),
    "pair of files": (["--scenario", "AerialLoc/RealPair-v2"], "--scenario AerialLoc/RealPair-v2: flies over two "
                      "image files given to gym.make (path_a=..., path_b=...), and `aerial-loc sitl` takes no map"),
    "old map file": (["--scenario", "AerialLoc/RealMap-v1"], "--scenario AerialLoc/RealMap-v1 (now "
                     "AerialLoc/RealMap-v2): flies over a map file given to gym.make (path=...), and `aerial-loc sitl` "
                     "takes no map file"),
    "plane on a small map": (["--vehicle", "plane", "--scenario", "AerialLoc/Small-v3"],
                             "its map is 400 x 400 m, and the plane's flight"),
    "plane external-nav": (["--vehicle", "plane", "--mission", "external-nav"],
                           "--mission 'external-nav' for --vehicle plane: use one of gps-input, gnss-denial"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_option_is_one_clear_line_before_sitl_starts(case, fake_sitl, tmp_path, capsys):
    """Each was a traceback, a thread traceback and a 120 s wait, or SITL dying of a floating point exception."""
    argv, message = CASES[case]
    if "--scenario" in argv or "plane" in argv:
        pytest.importorskip("gymnasium")
    rc, err = _sitl([*argv, "--sitl-bin", str(fake_sitl), "--out", str(tmp_path / "run")], capsys)
    assert rc == 2 and err.startswith("aerial-loc sitl: error: ") and message in err, err
    assert "Traceback" not in err and not (fake_sitl / "runs").exists() and not (tmp_path / "run").exists()


def test_out_on_a_previous_run_is_refused_and_left_as_it_was(fake_sitl, tmp_path, capsys):
    """A previous run's folder was silently replaced (exit 0): now refused before the flight, a free name
    offered, the files untouched."""
    prev = tmp_path / "sitl-run"
    prev.mkdir()
    for name in ("errors.csv", "messages.txt", "summary.json"):
        (prev / name).write_text(f"previous {name}")
    rc, err = _sitl(["--sitl-bin", str(fake_sitl), "--out", str(prev)], capsys)
    assert rc == 2 and f"--out {prev}: holds a previous run's errors.csv, messages.txt, summary.json; a run never " \
                       f"overwrites results: give a new folder (e.g. --out {prev}-2)" in err, err
    assert all((prev / n).read_text() == f"previous {n}" for n in ("errors.csv", "messages.txt", "summary.json"))
    assert not (fake_sitl / "runs").exists()


def test_out_an_existing_file_is_refused_before_the_flight(fake_sitl, tmp_path, capsys):
    """Found only after the whole flight before (nothing written): now before anything starts."""
    mine = tmp_path / "results.txt"
    mine.write_text("mine")
    rc, err = _sitl(["--sitl-bin", str(fake_sitl), "--out", str(mine)], capsys)
    assert rc == 2 and f"--out {mine}: is a file, not a folder" in err, err
    assert mine.read_text() == "mine" and not (fake_sitl / "runs").exists()


@pytest.mark.parametrize("wind", ["5", "x,3", "40,270", "5,270,11", "5,270,1,2", "5,nan", "-1,90"])
def test_wind_option_refuses_a_malformed_value_naming_the_form(wind, fake_sitl, tmp_path, capsys):
    """--wind is checked before SITL starts: a clear error naming the option and its form, exit 2."""
    rc, err = _sitl(["--vehicle", "plane", f"--wind={wind}", "--sitl-bin", str(fake_sitl), "--out",
                     str(tmp_path / "run")], capsys)
    assert rc == 2 and f"--wind {wind!r}" in err and "SPEED,FROM_DEG[,GUST]" in err and "0..30 m/s" in err, err
    assert not (fake_sitl / "runs").exists()


def test_sitl_bin_that_cannot_run_is_refused_by_the_command(fake_sitl, tmp_path, capsys):
    """A binary the kernel refuses ('Exec format error' traceback): the command names the file and the fix."""
    (fake_sitl / "arducopter").write_bytes(b"\x7fELF" + bytes(60))
    rc, err = _sitl(["--sitl-bin", str(fake_sitl), "--out", str(tmp_path / "run")], capsys)
    assert rc == 2 and "--sitl-bin: " in err and "./waf configure --board sitl" in err, err


def test_the_command_and_the_module_reach_the_sitl_package(tmp_path):
    """`aerial-loc sitl` and `python -m aerial_loc_env.sitl` (also `.sitl.cli`) run the same command; an error
    through the module is the same one line and exit status 2."""
    assert COMMANDS["sitl"][0] == "aerial_loc_env.sitl.cli"
    for module in ("aerial_loc_env.sitl", "aerial_loc_env.sitl.cli"):
        out = subprocess.run([sys.executable, "-m", module, "--help"], capture_output=True, text=True, timeout=120)
        assert out.returncode == 0 and "usage: aerial-loc sitl" in out.stdout and "--speedup" in out.stdout, out
        assert "Warning" not in out.stderr, out.stderr
    out = subprocess.run([sys.executable, "-m", "aerial_loc_env.sitl", "--speedup", "0", "--out", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2 and out.stderr.startswith("aerial-loc sitl: error: --speedup 0.0"), out
