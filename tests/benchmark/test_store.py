"""The results folder (``benchmark/store.py``): what it refuses about a folder, before any work starts, and how."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from aerial_loc_env.benchmark import cli, runner
from aerial_loc_env.benchmark.grid import make_grid
from aerial_loc_env.benchmark.store import LOCK_FILE, MANIFEST_FILE, TRIALS_FILE, RunLock, TrialStore
from aerial_loc_env.errors import ConfigError

GRID = make_grid("tiny", ["dead-reckoning"], [{"id": "AerialLoc/Small-v3", "overrides": {"flight.duration_s": 2}}],
                 seeds=1)


@pytest.fixture
def no_work(monkeypatch: pytest.MonkeyPatch) -> None:
    """Resolving the specs or building the scenarios fails the test: a bad folder must be refused first."""
    def forbidden(*_args, **_kwargs):
        raise AssertionError("work started before the results folder was checked")

    monkeypatch.setattr(runner, "resolve_grid", forbidden)
    monkeypatch.setattr(cli, "check_scenarios", forbidden)


@pytest.mark.parametrize("line", ["[1, 2]", "5", '"a string"', "null"])
def test_a_line_that_is_json_but_not_a_row_is_named_with_its_line_number(tmp_path: Path, line: str,
                                                                         no_work: None) -> None:
    (tmp_path / TRIALS_FILE).write_text('{"key": "a", "rmse_m": 1.0}\n' + line + "\n")
    with pytest.raises(ConfigError, match=rf"{TRIALS_FILE}, line 2: .* is not a trial row.*delete that line"):
        runner.run_grid(GRID, str(tmp_path), progress=False)
    assert (tmp_path / TRIALS_FILE).read_text().endswith(line + "\n")     # the file is left as it was


def test_garbled_bytes_count_as_a_torn_line(tmp_path: Path) -> None:
    (tmp_path / TRIALS_FILE).write_bytes(b'{"key": "a"}\n{"key": "\xff\xfe\n{"key": "c"}\n')
    assert [r["key"] for r in TrialStore(tmp_path).rows()] == ["a", "c"]


@pytest.mark.parametrize("name", [TRIALS_FILE, LOCK_FILE, MANIFEST_FILE, "report.md", "trials.csv"])
def test_a_folder_where_a_run_file_belongs_is_refused_before_the_run(tmp_path: Path, name: str,
                                                                     no_work: None) -> None:
    (tmp_path / name).mkdir()
    with pytest.raises(ConfigError, match=rf"'{tmp_path / name}' is a folder .*move it out of the way"):
        runner.run_grid(GRID, str(tmp_path), progress=False)
    assert (tmp_path / name).is_dir()


def test_a_lock_file_that_cannot_be_opened_is_a_clear_error(tmp_path: Path) -> None:
    (tmp_path / LOCK_FILE).mkdir()
    with pytest.raises(ConfigError, match="cannot open the lock file"):
        RunLock(tmp_path / LOCK_FILE).acquire()


def test_the_cli_checks_the_folder_before_building_the_scenarios(tmp_path: Path, no_work: None,
                                                                 capsys: pytest.CaptureFixture) -> None:
    (tmp_path / TRIALS_FILE).write_text("[1, 2]\n")
    with pytest.raises(ConfigError, match="line 1: \\[1, 2\\] is not a trial row"):
        cli.main(["default", "--out", str(tmp_path), "--quiet", "--no-plots"])


def test_a_manifest_naming_one_experiment_as_a_string_is_that_one_name(tmp_path: Path, no_work: None) -> None:
    """``{"experiments": "dr2"}`` is the experiment 'dr2', not 'd', 'r', '2'."""
    (tmp_path / MANIFEST_FILE).write_text('{"experiments": "dr2"}')
    store = TrialStore(tmp_path)
    with pytest.raises(ConfigError, match=r"holds the results of experiment 'dr2', not 'tiny'"):
        runner.run_grid(GRID, str(tmp_path), progress=False)
    store.claim("dr2")                                          # its own experiment: accepted, left as written
    assert (tmp_path / MANIFEST_FILE).read_text() == '{"experiments": "dr2"}'
    store.claim("tiny", add=True)
    assert json.loads((tmp_path / MANIFEST_FILE).read_text()) == {"experiments": ["dr2", "tiny"]}


@pytest.mark.parametrize("text", ['{"experiments": 5}', '{"experiments": {"a": 1}}', '{"experiments": [1, 2]}',
                                  '{"experiments": [""]}', "[1]", "{}"])
def test_a_manifest_that_is_not_a_list_of_names_is_refused(tmp_path: Path, text: str) -> None:
    (tmp_path / MANIFEST_FILE).write_text(text)
    with pytest.raises(ConfigError, match=rf"{MANIFEST_FILE}: .*\{{\"experiments\": \[\"<name>\", \.\.\.\]\}}"):
        TrialStore(tmp_path).check("tiny")
    assert (tmp_path / MANIFEST_FILE).read_text() == text
