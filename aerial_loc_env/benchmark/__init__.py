"""Layer 5: the benchmark harness (``aerial-loc bench``): experiment grids of agents x scenarios x seeds,
run with one rendering per episode shared by all agents, resumable on disk, reported beside the paper's
tables.

From Python::

    from aerial_loc_env.benchmark import make_grid, run_experiment
    grid = make_grid("mine", ["mcl-shadow-aware", "mcl-conventional"], ["AerialLoc/PaperShadows-v2"],
                     seeds=10)
    rows = run_experiment(grid, "results/mine", workers=2)     # or run_experiment("table5", ...)
"""

from aerial_loc_env.benchmark.grid import (
    AgentEntry,
    Grid,
    ScenarioEntry,
    available_experiments,
    grid_from_dict,
    load_grid,
    make_grid,
)
from aerial_loc_env.benchmark.runner import rerun_row, run_grid

__all__ = ["AgentEntry", "Grid", "ScenarioEntry", "available_experiments", "grid_from_dict", "load_grid",
           "make_grid", "rerun_row", "run_experiment", "run_grid"]


def run_experiment(experiment: "str | Grid", out_dir: str, *, workers: int = 1, executor: str = "local",
                   plots: bool = True, progress: bool = True, add: bool = False) -> list[dict]:
    """Run an experiment (a name, a TOML path or a ``Grid``) into ``out_dir`` and write its report and plots;
    returns the rows (finished trials already in ``out_dir`` are kept and skipped). ``add`` lets it write
    into a folder that holds another experiment's results."""
    from pathlib import Path

    from aerial_loc_env.benchmark.cli import write_report

    grid = experiment if isinstance(experiment, Grid) else load_grid(experiment)
    rows = run_grid(grid, out_dir, workers=workers, executor=executor, progress=progress, add=add)
    write_report(grid, rows, Path(out_dir), plots=plots)
    return rows
