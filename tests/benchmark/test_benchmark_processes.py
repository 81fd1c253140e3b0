"""The benchmark among processes: one run per results folder, a doubled trials file, another experiment's
folder, workers that outlive a killed run, the exit status, and the modes of the files written."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aerial_loc_env.benchmark import cli
from aerial_loc_env.benchmark.grid import make_grid
from aerial_loc_env.benchmark.runner import run_grid
from aerial_loc_env.benchmark.store import LOCK_FILE, TrialStore
from aerial_loc_env.errors import ConfigError

TINY = {"id": "AerialLoc/Small-v3", "overrides": {"flight.duration_s": 2.0}, "label": "tiny"}
DR = {"name": "dead-reckoning", "label": "dr"}
LINUX = sys.platform.startswith("linux")


def _grid(name: str = "tiny", seeds: int = 1, agents=(DR,)):
    return make_grid(name, list(agents), [TINY], seeds=seeds)


def _experiment(path: Path, name: str, agent: str, seeds: int, duration_s: float = 2.0) -> Path:
    """An experiment file: one agent on a short Small-v3 episode, no plots."""
    lines = [f'name = "{name}"', f"seeds = {{start = 0, count = {seeds}}}", "plots = []",
             "[[agents]]", f'name = "{agent}"',
             "[[scenarios]]", 'id = "AerialLoc/Small-v3"', f'overrides = {{"flight.duration_s" = {duration_s}}}']
    path.write_text("\n".join(lines) + "\n")
    return path


def _hold_lock(folder: Path) -> subprocess.Popen:
    """Another process holding the folder's run lock (prints 'locked' once it does)."""
    code = ("import sys, time; from aerial_loc_env.benchmark.store import TrialStore; "
            "lock = TrialStore(sys.argv[1]).lock(); lock.acquire(); print('locked', flush=True); time.sleep(60)")
    proc = subprocess.Popen([sys.executable, "-c", code, str(folder)], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "locked"
    return proc


def test_a_second_run_on_a_folder_is_refused_naming_the_first_and_a_dead_ones_lock_is_taken_over(tmp_path):
    out = tmp_path / "out"
    holder = _hold_lock(out)
    try:
        with pytest.raises(ConfigError, match=rf"in use by another benchmark run \(PID {holder.pid}\b"):
            run_grid(_grid(), str(out), progress=False)
        assert not (out / "trials.jsonl").exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
        holder.stdout.close()
    assert (out / LOCK_FILE).read_text().split()[0] == str(holder.pid)   # a dead run's lock is left behind
    rows = run_grid(_grid(), str(out), progress=False)                   # ... and taken over
    assert len(rows) == 1


def test_a_doubled_trials_file_counts_each_trial_once(tmp_path):
    out = tmp_path / "doubled"
    first = run_grid(_grid(seeds=2), str(out), progress=False)
    trials = out / "trials.jsonl"
    trials.write_bytes(trials.read_bytes() * 2)          # what two simultaneous runs left before the lock
    assert len(TrialStore(out).rows()) == 2
    again = run_grid(_grid(seeds=2), str(out), progress=False)
    assert [r["key"] for r in again] == [r["key"] for r in first]
    assert len(json.loads((out / "trials.json").read_text())) == 2
    assert len((out / "trials.csv").read_text().strip().splitlines()) == 1 + 2


def test_another_experiments_folder_is_refused_unless_added_to(tmp_path, capsys):
    out = tmp_path / "shared"
    run_grid(_grid("first"), str(out), progress=False)
    with pytest.raises(ConfigError, match="holds the results of experiment 'first', not 'second'.*--add"):
        run_grid(_grid("second"), str(out), progress=False)
    rows = run_grid(_grid("second", seeds=2), str(out), progress=False, add=True)
    assert [r["seed"] for r in rows] == [0, 1]          # seed 0's trial is the same trial: shared, not re-run
    assert json.loads((out / "experiment.json").read_text()) == {"experiments": ["first", "second"]}
    run_grid(_grid("first"), str(out), progress=False)     # either may run again without --add
    # a folder written before the manifest: its report's title names the experiment
    legacy = tmp_path / "legacy"
    legacy.mkdir()
    (legacy / "report.md").write_text("# table5\n\nold results\n")
    spec = _experiment(tmp_path / "mine.toml", "mine", "dead-reckoning", 1)
    with pytest.raises(ConfigError, match="experiment 'table5', not 'mine'"):
        cli.main([str(spec), "--out", str(legacy), "--quiet", "--no-plots", "--workers", "1"])
    assert (legacy / "report.md").read_text() == "# table5\n\nold results\n"
    assert cli.main([str(spec), "--out", str(legacy), "--quiet", "--no-plots", "--workers", "1", "--add"]) == 0


def test_bench_exits_non_zero_when_trials_failed(tmp_path, capsys):
    spec = _experiment(tmp_path / "failing.toml", "failing", "test_benchmark_run:BrokenAgent", 2)
    code = cli.main([str(spec), "--out", str(tmp_path / "f"), "--quiet", "--no-plots", "--workers", "1"])
    assert code == 1
    assert "2 of 2 trial(s) have no result" in capsys.readouterr().err
    ok = _experiment(tmp_path / "fine.toml", "fine", "dead-reckoning", 2)
    assert cli.main([str(ok), "--out", str(tmp_path / "ok"), "--quiet", "--no-plots", "--workers", "1"]) == 0


@pytest.mark.skipif(not hasattr(os, "fchmod"), reason="file modes are POSIX")
def test_result_files_follow_the_umask(tmp_path):
    spec = _experiment(tmp_path / "modes.toml", "modes", "dead-reckoning", 1)
    out = tmp_path / "modes"
    old = os.umask(0o027)
    try:
        assert cli.main([str(spec), "--out", str(out), "--quiet", "--no-plots", "--workers", "1"]) == 0
    finally:
        os.umask(old)
    modes = {p.name: oct(p.stat().st_mode & 0o777) for p in out.iterdir()}
    assert {"trials.jsonl", "trials.csv", "trials.json", "report.md", "experiment.json"} <= set(modes)
    assert set(modes.values()) == {oct(0o640)}, modes


# ------------------------------------------------------------------------------ workers and their parent
SLOW_AGENT = '''
import time
from aerial_loc_env.estimators.protocol import Agent, prior_estimate


class SlowAgent(Agent):
    """Sleeps on every frame: a long run that costs no CPU."""

    def reset(self, briefing, *, seed=None):
        self.briefing = briefing
        return prior_estimate(briefing)

    def step(self, observation, info=None):
        time.sleep(0.05)
        return prior_estimate(self.briefing)
'''


def _children(pid: int) -> dict[int, str]:
    """pid -> command line of the live (not zombie) children of ``pid``."""
    out = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            cmdline = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if int(fields[1]) == pid and fields[0] != "Z":
            out[int(entry.name)] = cmdline
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return state[state.rindex(")") + 2] != "Z"


@pytest.mark.slow
@pytest.mark.skipif(not LINUX, reason="finds the worker processes through /proc (Linux)")
def test_workers_exit_when_the_run_is_killed(tmp_path):
    (tmp_path / "slowmod.py").write_text(SLOW_AGENT)
    spec = _experiment(tmp_path / "slow.toml", "slow", "slowmod:SlowAgent", 200)
    out = tmp_path / "slow"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.Popen([sys.executable, "-m", "aerial_loc_env.cli", "bench", str(spec), "--out", str(out),
                             "--workers", "2", "--no-plots", "--quiet"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    workers: dict[int, str] = {}
    try:
        deadline = time.monotonic() + 120
        trials = out / "trials.jsonl"
        while time.monotonic() < deadline and proc.poll() is None:
            workers = {p: c for p, c in _children(proc.pid).items() if "spawn_main" in c}
            if len(workers) == 2 and trials.exists() and trials.read_bytes().count(b"\n") >= 2:
                break
            time.sleep(0.05)
        assert proc.poll() is None and len(workers) == 2, \
            f"the run should be busy with 2 workers: {workers}, {proc.stderr.read().decode()[-2000:]}"
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and any(_alive(p) for p in workers):
            time.sleep(0.05)
        assert not [p for p in workers if _alive(p)], "workers outlived the killed run"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
        for pid in workers:           # only what this test started, by pid
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)
