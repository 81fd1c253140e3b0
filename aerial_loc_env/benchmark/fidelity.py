"""``aerial-loc fidelity``: does the simulator rank estimators as real imagery does?

A benchmark is worth using when it ranks localization methods as real flights would. This report flies the
same agents over real two-epoch pairs (``AerialLoc/RealPair-v2``: the map is the earlier image, the camera flies
over the later one) and over chosen simulated presets at the **same flight geometry** (camera, altitude, speed,
duration, prior), and compares:

- each agent's **median-trial RMSE** on the real pairs and on each preset (a trial: one agent, one episode; its
  RMSE over the episode's steps), and the fraction of trials that converged;
- the **two orders** (agents by median RMSE, best first) and **Kendall's tau-b** between them (+1: the same
  order, 0: unrelated, -1: reversed);
- each agent's **sim / real ratio** of median RMSEs with a **bootstrap 95 % interval**: real trials resampled in
  two stages (pairs with replacement, then each chosen pair's trials; trials of one pair share its ground),
  the preset's seeds with replacement, ``BOOTSTRAP_RESAMPLES`` times, percentiles 2.5 and 97.5.

The issue's targets: tau >= ``TARGET_TAU`` and every ratio within ``TARGET_RATIO``.

**The flight** (``pair_scenarios.fit_flight``): RealPair-v2's geometry (the paper's 600 x 400 camera, 5 m/s,
a 15 m prior) at the altitude and duration fitted to the smallest pair; every pair and every preset fly that one
geometry, so that the comparison is at one geometry. A 512 m tile at 0.5 m/px (the LEVIR-CD pairs) gets
RealPair's own: 200 m, 60 s.

Trials go through the benchmark (``run_grid``) into ``--out`` (``results/fidelity``): a re-run skips what is done.
The benchmark form of a folder of pairs, every pair a scenario, is also what an experiment's ``[[scenarios]]
pairs = "DIR"`` expands to (``benchmark/pair_scenarios.py``), each pair at its own fitted flight there.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from aerial_loc_env.benchmark.pair_scenarios import (
    PAIR_ID,
    PairSource,
    fit_flight,
    pair_entries,
    pair_extent_m,
    pair_sources,
    sim_overrides,
)
from aerial_loc_env.benchmark.report import BOOTSTRAP_RESAMPLES, two_stage_resample
from aerial_loc_env.benchmark.store import finite_or_null
from aerial_loc_env.errors import ConfigError, MapError

#: the agents of issue 24's table: (spec, label)
DEFAULT_AGENTS = (("mcl-mi", "MCL MI"), ("mcl-ncc", "MCL NCC"), ("template-ncc", "template NCC"),
                  ("mcl-abbrief", "MCL abBRIEF"), ("mcl-conventional", "MCL conventional"),
                  ("mcl-shadow-aware", "MCL shadow-aware"), ("mcl-ssd", "MCL SSD"),
                  ("mcl-restoration", "MCL restoration"), ("features-orb", "ORB + RANSAC"))
DEFAULT_SIMS = ("AerialLoc/RealisticPaper-v3",)
TARGET_TAU = 0.8
TARGET_RATIO = (0.67, 1.5)


# ------------------------------------------------------------------------------------------ statistics
def kendall_tau(x: Sequence[float], y: Sequence[float]) -> float:
    """Kendall's tau-b of two paired sequences (ties in either count against neither order)."""
    n = len(x)
    if n != len(y) or n < 2:
        raise ConfigError(f"fidelity: Kendall's tau needs two equal sequences of at least 2 values, got {n}, {len(y)}")
    conc = disc = tie_x = tie_y = 0
    for i in range(n):
        for j in range(i + 1, n):
            dx, dy = np.sign(x[i] - x[j]), np.sign(y[i] - y[j])
            if dx == 0 and dy == 0:
                continue
            if dx == 0:
                tie_x += 1
            elif dy == 0:
                tie_y += 1
            elif dx == dy:
                conc += 1
            else:
                disc += 1
    den = math.sqrt((conc + disc + tie_x) * (conc + disc + tie_y))
    return (conc - disc) / den if den > 0 else 0.0


