"""Experiments of issue 4 (not CI tests): several agents in lockstep on the same rendered episodes.

``python -m aerial_loc_env.estimators.mcl.evaluate --scenario AerialLoc/PaperShadows-v1 --seeds 20 \\
    --agents dead-reckoning mcl-conventional mcl-restoration mcl-shadow-aware``

prints, per agent, the RMSE over all steps and seeds (the paper's Table 5 figure), the median of the per-seed
RMSEs, the final error, how many seeds converged (error below ``--converge-m`` from some step on, to the end)
and the median convergence time, plus the shadow detector's IoU/precision/recall against the simulator's masks.
The benchmark module (``aerial_loc_env.benchmark``) is the general tool; this one is small and self-contained.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np


def run_episodes(scenario: str, agents: Sequence[str], seeds: Sequence[int], *, overrides: dict | None = None,
                 agent_overrides: dict[str, dict] | None = None, detector_quality: bool = True,
                 max_steps: int | None = None) -> dict[str, Any]:
    """Errors (seeds x frames) per agent, times, and the detector's mask quality, on ``scenario``.

    The episode driver runs the agents (the benchmark's time line: the last frame is estimated too);
    ``max_steps`` ends each episode after that many env steps."""
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.estimators.episode import EpisodeDriver
    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.estimators.shadow_detection import ShadowDetector, mask_quality

    overrides = dict(overrides or {})
    if detector_quality:
        overrides.setdefault("observation", {})
        overrides["observation"] = {**overrides["observation"], "info_shadow_mask": True}
    env = gym.make(scenario, **overrides)
    detector = ShadowDetector()
    errors: dict[str, list[list[float]]] = {a: [] for a in agents}
    step_s: dict[str, list[float]] = {a: [] for a in agents}
    quality: list[dict[str, float]] = []
    t_s: list[float] = []
    try:
        for seed in seeds:
            built = [make_agent(a, **(agent_overrides or {}).get(a, {})) for a in agents]
            errs: list[list[float]] = [[] for _ in agents]
            t_s = []
            with EpisodeDriver(env, built) as driver:
                for rec in driver.episode(seed, max_steps=max_steps):
                    t_s.append(rec.time_s)
                    if detector_quality and "shadow_mask" in rec.info:
                        quality.append(mask_quality(detector.detect(rec.observation["image"]).full(),
                                                    rec.info["shadow_mask"]))
                    for i, a in enumerate(agents):
                        step_s[a].append(rec.wall_s[i])
                        errs[i].append(rec.error_m(i))
            for a, e in zip(agents, errs, strict=True):
                errors[a].append(e)
    finally:
        env.close()
    return {"errors": {a: np.array(e) for a, e in errors.items()}, "step_s": step_s, "quality": quality,
            "t_s": np.array(t_s)}


def summarize(result: dict[str, Any], converge_m: float = 10.0) -> dict[str, dict[str, float]]:
    """Per agent: overall RMSE, median per-seed RMSE, final error, seeds converged, median convergence time."""
    out = {}
    t = result["t_s"]
    for a, e in result["errors"].items():
        per_seed = np.sqrt(np.mean(e ** 2, axis=1))
        conv_t = []
        for row in e:
            bad = np.flatnonzero(row >= converge_m)
            first_good = 0 if bad.size == 0 else bad[-1] + 1
            if first_good < row.size:
                conv_t.append(float(t[first_good]) if first_good < t.size else float("nan"))
        out[a] = {"rmse_m": float(np.sqrt(np.mean(e ** 2))), "median_seed_rmse_m": float(np.median(per_seed)),
                  "final_error_median_m": float(np.median(e[:, -1])), "converged": len(conv_t),
                  "seeds": int(e.shape[0]),
                  "converge_time_median_s": float(np.median(conv_t)) if conv_t else float("nan"),
                  "step_ms_median": float(np.median(result["step_s"][a]) * 1e3)}
    q = result["quality"]
    if q:
        out["shadow_detector"] = {k: float(np.mean([d[k] for d in q if math.isfinite(d[k])]))
                                  for k in ("iou", "precision", "recall", "fraction_true", "fraction_predicted")}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m aerial_loc_env.estimators.mcl.evaluate", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="AerialLoc/PaperShadows-v1")
    ap.add_argument("--agents", nargs="+", default=["dead-reckoning", "mcl-conventional", "mcl-restoration",
                                                     "mcl-shadow-aware", "mcl-shadow-aware-tempered"])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--max-steps", type=int, default=None)
    ap.add_argument("--converge-m", type=float, default=10.0)
    ap.add_argument("--set", action="append", default=[], metavar="AGENT:KEY=JSON",
                    help="agent parameter override, e.g. mcl-global:n_particles=3000")
    ap.add_argument("--json", help="write the summary here")
    args = ap.parse_args(argv)
    agent_overrides: dict[str, dict] = {}
    for item in args.set:
        name, _, kv = item.partition(":")
        key, _, val = kv.partition("=")
        agent_overrides.setdefault(name, {})[key] = json.loads(val)
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    t0 = time.time()
    res = run_episodes(args.scenario, args.agents, seeds, agent_overrides=agent_overrides, max_steps=args.max_steps)
    summary = summarize(res, args.converge_m)
    print(f"{args.scenario}, seeds {seeds.start}..{seeds.stop - 1}, {time.time() - t0:.0f} s")
    print(f"{'agent':28s} {'RMSE':>8s} {'med/seed':>9s} {'final':>8s} {'converged':>10s} {'t_conv':>7s} "
          f"{'ms/step':>8s}")
    for a, s in summary.items():
        if a == "shadow_detector":
            continue
        print(f"{a:28s} {s['rmse_m']:8.2f} {s['median_seed_rmse_m']:9.2f} {s['final_error_median_m']:8.2f} "
              f"{s['converged']:>4d}/{s['seeds']:<5d} {s['converge_time_median_s']:7.1f} {s['step_ms_median']:8.2f}")
    if "shadow_detector" in summary:
        print("shadow detector:", {k: round(v, 3) for k, v in summary["shadow_detector"].items()})
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(summary, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
