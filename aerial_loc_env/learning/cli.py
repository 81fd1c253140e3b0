"""``aerial-loc train agents/<recipe>``: train a learned policy from a recipe spec."""

from __future__ import annotations

import argparse


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="aerial-loc train", description=__doc__)
    ap.add_argument("recipe", help="an agent spec with a [train] table: a name in agents/ or a path to its TOML")
    ap.add_argument("--out", help="output folder (default runs/<recipe name>)")
    ap.add_argument("--timesteps", type=int, help="override the recipe's total_timesteps")
    ap.add_argument("--resume", help="continue from this checkpoint (.zip)")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing model in --out")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("-v", "--verbose", action="count", default=0)
    args = ap.parse_args(argv)
    from .train import train

    res = train(args.recipe, args.out, overwrite=args.overwrite, resume=args.resume, total_timesteps=args.timesteps,
                progress_bar=not args.no_progress, verbose=args.verbose)
    print(f"trained {res.timesteps} timesteps in {res.wall_time_s:.0f} s; model: {res.model_path}")
    return 0