def bootstrap_ratio(sim: Sequence[float], real_by_pair: Sequence[Sequence[float]], *,
                    resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> tuple[float, float]:
    """The 95 % bootstrap interval of median(sim) / median(real): the preset's trials resampled with replacement,
    the real ones in two stages (pairs, then each chosen pair's trials)."""
    gen = np.random.default_rng(seed)
    sim_arr = np.asarray(sim, dtype=float)
    groups = [np.asarray(g, dtype=float) for g in real_by_pair if len(g)]
    ratios = np.empty(resamples)
    for k in range(resamples):
        s = sim_arr[gen.integers(0, sim_arr.size, sim_arr.size)]
        r = two_stage_resample(groups, gen)
        ratios[k] = np.median(s) / max(float(np.median(r)), 1e-9)
    lo, hi = np.percentile(ratios, [2.5, 97.5])
    return float(lo), float(hi)


def bootstrap_tau(real: Sequence[Mapping[Any, Mapping[Any, float]]], sim: Sequence[Mapping[Any, float]], *,
                  resamples: int = BOOTSTRAP_RESAMPLES, seed: int = 0) -> tuple[float, float]:
    """The 95 % bootstrap interval of Kendall's tau-b between the agents' real and simulated median-trial RMSEs.

    ``real[i]`` holds agent i's real trials as ``{pair: {seed: rmse}}``, ``sim[i]`` its preset's as ``{seed:
    rmse}``. The agents fly the same episodes, so their errors are paired: each resample draws the pairs with
    replacement, then each chosen pair's seeds, then the preset's seeds, once for all agents (a trial an agent
    lacks is left out of its median)."""
    if len(real) != len(sim) or len(real) < 2:
        raise ConfigError(f"fidelity: tau's interval needs the same >= 2 agents on both sides, got {len(real)} "
                          f"and {len(sim)}")
    gen = np.random.default_rng(seed)
    pairs = sorted({p for agent in real for p in agent}, key=str)
    seeds_of = {p: sorted({s for agent in real for s in agent.get(p, {})}, key=str) for p in pairs}
    sim_seeds = sorted({s for agent in sim for s in agent}, key=str)
    taus = []
    for _ in range(resamples):
        keys = [(p, seeds_of[p][j]) for p in (pairs[i] for i in gen.integers(0, len(pairs), len(pairs)))
                for j in gen.integers(0, len(seeds_of[p]), len(seeds_of[p]))]
        sim_keys = [sim_seeds[j] for j in gen.integers(0, len(sim_seeds), len(sim_seeds))]
        real_med = [[agent[p][s] for p, s in keys if s in agent.get(p, {})] for agent in real]
        sim_med = [[agent[s] for s in sim_keys if s in agent] for agent in sim]
        if all(real_med) and all(sim_med):
            taus.append(kendall_tau([float(np.median(v)) for v in real_med], [float(np.median(v)) for v in sim_med]))
    if not taus:
        raise ConfigError("fidelity: no bootstrap resample held a trial of every agent on both sides")
    lo, hi = np.percentile(taus, [2.5, 97.5])
    return float(lo), float(hi)


@dataclass(frozen=True)
class AgentFidelity:
    """One agent's figures: real pairs against one preset."""

    agent: str
    real_median_m: float
    real_trials: int
    real_converged: float
    sim_median_m: float
    sim_trials: int
    sim_converged: float
    ratio: float
    ratio_lo: float
    ratio_hi: float


@dataclass(frozen=True)
class Fidelity:
    """A preset against the real pairs: every agent's figures, both orders and Kendall's tau."""

    sim: str
    agents: tuple[AgentFidelity, ...]
    real_order: tuple[str, ...]
    sim_order: tuple[str, ...]
    tau: float
    tau_lo: float                # its 95 % bootstrap interval (bootstrap_tau)
    tau_hi: float

    @property
    def meets_targets(self) -> bool:
        lo, hi = TARGET_RATIO
        return self.tau >= TARGET_TAU and all(lo <= a.ratio <= hi for a in self.agents)


def _by_seed(rows: Sequence[Mapping[str, Any]], agent: str, scenario: str) -> dict[Any, float]:
    """An agent's trials on one scenario as {seed: RMSE} (rows without a seed: keyed by their order)."""
    mine = (r for r in rows if r["agent"] == agent and r["scenario"] == scenario)
    return {r.get("seed", i): float(r["rmse_m"]) for i, r in enumerate(mine)}


def fidelity(rows: Sequence[Mapping[str, Any]], real_labels: Sequence[str], sim_label: str,
             agents: Sequence[str]) -> Fidelity:
    """The comparison of one preset (trials whose scenario is ``sim_label``) with the real pairs (trials whose
    scenario is one of ``real_labels``) for ``agents`` (their labels), from benchmark rows."""
    real_set = set(real_labels)
    out = []
    for agent in agents:
        mine = [r for r in rows if r["agent"] == agent]
        real = [r for r in mine if r["scenario"] in real_set]
        sim = [r for r in mine if r["scenario"] == sim_label]
        if not real or not sim:
            raise ConfigError(f"fidelity: agent {agent!r} has {len(real)} real and {len(sim)} simulated trials "
                              "(every trial failed? see failures.jsonl in the results folder); the comparison "
                              "needs both")
        by_pair = [[r["rmse_m"] for r in real if r["scenario"] == label] for label in real_labels]
        real_med = float(np.median([r["rmse_m"] for r in real]))
        sim_med = float(np.median([r["rmse_m"] for r in sim]))
        lo, hi = bootstrap_ratio([r["rmse_m"] for r in sim], by_pair)
        out.append(AgentFidelity(agent, real_med, len(real), float(np.mean([bool(r["converged"]) for r in real])),
                                 sim_med, len(sim), float(np.mean([bool(r["converged"]) for r in sim])),
                                 sim_med / max(real_med, 1e-9), lo, hi))
    real_order = tuple(a.agent for a in sorted(out, key=lambda a: a.real_median_m))
    sim_order = tuple(a.agent for a in sorted(out, key=lambda a: a.sim_median_m))
    if len(out) < 2:             # one agent: no order to compare
        return Fidelity(sim_label, tuple(out), real_order, sim_order, math.nan, math.nan, math.nan)
    tau = kendall_tau([a.real_median_m for a in out], [a.sim_median_m for a in out])
    real_trials = [{label: _by_seed(rows, agent, label) for label in real_labels} for agent in agents]
    sim_trials = [_by_seed(rows, agent, sim_label) for agent in agents]
    tau_lo, tau_hi = bootstrap_tau(real_trials, sim_trials)
    return Fidelity(sim_label, tuple(out), real_order, sim_order, tau, tau_lo, tau_hi)


def fidelity_table(result: Fidelity, real_name: str = "real pairs") -> str:
    """A Markdown table: per agent (in the real order) the two median-trial RMSEs, the ratio with its interval,
    and the two ranks; then both orders and tau."""
    lo_t, hi_t = TARGET_RATIO
    rank_sim = {a: i + 1 for i, a in enumerate(result.sim_order)}
    by_name = {a.agent: a for a in result.agents}
    lines = [f"| agent | {real_name}: median RMSE (converged) | {result.sim}: median RMSE (converged) | "
             "sim / real (95 % interval) | rank real | rank sim |", "|---|---|---|---|---|---|"]
    for i, name in enumerate(result.real_order, start=1):
        a = by_name[name]
        mark = "" if lo_t <= a.ratio <= hi_t else " (!)"
        lines.append(f"| {name} | {a.real_median_m:.2f} m ({a.real_converged:.0%} of {a.real_trials}) | "
                     f"{a.sim_median_m:.2f} m ({a.sim_converged:.0%} of {a.sim_trials}) | {a.ratio:.2f} "
                     f"({a.ratio_lo:.2f}-{a.ratio_hi:.2f}){mark} | {i} | {rank_sim[name]} |")
    lines += ["", f"real order: {' < '.join(result.real_order)}", f"sim order:  {' < '.join(result.sim_order)}",
              (f"Kendall tau-b: {result.tau:+.2f} (95 % interval {result.tau_lo:+.2f} to {result.tau_hi:+.2f}; "
               if math.isfinite(result.tau) else "Kendall tau-b: none with one agent (") +
              f"target >= {TARGET_TAU:g}); ratios outside "
              f"[{lo_t:g}, {hi_t:g}] marked (!)"]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------ the command
def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="aerial-loc fidelity", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--pairs-dir", nargs="+", action="append", default=[], metavar="DIR",
                    help="a folder of real pairs, DIR/A/<name> and DIR/B/<name>: DIR [GSD] (GSD: metres per pixel "
                         "of images without a georeference; repeatable)")
    ap.add_argument("--pair", nargs="+", action="append", default=[], metavar="PATH",
                    help="one real pair: EARLIER LATER [GSD] (repeatable)")
    ap.add_argument("--sim", action="append", default=[], metavar="ID",
                    help=f"a simulated preset to compare (repeatable; default {', '.join(DEFAULT_SIMS)})")
    ap.add_argument("--agents", metavar="SPEC[,SPEC...]",
                    help="agent specs to fly (default: the nine of issue 24's table: "
                         f"{', '.join(a for a, _ in DEFAULT_AGENTS)})")
    ap.add_argument("--seeds", type=int, default=4, help="episodes per real pair (seeds 0..N-1; default 4)")
    ap.add_argument("--sim-seeds", type=int, default=8, help="episodes per preset (default 8)")
    ap.add_argument("--out", default=str(Path("results") / "fidelity"),
                    help="results folder (trials kept and skipped on a re-run; fidelity.md and fidelity.json, written "
                         "for each run's settings: a run with other --set / --sim-set reuses the real trials and "
                         "rewrites them, and the first command run again writes its own back from the kept trials)")
    ap.add_argument("--workers", type=int, default=max(1, len(os.sched_getaffinity(0)))
                    if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1), help="parallel processes")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an override for every scenario, real and simulated, after the fitted flight (JSON value), "
                         "e.g. flight.duration_s=20 for a quick look")
    ap.add_argument("--sim-set", action="append", default=[], metavar="KEY=VALUE",
                    help="an override for the simulated presets only, after --set (JSON value): a sensitivity run "
                         "against the same real trials, e.g. perspective.enabled=false")
    ap.add_argument("--quiet", action="store_true", help="no progress bar")
    return ap


