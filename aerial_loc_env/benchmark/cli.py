"""``aerial-loc bench [EXPERIMENT]``: run an experiment grid, print the table, write CSV/JSON, a Markdown report
and plots. With no argument it runs the default comparison on the embedded procedural city."""

from __future__ import annotations

import argparse
import dataclasses
import os
from pathlib import Path

from ..perf import machine
from .grid import available_experiments, load_grid
from .report import markdown_report, summarize, summary_table
from .runner import run_grid


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="aerial-loc bench", description=__doc__)
    ap.add_argument("experiment", nargs="?", default="default",
                    help=f"an experiment name ({', '.join(available_experiments())}) or a TOML path")
    ap.add_argument("--out", help="results folder (default results/<experiment>); finished trials there are kept "
                                  "and skipped, never overwritten")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="parallel processes (default: cores)")
    ap.add_argument("--executor", default="local", choices=("local", "ray"), help="where episodes run")
    ap.add_argument("--seeds", type=int, help="use only the first N seeds of the experiment")
    ap.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    ap.add_argument("--list", action="store_true", help="list the experiments and exit")
    args = ap.parse_args(argv)
    if args.list:
        for name in available_experiments():
            g = load_grid(name)
            print(f"{name:18s} {g.trials():6d} trials  {g.description}")
        return 0
    grid = load_grid(args.experiment)
    if args.seeds:
        grid = dataclasses.replace(grid, seeds=grid.seeds[: args.seeds])
    out = Path(args.out or Path("results") / grid.name)
    print(f"{grid.name}: {len(grid.agents)} agents x {len(grid.scenarios)} scenarios x {len(grid.seeds)} seeds "
          f"= {grid.trials()} trials -> {out}/", flush=True)
    rows = run_grid(grid, str(out), workers=args.workers, executor=args.executor)
    print()
    print(summary_table(summarize(rows)))
    write_report(grid, rows, out, plots=not args.no_plots)
    print(f"\nreport: {out / 'report.md'}; rows: {out / 'trials.csv'}")
    return 0


def write_report(grid, rows, out: Path, *, plots: bool = True) -> Path:
    sections = []
    if plots:
        from . import plots as pl

        png = pl.error_vs_time(rows, out / "error_vs_time.png", grid.description)
        sections.append(f"![error against time]({png.name})\n")
        for plot in grid.plots:
            if plot.startswith("rmse_vs_"):
                param = plot[len("rmse_vs_"):]
                png = pl.rmse_vs_param(rows, param, out / f"{plot}.png", grid.description)
                sections.append(f"![RMSE against {param}]({png.name})\n")
    from .report import paper_sections

    sections = paper_sections(grid.name, rows) + sections
    text = markdown_report(grid.name, grid.description, rows, machine(), sections)
    path = out / "report.md"
    from ..paths import atomic_write_bytes

    atomic_write_bytes(path, text.encode())
    return path
