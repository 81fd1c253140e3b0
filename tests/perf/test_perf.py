"""The speed-benchmark harness: ratios to the interleaved floor (no timings asserted, the clock is faked)."""

from __future__ import annotations

import itertools

import pytest

from aerial_loc_env import perf
from aerial_loc_env.perf import FLOOR_NAME, Benchmark, measure
from aerial_loc_env.perf.__main__ import collect


def test_registry_has_one_floor_and_unique_names():
    names = [b.name for b in collect()]
    assert names.count(FLOOR_NAME) == 1
    assert len(names) == len(set(names))
    assert all(b.target_ratio is None or b.target_ratio > 0 for b in collect())


@pytest.mark.parametrize("target, ok", [(5.5, True), (4.5, False), (None, None)])
def test_ratio_is_median_over_interleaved_floor_median(monkeypatch, target, ok):
    calls: list[str] = []       # every call, timed or not
    timed: list[str] = []
    # benchmark calls take 10, 20, 30 ms (two items each); every floor call takes 2 ms, then one slow 50 ms outlier
    bench_times = iter([0.010, 0.020, 0.030])
    floor_times = itertools.chain([0.002] * 8, [0.050])

    def fake_timed(fn):
        timed.append(fn())
        cpu = next(bench_times) if timed[-1] == "bench" else next(floor_times)
        return cpu, 2.0 * cpu     # wall clock: descheduled half of the time

    def call(name):
        return lambda: (calls.append(name), name)[1]

    monkeypatch.setattr(perf, "_timed", fake_timed)
    bench = Benchmark("b", lambda: call("bench"), target_ratio=target, repeats=3, per_call_items=2)
    r = measure(bench, call("floor"))
    warm, n = perf._FLOOR_WARMUP_CALLS, perf._FLOOR_CALLS_PER_CALL
    assert calls == ["bench"] + (["bench"] + ["floor"] * (warm + n)) * 3  # one untimed warm-up of the benchmark
    assert timed == (["bench"] + ["floor"] * n) * 3                        # floor warm-up calls are not timed
    assert r["median_s"] == pytest.approx(0.010)                 # 20 ms / 2 items
    assert r["wall_median_s"] == pytest.approx(0.020)
    assert r["floor_s"] == pytest.approx(0.002)                  # the outlier does not move the median
    assert r["ratio"] == pytest.approx(0.010 / 0.002)            # median of 2.5, 5 and 7.5
    assert r["ok"] is ok


def test_without_floor_there_is_no_ratio(monkeypatch):
    monkeypatch.setattr(perf, "_timed", lambda fn: (fn(), (0.004, 0.005))[1])
    r = measure(Benchmark("b", lambda: (lambda: None), target_ratio=1.0, repeats=4))
    assert r["ratio"] is None and r["ok"] is None and r["median_s"] == pytest.approx(0.004)


def test_ratio_pairs_each_call_with_the_floor_right_after_it(monkeypatch):
    """Load doubles midway: calls and floors both slow down; per-call ratios stay 3, a ratio of medians would not."""
    seq = iter([0.003, *[0.001] * 3, 0.003, *[0.001] * 3, 0.006, *[0.002] * 3, 0.006, *[0.002] * 3,
                0.006, *[0.002] * 3])
    monkeypatch.setattr(perf, "_timed", lambda fn: (fn(), (t := next(seq), t))[1])
    r = measure(Benchmark("b", lambda: (lambda: None), repeats=5), lambda: None)
    assert r["ratio"] == pytest.approx(3.0)
    assert r["median_s"] / r["floor_s"] == pytest.approx(3.0)   # here both agree; now make the floor lag the load
    seq = iter([0.003, *[0.001] * 3, 0.003, *[0.001] * 3, 0.006, *[0.002] * 3, 0.006, *[0.002] * 3,
                0.006, *[0.001] * 3])
    r = measure(Benchmark("b", lambda: (lambda: None), repeats=5), lambda: None)
    assert r["ratio"] == pytest.approx(3.0)
    assert r["median_s"] / r["floor_s"] == pytest.approx(6.0)


