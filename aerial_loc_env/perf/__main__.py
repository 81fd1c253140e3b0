"""``python -m aerial_loc_env.perf [filter ...] [--json FILE] [--avx2]``: run the speed benchmarks, print a table of
medians and their ratios to the floor (one bare map warp, timed interleaved with each benchmark); ``--avx2``: in a
process that computes as an AVX2 machine without AVX-512 does (``sysinfo.avx2_env``), on any x86-64 host."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import pkgutil
import sys

from aerial_loc_env.perf import FLOOR_NAME, Benchmark, load, machine, measure, single_core
from aerial_loc_env.sysinfo import isa


def collect() -> list[Benchmark]:
    import aerial_loc_env.perf as pkg

    out: list[Benchmark] = []
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{pkg.__name__}.{info.name}")
        out.extend(getattr(mod, "BENCHMARKS", []))
    return out


class Baselines:
    """The baseline benchmarks' functions, each set up once when a row first names it (``measure`` times one call
    of it after each of the row's calls): ``get(name)`` -> (function, items per call), None for no baseline."""

    def __init__(self, benches: list[Benchmark]) -> None:
        self._benches = {b.name: b for b in benches}
        self._fns: dict[str, tuple] = {}

    def get(self, name: str | None) -> tuple | None:
        if name is None:
            return None
        if name not in self._fns:
            base = self._benches[name]
            fn = base.setup()
            fn()  # warm-up
            self._fns[name] = (fn, base.per_call_items)
        return self._fns[name]


def _row(r: dict) -> str:
    ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}x"
    tgt = "-" if r["target_ratio"] is None else f"<= {r['target_ratio']:g}x"
    ok = "-" if r["ok"] is None else ("yes" if r["ok"] else "NO")
    line = (f"{r['name']:66s} {ratio:>9s} {tgt:>10s} {ok:>3s}  {r['median_s'] * 1e3:10.3f} ms "
            f"{r['p95_s'] * 1e3:10.3f} ms {r['wall_median_s'] * 1e3:10.3f} ms {r['rate_per_s']:10.1f} /{r['unit']}")
    if r.get("clock") == "wall":
        line += " (wall)"
    if r.get("vs_baseline") is not None:
        line += f"  {r['vs_baseline']:.2f}x {r['baseline']}"
        if r["baseline_target"] is not None:
            line += f" (>= {r['baseline_target']:g}x: {'yes' if r['vs_baseline'] >= r['baseline_target'] else 'NO'})"
    return line


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m aerial_loc_env.perf", description=__doc__)
    ap.add_argument("filters", nargs="*", help="run only benchmarks whose name contains one of these")
    ap.add_argument("--json", help="also write the results to this JSON file")
    ap.add_argument("--avx2", action="store_true",
                    help="run as an AVX2 machine without AVX-512 does (numba, NumPy, OpenCV, OpenBLAS; x86-64 only)")
    args = ap.parse_args(argv)
    if args.avx2 and os.environ.get("AERIAL_LOC_AVX2") != "1":     # the libraries read it at import: a new process
        from aerial_loc_env.paths import cache_dir
        from aerial_loc_env.sysinfo import avx2_env

        rest = [a for a in (sys.argv[1:] if argv is None else argv) if a != "--avx2"]
        env = {**os.environ, **avx2_env(str(cache_dir("numba-avx2"))), "AERIAL_LOC_AVX2": "1"}
        os.execve(sys.executable, [sys.executable, "-m", "aerial_loc_env.perf", *rest], env)
    single_core()
    benches = collect()
    floor = next(b for b in benches if b.name == FLOOR_NAME)
    chosen = [b for b in benches if not args.filters or any(f in b.name for f in args.filters)]
    floor_fn = floor.setup()
    start_load = load()
    print(f"machine: {machine()} (one core: OMP_NUM_THREADS=1, cv2.setNumThreads(1)); {start_load} at start")
    print(f"compiled kernels: {isa()}")
    if os.environ.get("AERIAL_LOC_AVX2") == "1":
        env = os.environ
        print(f"libraries as on an AVX2 CPU (--avx2): NumPy without {env.get('NPY_DISABLE_CPU_FEATURES') or '-'}, "
              f"OpenBLAS {env.get('OPENBLAS_CORETYPE')}, OpenCV without {env.get('OPENCV_CPU_DISABLE') or '-'}, "
              f"torch {env.get('ATEN_CPU_CAPABILITY')}")
    print(f"ratio = median CPU time per item / median CPU time of the floor ('{FLOOR_NAME}': one bilinear warp "
          "of the frame from the map) timed interleaved with it")
    print(f"{'benchmark':66s} {'ratio':>9s} {'target':>10s} {'ok':>3s}  {'median CPU':>13s} {'p95 CPU':>13s} "
          f"{'median wall':>13s} {'rate (CPU)':>12s}")
    rows = []
    baselines = Baselines(benches)
    for b in chosen:
        r = measure(b, floor_fn, baselines.get(b.baseline))
        rows.append(r)
        print(_row(r), flush=True)
    floors = [r["floor_s"] for r in rows if r["floor_s"]]
    end_load = load()
    if floors:
        print(f"floor medians across the run: {min(floors) * 1e3:.3f} .. {max(floors) * 1e3:.3f} ms; "
              f"{end_load} at the end")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": machine(), "isa": isa(), "load_start": start_load, "load_end": end_load,
                       "floor": FLOOR_NAME, "results": rows}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
