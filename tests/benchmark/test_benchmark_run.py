"""The benchmark end to end on tiny grids: the CLI, resume after SIGKILL, determinism, local vs Ray."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from aerial_loc_env.benchmark import cli
from aerial_loc_env.benchmark.grid import load_grid, make_grid
from aerial_loc_env.benchmark.metrics import TIMING_COLUMNS
from aerial_loc_env.benchmark.runner import rerun_row, run_grid
from aerial_loc_env.benchmark.store import TrialStore
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.protocol import Agent, Estimate, prior_estimate

# A tiny episode: the small city, 3 s at 4 Hz (13 frames), few particles.
TINY = {"id": "AerialLoc/Small-v3", "overrides": {"flight.duration_s": 3.0}, "label": "tiny"}
MCL = {"name": "mcl-shadow-aware", "params": {"n_particles": 150}, "label": "sa"}


def _comparable(rows: list[dict]) -> dict[str, dict]:
    """Rows by key without the wall-clock columns (the only ones allowed to differ between runs)."""
    return {r["key"]: {k: v for k, v in r.items() if k not in TIMING_COLUMNS} for r in rows}


def _tiny_grid(name: str = "tiny", seeds: int = 2, **options):
    agents = options.pop("agents", [MCL, {"name": "dead-reckoning", "label": "dr"}])
    return make_grid(name, agents, [TINY], seeds=seeds, **options)


def _write_experiment(path: Path, seeds: int, duration_s: float = 3.0, n_particles: int = 150) -> Path:
    path.write_text(f"""
name = "tinyexp"
description = "tiny end-to-end experiment"
seeds = {{start = 0, count = {seeds}}}
paper = ["table5"]
plots = ["error_vs_time", "rmse_vs_n_pairs"]

[[agents]]
name = "mcl-shadow-aware"
label = "sa"
params = {{n_particles = {n_particles}}}
sweep = {{"measurement_params.n_pairs" = [10, 40]}}

[[agents]]
name = "dead-reckoning"