def test_wall_clock_rows_and_their_rate_over_a_baseline(monkeypatch):
    """Work spread over processes is timed by the wall clock (its CPU time is elsewhere) and compared with its
    baseline, one baseline call timed after each call: rate / the baseline's rate, judged against baseline_target."""
    from aerial_loc_env.perf.__main__ import Baselines, _row

    def fake_timed(fn):
        return (0.001, 0.004) if fn() == "one" else (0.001, 0.005)          # CPU 1 ms a call; wall 4 / 5 ms

    monkeypatch.setattr(perf, "_timed", fake_timed)
    one = Benchmark("one", lambda: (lambda: "one"), repeats=3, per_call_items=2, clock="wall")
    baselines = Baselines([one])
    assert baselines.get(None) is None
    for target, verdict in ((1.5, "yes"), (2.0, "NO")):
        vec = Benchmark("vec", lambda: (lambda: "vec"), repeats=3, per_call_items=4, clock="wall", baseline="one",
                        baseline_target=target)
        r = measure(vec, None, baselines.get(vec.baseline))
        assert r["median_s"] == pytest.approx(0.00125) and r["clock"] == "wall"
        assert r["vs_baseline"] == pytest.approx(0.002 / 0.00125)            # 1.6x the baseline's rate
        assert _row(r).endswith(f"(wall)  1.60x one (>= {target:g}x: {verdict})")
    cpu = measure(Benchmark("cpu", lambda: (lambda: "cpu"), repeats=3))
    assert cpu["median_s"] == pytest.approx(0.001) and cpu["vs_baseline"] is None


def test_a_baseline_is_paired_call_by_call(monkeypatch):
    """Load doubles midway through a row: its calls and the baseline calls right after them slow down alike, so the
    paired figure stays 2x where a ratio of the two rows' medians (the baseline timed before the load) would not."""
    slow = iter([False] * 2 + [True] * 3)       # the load arrives after the second call of the row

    def fake_timed(fn):
        kind = fn()
        if kind == "vec":
            load = 2.0 if next(slow) else 1.0
            fake_timed.load = load
            return 0.0, 0.004 * load             # 4 items: 1 ms an item
        return 0.0, 0.004 * getattr(fake_timed, "load", 1.0)   # one: 2 items, 2 ms an item

    monkeypatch.setattr(perf, "_timed", fake_timed)
    one = Benchmark("one", lambda: (lambda: "one"), repeats=5, per_call_items=2, clock="wall")
    vec = Benchmark("vec", lambda: (lambda: "vec"), repeats=5, per_call_items=4, clock="wall", baseline="one")
    from aerial_loc_env.perf.__main__ import Baselines

    r = measure(vec, None, Baselines([one]).get("one"))
    assert r["vs_baseline"] == pytest.approx(2.0)
    assert 0.002 / r["median_s"] == pytest.approx(1.0)   # the baseline's quiet median over the row's loaded one


@pytest.mark.slow
def test_the_header_names_the_code_the_kernels_are_compiled_for(tmp_path):
    """``make bench``'s header says which instructions the kernels use (``sysinfo.isa``: the target CPU, its vector
    sets, the CPU-specific paths), and its JSON keeps it: AVX2 and AVX-512 figures are told apart."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from aerial_loc_env.sysinfo import isa

    out = tmp_path / "bench.json"
    r = subprocess.run([sys.executable, "-m", "aerial_loc_env.perf", "no benchmark has this name", "--json", str(out)],
                       cwd=Path(__file__).resolve().parents[2], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[1] == f"compiled kernels: {isa()}"
    assert json.loads(out.read_text())["isa"] == isa()


@pytest.mark.slow
@pytest.mark.skipif(__import__("platform").machine().lower() not in ("x86_64", "amd64"),
                    reason="--avx2 emulates an x86-64 AVX2 CPU")
def test_avx2_runs_in_a_process_that_computes_as_an_avx2_machine(tmp_path):
    """``--avx2`` (``make bench-avx2``) runs the benchmarks in a new process under ``sysinfo.avx2_env``: the header
    names znver3's own code for the kernels and the libraries' paths left out, and the JSON keeps the ISA."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from shared_helpers import host_env

    env = host_env()
    env["XDG_CACHE_HOME"] = str(tmp_path / "cache")      # (its numba cache: kept apart from the native one)
    out = tmp_path / "bench.json"
    r = subprocess.run([sys.executable, "-m", "aerial_loc_env.perf", "no benchmark has this name", "--avx2", "--json",
                        str(out)], cwd=Path(__file__).resolve().parents[2], env=env, capture_output=True, text=True,
                       timeout=600)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert lines[1].startswith("compiled kernels: znver3 (NUMBA_CPU_NAME") and "FAST_GATHER False" in lines[1]
    assert lines[2].startswith("libraries as on an AVX2 CPU (--avx2): NumPy without ")
    assert "OpenBLAS Haswell" in lines[2]
    assert json.loads(out.read_text())["isa"].startswith("znver3 (NUMBA_CPU_NAME")
    assert (tmp_path / "cache" / "aerial_loc_env" / "numba-avx2").is_dir()
