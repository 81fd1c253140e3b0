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
    assert r["ratio"] == pytest.approx(0.010 / 0.002)
    assert r["ok"] is ok


def test_without_floor_there_is_no_ratio(monkeypatch):
    monkeypatch.setattr(perf, "_timed", lambda fn: (fn(), (0.004, 0.005))[1])
    r = measure(Benchmark("b", lambda: (lambda: None), target_ratio=1.0, repeats=4))
    assert r["ratio"] is None and r["ok"] is None and r["median_s"] == pytest.approx(0.004)
