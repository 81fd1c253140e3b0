"""``python -m aerial_loc_env.perf [filter ...] [--json FILE]``: run the speed benchmarks, print a table."""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import sys

from . import Benchmark, machine, measure, single_core


def collect() -> list[Benchmark]:
    import aerial_loc_env.perf as pkg

    out: list[Benchmark] = []
    for info in sorted(pkgutil.iter_modules(pkg.__path__), key=lambda m: m.name):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{pkg.__name__}.{info.name}")
        out.extend(getattr(mod, "BENCHMARKS", []))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m aerial_loc_env.perf", description=__doc__)
    ap.add_argument("filters", nargs="*", help="run only benchmarks whose name contains one of these")
    ap.add_argument("--json", help="also write the results to this JSON file")
    args = ap.parse_args(argv)
    single_core()
    benches = [b for b in collect() if not args.filters or any(f in b.name for f in args.filters)]
    print(f"machine: {machine()} (one core: OMP_NUM_THREADS=1, cv2.setNumThreads(1))")
    print(f"{'benchmark':58s} {'median':>12s} {'p95':>12s} {'rate':>14s} {'target':>12s}  ok")
    rows = []
    for b in benches:
        r = measure(b)
        rows.append(r)
        tgt = "-" if r["target_s"] is None else f"{r['target_s'] * 1e3:.2f} ms"
        ok = "-" if r["ok"] is None else ("yes" if r["ok"] else "NO")
        print(f"{r['name']:58s} {r['median_s'] * 1e3:9.3f} ms {r['p95_s'] * 1e3:9.3f} ms "
              f"{r['rate_per_s']:9.1f} /{r['unit']:4s} {tgt:>12s}  {ok}", flush=True)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"machine": machine(), "results": rows}, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