[[scenarios]]
id = "AerialLoc/Small-v3"
overrides = {{"flight.duration_s" = {duration_s}}}
""")
    return path


def test_cli_tiny_experiment_end_to_end(tmp_path, capsys):
    spec = _write_experiment(tmp_path / "tinyexp.toml", seeds=2)
    out = tmp_path / "out"
    assert cli.main([str(spec), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "| tinyexp" not in printed and "sa n_pairs=10" in printed and "Table 5" in printed
    rows = json.loads((out / "trials.json").read_text())
    assert len(rows) == 3 * 2
    n_frames = 13
    for r in rows:
        assert len(r["errors_m"]) == len(r["t_s"]) == r["steps"] == n_frames
        assert r["rmse_m"] == pytest.approx(np.sqrt(np.mean(np.square(r["errors_m"]))), rel=1e-3)
        assert r["scenario_config"]["flight"]["duration_s"] == 3.0 and r["agent_config"]["class"]
    swept = {r["agent"]: r["agent_config"]["params"]["measurement_params"]["n_pairs"] for r in rows
             if r["agent"].startswith("sa")}
    assert swept == {"sa n_pairs=10": 10, "sa n_pairs=40": 40}
    csv_lines = (out / "trials.csv").read_text().strip().splitlines()
    assert len(csv_lines) == 1 + 6 and "agent_spec" in csv_lines[0] and "version" in csv_lines[0]
    report = (out / "report.md").read_text()
    assert "## Table 5" in report and "![error against time" in report
    for png in ("error_vs_time.png", "rmse_vs_n_pairs.png"):
        assert (out / png).stat().st_size > 1000


def test_same_seed_same_rows_and_rows_rerun(tmp_path):
    grid = _tiny_grid(seeds=2)
    a = run_grid(grid, str(tmp_path / "a"), workers=1, progress=False)
    b = run_grid(grid, str(tmp_path / "b"), workers=1, progress=False)
    assert len(a) == 4 and _comparable(a) == _comparable(b)
    # another seed gives another episode
    assert a[0]["errors_m"] != a[1]["errors_m"]
    # any stored row can be re-run from its specs alone
    again = rerun_row(json.loads(json.dumps(a[0])))
    assert _comparable([again]) == _comparable([a[0]])


@pytest.mark.slow
def test_parallel_workers_give_the_same_rows_and_resume_skips_done(tmp_path):
    grid = _tiny_grid(seeds=3)
    serial = run_grid(grid, str(tmp_path / "serial"), workers=1, progress=False)
    parallel = run_grid(grid, str(tmp_path / "par"), workers=2, progress=False)
    assert _comparable(serial) == _comparable(parallel)

    def refuse(tasks, on_result, workers):
        raise AssertionError(f"nothing should run again, got {len(tasks)} episodes")

    again = run_grid(grid, str(tmp_path / "par"), executor=refuse, progress=False)
    assert _comparable(again) == _comparable(serial)


def test_grid_growth_runs_only_the_missing_trials(tmp_path):
    out = str(tmp_path / "grow")
    run_grid(_tiny_grid(seeds=1), out, workers=1, progress=False)
    before = (Path(out) / "trials.jsonl").read_bytes()
    seen: list[int] = []

    def counting(tasks, on_result, workers):
        from aerial_loc_env.benchmark.executors import local_executor

        seen.extend(len(t.agents) for t in tasks)
        local_executor(tasks, on_result, 1)

    rows = run_grid(_tiny_grid(seeds=2), out, executor=counting, progress=False)
    assert seen == [2] and len(rows) == 4            # only seed 1's episode, with both agents
    assert (Path(out) / "trials.jsonl").read_bytes().startswith(before)  # nothing on disk rewritten


@pytest.mark.slow
def test_kill_mid_run_then_resume_loses_nothing(tmp_path):
    spec = _write_experiment(tmp_path / "tinyexp.toml", seeds=8, duration_s=6.0, n_particles=300)
    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "aerial_loc_env.cli", "bench", str(spec), "--out", str(out),
           "--workers", "1", "--no-plots", "--quiet"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)
    trials = out / "trials.jsonl"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if trials.exists() and trials.read_bytes().count(b"\n") >= 1:
            break
        time.sleep(0.02)
    assert proc.poll() is None, f"the run ended before the kill: {proc.stderr.read().decode()[-2000:]}"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    before = trials.read_bytes()
    kept = TrialStore(out).rows()
    assert 1 <= len(kept) < 3 * 8, "the kill should land after the first episode and before the last"

    done = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert trials.read_bytes().startswith(before)      # the first run's rows are still there, untouched
    resumed = TrialStore(out).rows()
    keys = [r["key"] for r in resumed]
    assert len(keys) == len(set(keys)) == 3 * 8        # nothing lost, nothing run twice
    for r in kept:                                     # the killed run's rows are kept as they were
        assert _comparable([r]) == _comparable([next(x for x in resumed if x["key"] == r["key"])])

    full = run_grid(load_grid(spec), str(tmp_path / "uninterrupted"), workers=1, progress=False)
    assert _comparable(resumed) == _comparable(full)


@pytest.mark.slow
def test_ray_executor_gives_the_same_rows_as_local(tmp_path):
    pytest.importorskip("ray", reason="Ray is an optional extra (pip install 'aerial-loc-env[ray]'); "
                                      "the Ray executor test needs it")
    grid = _tiny_grid(seeds=2)
    local = run_grid(grid, str(tmp_path / "local"), workers=1, progress=False)
    ray_rows = run_grid(grid, str(tmp_path / "ray"), workers=2, executor="ray", progress=False)
    assert _comparable(local) == _comparable(ray_rows)


class BrokenAgent(Agent):
    """Raises on its third step: the other agents of the episode must still finish."""

    def reset(self, briefing, *, seed=None) -> Estimate:
        self.briefing, self.n = briefing, 0
        return prior_estimate(briefing)

    def step(self, observation, info=None) -> Estimate:
        self.n += 1
        if self.n == 3:
            raise RuntimeError("deliberate failure")
        return prior_estimate(self.briefing)


def test_a_failing_agent_is_logged_and_retried_not_stored(tmp_path):
    grid = _tiny_grid(seeds=1, agents=[f"{__name__}:BrokenAgent", {"name": "dead-reckoning", "label": "dr"}])
    rows = run_grid(grid, str(tmp_path / "f"), workers=1, progress=False)
    assert [r["agent"] for r in rows] == ["dr"]
    failures = [json.loads(line) for line in (tmp_path / "f" / "failures.jsonl").read_text().splitlines()]
    assert len(failures) == 1 and failures[0]["stage"] == "step 2"
    assert "deliberate failure" in failures[0]["error"]
    run_grid(grid, str(tmp_path / "f"), workers=1, progress=False)   # a re-run tries the failed trial again
    assert len((tmp_path / "f" / "failures.jsonl").read_text().splitlines()) == 2


def test_bad_specs_fail_before_any_episode(tmp_path):
    with pytest.raises(ConfigError, match="no-such-agent"):
        run_grid(_tiny_grid(agents=["no-such-agent"]), str(tmp_path / "x"), progress=False)
    with pytest.raises(ConfigError, match="n_particles"):
        run_grid(_tiny_grid(agents=[{"name": "mcl-shadow-aware", "params": {"n_particles": -1}}]),
                 str(tmp_path / "x"), progress=False)
    assert not (tmp_path / "x" / "trials.jsonl").exists()


def test_track_and_likelihood_plots(tmp_path):
    from aerial_loc_env.benchmark import plots
    from aerial_loc_env.benchmark.grid import AgentEntry, ScenarioEntry

    scen = ScenarioEntry(TINY["id"], TINY["overrides"], "tiny")
    flat = ScenarioEntry(TINY["id"], {**TINY["overrides"], "shadows.strength_range": [0.0, 0.0]},
                         "no shadows")
    agent = AgentEntry("mcl-shadow-aware", {"n_particles": 100}, "sa")
    assert plots.track_plot(scen, 0, agent, tmp_path / "track.png").stat().st_size > 1000
    surf = plots.likelihood_surface(agent, flat, 0, radius_m=10.0, step_m=2.0)
    assert surf["log_likelihood"].shape == (11, 11) and np.isfinite(surf["log_likelihood"]).all()
    assert plots.likelihood_surface(AgentEntry("dead-reckoning"), flat, 0) is None
    png = plots.likelihood_plot([agent, AgentEntry("dead-reckoning")], [scen, flat], 0, tmp_path / "lik.png",
                                radius_m=10.0, step_m=2.0)
    assert png.stat().st_size > 1000


def test_bench_out_that_cannot_be_created(tmp_path, capsys):
    from aerial_loc_env.cli import main

    blocker = tmp_path / "file"
    blocker.write_text("x")
    rc = main(["bench", "--quiet", "--no-plots", "--seeds", "1", "--out", str(blocker / "sub")])
    err = capsys.readouterr().err
    assert rc != 0 and "Traceback" not in err and "--out" in err and str(blocker / "sub") in err, err


def test_bench_refuses_unusable_map_before_running(tmp_path, capsys):
    from aerial_loc_env.cli import main

    exp = tmp_path / "exp.toml"
    exp.write_text('name = "m"\nagents = ["dead-reckoning"]\nseeds = 2\n[[scenarios]]\nid = "AerialLoc/RealMap-v2"\n'
                   'overrides = {"map.path" = "nowhere.tif"}\n')
    rc = main(["bench", str(exp), "--quiet", "--no-plots", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc != 0 and "nowhere.tif" in err and "Traceback" not in err, err
    assert not (tmp_path / "out" / "trials.jsonl").exists()


def test_track_plot_on_a_map_read_by_window(tmp_path):
    """The track picture on a map read by window draws the map from the file's tiles (never its whole layer,
    which a RasterMap refuses to load): the map under the track is there, not a blank canvas."""
    from aerial_loc_env.benchmark import plots
    from aerial_loc_env.benchmark.grid import AgentEntry, ScenarioEntry
    from aerial_loc_env.perf.bigmap import SyntheticMap
    from aerial_loc_env.world.maps.cog import write_cog

    cog = write_cog(SyntheticMap(1600), tmp_path / "synthetic.cog.tif")
    scen = ScenarioEntry("AerialLoc/RealMap-v2", {"map.path": str(cog), "map.read": "window",
                                                  "flight.duration_s": 3.0}, "windowed")
    png = plots.track_plot(scen, 0, AgentEntry("dead-reckoning"), tmp_path / "track.png", max_px=300)
    import cv2

    image = cv2.imread(str(png))
    assert image is not None and image.std() > 10.0