def _sources(args: argparse.Namespace) -> list[PairSource]:
    from aerial_loc_env.benchmark.gap import _gsd_arg

    out: list[PairSource] = []
    for item in args.pairs_dir:
        if len(item) not in (1, 2):
            raise ConfigError(f"fidelity: --pairs-dir {' '.join(item)}: give DIR [GSD]")
        try:
            out += pair_sources(item[0], _gsd_arg(item[1], f"--pairs-dir {item[0]} GSD") if len(item) == 2 else None)
        except MapError as exc:
            raise ConfigError(f"fidelity: {exc}") from None
    for item in args.pair:
        if len(item) not in (2, 3):
            raise ConfigError(f"fidelity: --pair {' '.join(item)}: give EARLIER LATER [GSD]")
        gsd = _gsd_arg(item[2], f"--pair {item[0]} {item[1]} GSD") if len(item) == 3 else None
        a, b = Path(item[0]), Path(item[1])
        out.append(PairSource(a, b, gsd, f"{a.name} -> {b.name}"))
    labels = [s.label for s in out]
    if len(set(labels)) != len(labels):
        raise ConfigError(f"fidelity: two pairs share a label ({sorted({x for x in labels if labels.count(x) > 1})});"
                          " give folders of different names")
    return out


def _overrides(items: Sequence[str], option: str, example: str) -> dict[str, Any]:
    from aerial_loc_env.config import parse_assignments

    return parse_assignments(items, where=f"fidelity: {option}", example=example)


