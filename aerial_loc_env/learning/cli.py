"""``aerial-loc train <recipe>``: train a learned policy from a recipe (an agent spec with a [train] table).

Examples::

    aerial-loc train ppo-local-registration                     # -> runs/ppo-local-registration/
    aerial-loc train ppo-local-registration --timesteps 2000 --out /tmp/try
    aerial-loc train ppo-local-registration \
        --resume runs/ppo-local-registration/checkpoints/model_5000_steps.zip
    aerial-loc train --curve runs/ppo-local-registration         # training curves -> <run>/learning_curve.png
    aerial-loc train mcl-learned --out /tmp/w.npz                # the learned MCL model's encoder (--timesteps:
                                                                 # its steps)
    aerial-loc train ppo-learned-registration --out /tmp/reg     # cloning then PPO on the encoder's surface
                                                                 # (--timesteps: the PPO steps)
"""

from __future__ import annotations

import argparse
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="aerial-loc train", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recipe", nargs="?",
                    help="an agent spec with a [train] table: a name in agents/ or a TOML path")
    ap.add_argument("--out", help="output folder (default runs/<recipe name>)")
    ap.add_argument("--timesteps", type=int, help="override the recipe's total_timesteps")
    ap.add_argument("--resume",
                    help="continue from this checkpoint (.zip); its timesteps count towards the total")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing model in --out")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("--curve", metavar="RUN_DIR", help="only plot the training curves of a run folder")
    ap.add_argument("--png", help="with --curve: the PNG to write (default RUN_DIR/learning_curve.png)")
    ap.add_argument("-v", "--verbose", action="count", default=0)
    args = ap.parse_args(argv)
    if args.curve:
        from aerial_loc_env.learning.plots import learning_curve, registration_curve

        plot = registration_curve if (Path(args.curve) / "ppo_curve.csv").is_file() else learning_curve
        print(plot(args.curve, args.png or Path(args.curve) / "learning_curve.png"))
        return 0
    if not args.recipe:
        ap.error("a recipe is required (or --curve RUN_DIR)")
    from aerial_loc_env.learning.embedding import is_embedding_recipe

    if is_embedding_recipe(args.recipe):     # the learned MCL model's encoder (learning/embedding.py)
        from aerial_loc_env.learning.embedding import read_recipe, train_embedding

        recipe = read_recipe(args.recipe, **({"steps": args.timesteps} if args.timesteps else {}))
        out = Path(args.out) if args.out else Path("runs") / Path(args.recipe).stem
        out = out if out.suffix == ".npz" else out / "weights.npz"
        res = train_embedding(recipe, out, overwrite=args.overwrite, verbose=args.verbose > 0)
        print(f"trained {res.figures['steps']} steps in {res.wall_s:.0f} s; weights: {res.path} "
              f"(temperature {res.temperature:.4g})")
        return 0
    from aerial_loc_env.learning.surface_train import is_registration_recipe

    if is_registration_recipe(args.recipe):  # local registration on the learned encoder (learning/surface_train.py)
        from aerial_loc_env.learning.surface_train import read_recipe as read_registration
        from aerial_loc_env.learning.surface_train import train_registration

        recipe = read_registration(args.recipe, **({"ppo_timesteps": args.timesteps}
                                                   if args.timesteps is not None else {}))
        out = Path(args.out) if args.out else Path("runs") / Path(args.recipe).stem
        res = train_registration(recipe, out, overwrite=args.overwrite, verbose=args.verbose > 0)
        print(f"trained in {res.wall_s:.0f} s ({res.figures['ppo_timesteps']} PPO timesteps); kept the {res.chosen} "
              f"policy (validation RMSE {res.figures['chosen_val_rmse_m']:.2f} m): {res.path}")
        return 0
    from aerial_loc_env.learning.train import train

    res = train(args.recipe, args.out, overwrite=args.overwrite, resume=args.resume,
                total_timesteps=args.timesteps, progress_bar=not args.no_progress, verbose=args.verbose)
    print(f"trained {res.timesteps} timesteps in {res.wall_time_s:.0f} s; model: {res.model_path}")
    return 0
