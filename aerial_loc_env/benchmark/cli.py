"""``aerial-loc bench [EXPERIMENT]``: run an experiment grid, print the table, write CSV/JSON, a Markdown
report and plots. With no argument it runs the default comparison on the embedded procedural city: the paper's
setting (AerialLoc/PaperShadows-v2) beside the realistic map-camera gap (AerialLoc/RealisticPaper-v3).

Results go to ``results/<experiment>/`` (``--out``): ``trials.jsonl`` (the source of truth, appended as each
episode ends), ``trials.csv`` / ``trials.json`` (derived), ``report.md`` and PNG plots. A re-run skips the
trials already there, so an interrupted run resumes where it stopped. One run at a time per folder; a folder
holding another experiment's results is refused unless ``--add``.

Exit status: 0 when every trial of the experiment has a row, 1 when trials failed (see failures.jsonl; a
re-run retries them), 2 for a bad experiment, option or folder."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from aerial_loc_env.benchmark.grid import Grid, ScenarioEntry, available_experiments, check_scenarios, load_grid
from aerial_loc_env.benchmark.report import detector_table, markdown_report, paper_sections, summarize, summary_table
from aerial_loc_env.benchmark.runner import run_grid
from aerial_loc_env.benchmark.store import TrialStore
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.sysinfo import machine


def _default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover (not Linux)
        return os.cpu_count() or 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="aerial-loc bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("experiment", nargs="?", default="default",
                    help=f"an experiment name ({', '.join(available_experiments())}) or a TOML path")
    ap.add_argument("--out", help="results folder (default results/<experiment>); finished trials there are "
                                  "kept and skipped, never overwritten")
    ap.add_argument("--add", action="store_true",
                    help="add this experiment's trials to an --out folder that holds another experiment's results")
    ap.add_argument("--workers", type=int, default=_default_workers(),
                    help="parallel processes (default: the usable cores)")
    ap.add_argument("--executor", default="local", choices=("local", "ray"),
                    help="where episodes run: local processes, or Ray (RAY_ADDRESS or a local instance)")
    ap.add_argument("--seeds", type=int, metavar="N", help="use only the first N seeds of the experiment")
    ap.add_argument("--detector-quality", action="store_true",
                    help="score the image shadow detector against the simulator's masks (a report section)")
    ap.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    ap.add_argument("--list", action="store_true", help="list the experiments and exit")
    args = ap.parse_args(argv)
    if args.list:
        for name in available_experiments():
            g = load_grid(name)
            print(f"{name:14s} {g.trials():6d} trials ({g.episodes()} episodes)  {g.description}")
        return 0
    if args.workers < 1:
        ap.error(f"--workers {args.workers}: need at least 1")
    grid = load_grid(args.experiment)
    if args.seeds is not None:
        if args.seeds < 1:
            ap.error("--seeds must be >= 1")
        grid = dataclasses.replace(grid, seeds=grid.seeds[: args.seeds])
    if args.detector_quality:
        grid = dataclasses.replace(grid, detector_quality=True)
    out = Path(args.out or Path("results") / grid.name)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"--out '{out}': cannot create the results folder ({exc.strerror}); choose a folder "
                          "you can write to") from None
    TrialStore(out).check(grid.name, add=args.add)      # the folder first: building the scenarios takes time
    check_scenarios(grid)
    print(f"{grid.name}: {len(grid.agents)} agents x {len(grid.scenarios)} scenarios x "
          f"{len(grid.seeds)} seeds = {grid.trials()} trials -> {out}/", flush=True)
    t0 = time.monotonic()
    rows = run_grid(grid, str(out), workers=args.workers, executor=args.executor, progress=not args.quiet,
                    add=args.add)
    elapsed = time.monotonic() - t0
    print()
    print(summary_table(summarize(rows)))
    if any("detector_iou" in r for r in rows):
        print()
        print(detector_table(rows))
    for section in paper_sections(grid.paper, rows):
        print()
        print(section)
    path = write_report(grid, rows, out, plots=not args.no_plots,
                        note=f"Run time of this invocation: {elapsed:.0f} s with {args.workers} "
                             f"{args.executor} worker(s) (trials already on disk were skipped).")
    print(f"\nreport: {path}; rows: {out / 'trials.csv'}; {elapsed:.0f} s", flush=True)
    missing = grid.trials() - len(rows)
    if missing:
        print(f"aerial-loc bench: {missing} of {grid.trials()} trial(s) have no result (they failed: see "
              f"{out / 'failures.jsonl'}; a re-run retries them)", file=sys.stderr)
        return 1
    return 0


def write_report(grid: Grid, rows: Sequence[dict], out: Path, *, plots: bool = True, note: str = "") -> Path:
    """Write ``out/report.md`` (the summary, the paper's tables, the plots) and the PNGs it links."""
    from aerial_loc_env.paths import atomic_write_bytes

    sections = paper_sections(grid.paper, rows)
    if plots and rows:
        sections += _plots(grid, rows, out)
    if note:
        sections.append(note + "\n")
    text = markdown_report(grid.name, grid.description, rows, machine(), sections)
    path = Path(out) / "report.md"
    atomic_write_bytes(path, text.encode())
    return path


def _with_and_without_shadows(grid: Grid) -> list[ScenarioEntry]:
    """The grid's first two scenarios when they are one ground in two conditions (the same id, or one of them
    shadow-free), else the first beside its shadow-free twin (same track for a seed)."""
    if len(grid.scenarios) >= 2:
        first, second = grid.scenarios[:2]
        if first.id == second.id or _shadow_free(first) or _shadow_free(second):
            return [first, second]
    s = grid.scenarios[0]
    twin = ScenarioEntry(s.id, {**s.overrides, "shadows.strength_range": [0.0, 0.0]},
                         f"{s.display}, no shadows")
    return [s, twin]


def _shadow_free(scenario: ScenarioEntry) -> bool:
    from aerial_loc_env.env import load_scenario

    return max(load_scenario(scenario.id, scenario.overrides).shadows.strength_range) == 0.0


def _plots(grid: Grid, rows: Sequence[dict], out: Path) -> list[str]:
    from aerial_loc_env.benchmark import plots as pl

    made: list[tuple[str, Path | None]] = []
    for plot in grid.plots:
        try:
            if plot == "error_vs_time":
                made.append(("error against time (Figs. 13-17)", pl.error_vs_time(
                    rows, out / "error_vs_time.png", grid.description)))
            elif plot == "shadow_pairs":
                made.append(("pairs in shadow / K against time (Figs. 38, 42)", pl.shadow_pairs_vs_time(
                    rows, out / "shadow_pairs.png", grid.description)))
            elif plot.startswith("rmse_vs_"):
                param = plot[len("rmse_vs_"):]
                made.append((f"RMSE against {param} (Figs. 35-41)", pl.rmse_vs_param(
                    rows, param, out / f"{plot}.png", grid.description)))
            elif plot == "track":
                agent = next((a for a in grid.agents if "shadow-aware" in a.name),
                             next((a for a in grid.agents if a.name.startswith("mcl")), grid.agents[0]))
                made.append(("track, estimates, particles and shadow (Fig. 12)", pl.track_plot(
                    grid.scenarios[0], grid.seeds[0], agent, out / "track.png")))
            elif plot == "likelihood":
                made.append(("likelihood around the true position, with and without shadows (Figs. 26-34)",
                             pl.likelihood_plot(grid.agents, _with_and_without_shadows(grid), grid.seeds[0],
                                                out / "likelihood.png")))
        except Exception as exc:  # noqa: BLE001 (a plot must not lose a finished run's report)
            print(f"plot {plot!r} failed: {type(exc).__name__}: {exc}", file=sys.stderr)
    return [f"![{title}]({png.name})\n" for title, png in made if png is not None]