def main(argv: list[str] | None = None) -> int:
    from aerial_loc_env.benchmark.grid import AgentEntry, Grid, ScenarioEntry, check_scenarios
    from aerial_loc_env.benchmark.runner import run_grid
    from aerial_loc_env.benchmark.store import TrialStore, write_summaries
    from aerial_loc_env.paths import atomic_write_bytes
    from aerial_loc_env.sysinfo import machine

    ap = _parser()
    args = ap.parse_args(argv)
    if args.seeds < 1 or args.sim_seeds < 1 or args.workers < 1:
        ap.error("--seeds, --sim-seeds and --workers must be >= 1")
    sources = _sources(args)
    if not sources:
        ap.error("give the real pairs: --pairs-dir DIR [GSD] or --pair EARLIER LATER [GSD] (e.g. aerial-loc "
                 "fidelity --pairs-dir ../shared/data/pairs/levir-cd 0.5)")
    names = [a.strip() for a in args.agents.split(",")] if args.agents else [a for a, _ in DEFAULT_AGENTS]
    labels = dict(DEFAULT_AGENTS)
    agents = tuple(AgentEntry(n, {}, labels.get(n, n)) for n in names if n)
    out = Path(args.out)
    store = TrialStore(out)
    store.check("fidelity")          # a folder holding another experiment's results: refused before any work
    extents = {s.label: pair_extent_m(s) for s in sources}
    smallest = min(extents.values(), key=min)
    flight = fit_flight(smallest)
    extra = _overrides(args.set, "--set", "flight.duration_s=20")
    sim_extra = _overrides(args.sim_set, "--sim-set", "perspective.enabled=false")
    real = tuple(ScenarioEntry(**e) for e in pair_entries(sources, flight, extra))
    sims = tuple(ScenarioEntry(sid, {**sim_overrides(flight), **extra, **sim_extra}, f"sim: {sid.split('/')[-1]}")
                 for sid in (args.sim or DEFAULT_SIMS))
    grids = [Grid("fidelity", agents, real, tuple(range(args.seeds))),
             Grid("fidelity", agents, sims, tuple(range(args.sim_seeds)))]
    for grid in grids:
        check_scenarios(grid)
    print(f"fidelity: {len(agents)} agents on {len(real)} real pairs x {args.seeds} seeds and {len(sims)} "
          f"preset(s) x {args.sim_seeds} seeds at {flight['flight.altitude_m']:g} m, "
          f"{flight['flight.duration_s']:g} s (fitted to {smallest[0]:.0f} x {smallest[1]:.0f} m)"
          f"{f', overrides {extra}' if extra else ''}{f', presets only {sim_extra}' if sim_extra else ''} -> {out}/",
          flush=True)
    rows: list[dict] = []
    for grid in grids:
        rows += run_grid(grid, str(out), workers=args.workers, progress=not args.quiet)
    write_summaries(rows, out)
    missing = sum(g.trials() for g in grids) - len(rows)
    if missing:
        print(f"aerial-loc fidelity: {missing} trial(s) failed (see {out / 'failures.jsonl'}; a re-run retries "
              "them)", file=sys.stderr)
    real_labels = [e.display for e in real]
    results = [fidelity(rows, real_labels, e.display, [a.display for a in agents]) for e in sims]
    registrations = {}
    from aerial_loc_env.world.maps.pairs import load_pair

    for s in sources:
        registrations[s.label] = load_pair(s.path_a, s.path_b, gsd_m=s.gsd_m, max_shift_m=None).registration.describe()
    text = [f"# Fidelity: simulated presets against {len(real)} real pairs\n",
            f"Flight: {PAIR_ID}'s geometry at {flight['flight.altitude_m']:g} m for {flight['flight.duration_s']:g} s "
            f"(fitted to the smallest pair, {smallest[0]:.0f} x {smallest[1]:.0f} m)"
            f"{f', overrides {extra}' if extra else ''}{f', presets only {sim_extra}' if sim_extra else ''}; "
            f"{args.seeds} seeds per pair, {args.sim_seeds} per preset; "
            "median-trial RMSE.\n"]
    for res in results:
        text += [fidelity_table(res), ""]
    text += ["Pairs: " + "; ".join(f"{k}: {v}" for k, v in registrations.items()), "", f"Machine: {machine()}"]
    report = "\n".join(text) + "\n"
    print("\n" + report)
    atomic_write_bytes(out / "fidelity.md", report.encode())
    data = {"flight": flight, "overrides": extra, "sim_overrides": sim_extra, "seeds": args.seeds,
            "sim_seeds": args.sim_seeds, "pairs": {
        s.label: {"path_a": str(s.path_a), "path_b": str(s.path_b), "gsd_m": s.gsd_m, "extent_m": extents[s.label],
                  "registration": registrations[s.label]} for s in sources},
        "results": [finite_or_null(asdict(r)) for r in results], "machine": machine()}
    atomic_write_bytes(out / "fidelity.json", (json.dumps(data, indent=1, default=str) + "\n").encode())
    return 1 if missing else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
