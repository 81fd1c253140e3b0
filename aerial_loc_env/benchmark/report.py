"""Markdown reports whose tables mirror the paper's (Choi & Park 2020), with our figures beside the paper's.

Which paper tables an experiment reproduces is said by its spec (``paper = ["table5"]``); the cells are
matched by agent-spec name (``FAMILIES``) and by parameters found anywhere in the agent's nested params
(``n_pairs`` = K, ``n_particles`` = N).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from aerial_loc_env.benchmark.grid import PAPER_SECTION_NAMES, param_value

# Choi & Park (2020), Table 5 (RMSE [m], simulation with shadows, N = 700, 100 trials).
PAPER_TABLE5 = {
    "conventional": {10: 7.05, 30: 8.32, 50: 8.51, 70: 8.26},
    "restoration": {10: 8.37, 30: 7.01, 50: 7.13, 70: 7.06},
    "shadow-aware": {10: 6.35, 30: 3.91, 50: 2.84, 70: 2.33},
}
# Tables 6 and 9: RMSE [m] in simulation without / with shadows, and the computation time [s] (of the whole
# simulation run; the paper does not say over how many trials or steps).
PAPER_TABLE9 = {
    "SSD": (7.7, 12.5, 60.6),
    "NCC": (8.6, 9.6, 16401.0),
    "MI": (4.7, 5.9, 6004.0),
    "abBRIEF": (5.9, 8.9, 53.3),
    "Proposed": (4.2, 5.0, 56.0),
}
#: agent-spec name -> the paper's column of Tables 6/9
TABLE9_COLUMNS = {"mcl-ssd": "SSD", "mcl-ncc": "NCC", "mcl-mi": "MI", "mcl-abbrief": "abBRIEF",
                  "mcl-shadow-aware": "Proposed"}
#: agent-spec name -> the paper's algorithm family of Table 5 and Figs. 35-42
FAMILIES = {"mcl-conventional": "conventional", "mcl-restoration": "restoration",
            "mcl-restoration-gain": "restoration (gain)", "mcl-shadow-aware": "shadow-aware"}


def _fmt(x: float | None, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{digits}f}"


def pooled_rmse(rows: Sequence[dict]) -> float:
    """The paper's RMSE: over every step of every trial pooled."""
    if not rows:
        return float("nan")
    errs = np.concatenate([np.asarray(r["errors_m"], dtype=float) for r in rows])
    return float(np.sqrt(np.mean(errs**2)))


def _nanmean(values: Iterable) -> float:
    arr = np.asarray([np.nan if v is None else v for v in values], dtype=float)
    return float(np.nanmean(arr)) if np.isfinite(arr).any() else float("nan")


def _pct(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.0%}"


def summarize(rows: Sequence[dict]) -> list[dict]:
    """One summary per (scenario, agent): the pooled RMSE plus per-trial statistics (mean over trials)."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["agent"]), []).append(r)
    out = []
    for (scenario, agent), rs in groups.items():
        errs = np.concatenate([np.asarray(r["errors_m"], dtype=float) for r in rs])
        ttc = [r["time_to_converge_s"] for r in rs if r.get("time_to_converge_s") is not None
               and math.isfinite(r["time_to_converge_s"])]
        out.append({
            "agent": agent, "scenario": scenario, "trials": len(rs),
            "rmse_m": pooled_rmse(rs),
            "rmse_converged_m": _nanmean([r.get("rmse_converged_m") for r in rs]),
            "mean_error_m": float(np.mean(errs)),
            "p95_error_m": float(np.percentile(errs, 95)),
            "final_error_m": _nanmean([r.get("final_error_m") for r in rs]),
            "fix_rate": _nanmean([r.get("fix_rate") for r in rs]),
            "converge_threshold_m": _nanmean([r.get("converge_threshold_m") for r in rs]),
            "converged_frac": float(np.mean([bool(r.get("converged")) for r in rs])),
            "diverged_frac": float(np.mean([bool(r.get("diverged")) for r in rs])),
            "time_to_converge_s": float(np.median(ttc)) if ttc else float("nan"),
            "step_ms": _nanmean([r.get("step_time_median_ms") for r in rs]),
            "step_p95_ms": _nanmean([r.get("step_time_p95_ms") for r in rs]),
            "compute_s": _nanmean([r.get("compute_time_total_s") for r in rs]),
            "cpu_s": _nanmean([r.get("cpu_time_total_s") for r in rs]),
            "shadow_pairs_normalized": _nanmean([r.get("shadow_pairs_normalized") for r in rs]),
        })
    return sorted(out, key=lambda s: (s["scenario"], s["rmse_m"]))


def summary_table(summaries: Sequence[dict]) -> str:
    head = ("| scenario | agent | trials | RMSE [m] | RMSE after conv. [m] | mean [m] | p95 [m] "
            "| final [m] | fix rate | conv. threshold [m] | converged | diverged | t conv. [s] "
            "| step median [ms] | step p95 [ms] | compute / trial [s] | CPU / trial [s] | shadow pairs / K |")
    lines = [head, "|" + "---|" * 18]
    for s in summaries:
        lines.append(
            f"| {s['scenario']} | {s['agent']} | {s['trials']} | {_fmt(s['rmse_m'])} "
            f"| {_fmt(s['rmse_converged_m'])} "
            f"| {_fmt(s['mean_error_m'])} | {_fmt(s['p95_error_m'])} | {_fmt(s['final_error_m'])} "
            f"| {_pct(s.get('fix_rate'))} | {_fmt(s.get('converge_threshold_m'), 1)} "
            f"| {s['converged_frac']:.0%} | {s['diverged_frac']:.0%} | {_fmt(s['time_to_converge_s'], 1)} "
            f"| {_fmt(s['step_ms'], 2)} | {_fmt(s['step_p95_ms'], 2)} | {_fmt(s['compute_s'], 2)} "
            f"| {_fmt(s['cpu_s'], 2)} "
            f"| {_fmt(s['shadow_pairs_normalized'], 3)} |")
    return "\n".join(lines)


def detector_table(rows: Sequence[dict]) -> str:
    """The image shadow detector against the simulator's masks (a grid's ``detector_quality``), per scenario:
    IoU, precision, recall and the true / detected shadow fractions, means over the episodes (each episode once,
    whichever agents ran on it) of the means over their frames."""
    from aerial_loc_env.benchmark.episodes import DETECTOR_COLUMNS

    episodes: dict[str, dict[int, dict]] = {}
    for r in rows:
        if r.get("detector_iou") is not None:
            episodes.setdefault(r["scenario"], {}).setdefault(r["seed"], r)
    columns = tuple(DETECTOR_COLUMNS.values())
    lines = ["## Shadow detector against the true masks (image alone, default config)", "",
             "| scenario | episodes | IoU | precision | recall | shadow fraction true | detected |",
             "|---|" + "---|" * 6]
    for scenario, by_seed in episodes.items():
        means = [_nanmean(r.get(c) for r in by_seed.values()) for c in columns]
        lines.append(f"| {scenario} | {len(by_seed)} | " + " | ".join(_fmt(m, 3) for m in means) + " |")
    return "\n".join(lines) + "\n"


def markdown_report(title: str, description: str, rows: Sequence[dict], machine: str,
                    extra_sections: Sequence[str] = ()) -> str:
    seeds = sorted({r["seed"] for r in rows})
    versions = sorted({str(r.get("version")) for r in rows})
    parts = [f"# {title}", "", description, "",
             f"Machine: {machine}. Package version(s): {', '.join(versions)}. {len(rows)} trials, "
             f"{len(seeds)} seed(s).", "",
             "RMSE is the root mean square horizontal error over all steps of all trials pooled (the "
             "paper's figure); 'after conv.' is over the steps after the error fell below the convergence "
             "threshold for good (mean over the converged trials); the convergence threshold ('conv. "
             "threshold') is scaled with the scenario unless the experiment fixes it: min(camera footprint "
             "width / 15, prior sigma), i.e. the paper's 10 m at its 150 m footprint and 15 m prior, and never "
             "above the prior's spread (else dead reckoning would 'converge' at once); 'diverged' = final "
             "error above 5x that threshold; 'fix rate' is the fraction of steps whose estimate was an "
             "absolute fix (status 'ok'; a baseline at 0 % never fixed and equals dead reckoning); "
             "mean/p95 are over all steps (the second "
             "reference's figures); 'compute / trial' is the agent's own wall time over the episode "
             "(rendering excluded), 'CPU / trial' its CPU time (not inflated by other load on a shared "
             "machine); 'shadow pairs / K' is the mean fraction of the K pixel pairs with one end in "
             "detected shadow.", "",
             summary_table(summarize(rows)), ""]
    if any("detector_iou" in r for r in rows):
        parts += [detector_table(rows), ""]
    parts.extend(extra_sections)
    return "\n".join(parts)


# ------------------------------------------------------------------------------------------ paper tables
def _family(row: dict) -> str | None:
    return FAMILIES.get(row["agent_spec"]["name"])


def agent_param(row: dict, name: str) -> object:
    """A parameter of the trial's agent as run (the resolved config, else the grid entry's overrides)."""
    config = row.get("agent_config") or {}
    value = param_value(config.get("params") or {}, name)
    return param_value(row["agent_spec"]["params"], name) if value is None else value


def table5(rows: Sequence[dict]) -> str:
    """Table 5: RMSE by family and K (N as run), ours / paper's; one table per scenario with shadows."""
    by_scenario: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("shadow_fraction_mean", 0) > 0:
            by_scenario.setdefault(r["scenario"], []).append(r)
    parts = [_table5_one(scenario, rs) for scenario, rs in by_scenario.items()]
    parts = [p for p in parts if p]
    return "\n".join(parts) if parts else \
        "## Table 5\n\nNo trials of the paper's three variants with shadows and a K sweep.\n"


def _table5_one(scenario: str, rows: Sequence[dict]) -> str:
    cells: dict[tuple[str, int], list[dict]] = {}
    for r in rows:
        fam, k = _family(r), agent_param(r, "n_pairs")
        if fam and k is not None:
            cells.setdefault((fam, int(k)), []).append(r)
    if not cells:
        return ""
    ks = sorted({k for _, k in cells})
    fams = [f for f in dict.fromkeys(FAMILIES.values()) if any(f == c[0] for c in cells)]
    n_trials = sorted({len(v) for v in cells.values()})
    ns = sorted({int(agent_param(r, "n_particles") or 0) for rs in cells.values() for r in rs})
    cs = sorted({int(agent_param(r, "channels") or 0) for rs in cells.values() for r in rs})
    lines = [f"## Table 5 ({scenario}): RMSE [m], ours / paper (ours: {'/'.join(map(str, n_trials))} trials "
             f"per cell, N = {'/'.join(map(str, ns))}, C = {'/'.join(map(str, cs))}; paper: N = 700, C = 1, "
             "100 trials)", "",
             "| RMSE [m] | " + " | ".join(f"K = {k}" for k in ks) + " |", "|---|" + "---|" * len(ks)]
    for fam in fams:
        vals = []
        for k in ks:
            ours = _fmt(pooled_rmse(cells.get((fam, k), [])))
            vals.append(f"{ours} / {_fmt(PAPER_TABLE5.get(fam, {}).get(k))}")
        lines.append(f"| {fam} | " + " | ".join(vals) + " |")
    lines += ["", "Normalized count of pair samples in shadow (mean over steps and trials; the paper's "
              "Fig. 42):", "",
              "| shadow pairs / K | " + " | ".join(f"K = {k}" for k in ks) + " |", "|---|" + "---|" * len(ks)]
    for fam in fams:
        vals = [_fmt(_nanmean([r.get("shadow_pairs_normalized") for r in cells.get((fam, k), [])]), 3)
                for k in ks]
        lines.append(f"| {fam} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"


def table9(rows: Sequence[dict]) -> str:
    """Tables 6 and 9: RMSE without / with shadows and computation time per measurement model.

    The shadow-free and the shadowed trials are pooled over the grid's scenarios (the paper's pair: a
    scenario without and one with shadows); a grid with more than one scenario with shadows (the paper's
    setting beside the realistic gap) gets one table per scenario instead, so no cell pools two settings.
    """
    shadowed = {r["scenario"] for r in rows if r["agent_spec"]["name"] in TABLE9_COLUMNS
                and r.get("shadow_fraction_mean", 0) > 0}
    if len(shadowed) > 1:
        by_scenario: dict[str, list[dict]] = {}
        for r in rows:
            by_scenario.setdefault(r["scenario"], []).append(r)
        return "\n".join(_table9_one(rs, f" ({scenario})") for scenario, rs in by_scenario.items())
    return _table9_one(rows)


def _table9_one(rows: Sequence[dict], title: str = "") -> str:
    cols: dict[str, dict[str, list[dict]]] = {}
    for r in rows:
        col = TABLE9_COLUMNS.get(r["agent_spec"]["name"])
        if col is None:
            continue
        cond = "with" if r.get("shadow_fraction_mean", 0) > 0 else "without"
        cols.setdefault(col, {}).setdefault(cond, []).append(r)
    if not cols:
        return f"## Tables 6 and 9{title}\n\nNo trials of the paper's measurement models.\n"
    names = [c for c in PAPER_TABLE9 if c in cols]
    lines = [f"## Tables 6 and 9{title}: ours / paper", "",
             "| | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]

    def row(label: str, fn: Callable[[str], str]) -> None:
        lines.append(f"| {label} | " + " | ".join(fn(c) for c in names) + " |")

    row("Sim. w/o shadow RMSE [m]", lambda c: f"{_fmt(pooled_rmse(cols[c].get('without', [])))} / "
                                              f"{_fmt(PAPER_TABLE9[c][0])}")
    row("Sim. w/ shadow RMSE [m]", lambda c: f"{_fmt(pooled_rmse(cols[c].get('with', [])))} / "
                                             f"{_fmt(PAPER_TABLE9[c][1])}")
    row("compute per step [ms] (ours)", lambda c: _fmt(_nanmean(
        [r.get("step_time_median_ms") for rs in cols[c].values() for r in rs]), 2))
    row("compute per trial [s] (ours)", lambda c: _fmt(_nanmean(
        [r.get("compute_time_total_s") for rs in cols[c].values() for r in rs]), 2))
    row("CPU per trial [s] (ours)", lambda c: _fmt(_nanmean(
        [r.get("cpu_time_total_s") for rs in cols[c].values() for r in rs]), 2))
    row("computation time [s] (paper)", lambda c: f"{PAPER_TABLE9[c][2]:g}")
    row("trials w/o / w/ shadow",
        lambda c: f"{len(cols[c].get('without', []))} / {len(cols[c].get('with', []))}")
    return "\n".join(lines) + "\n"


def sweep_tables(rows: Sequence[dict]) -> str:
    """Figs. 35-42 as tables: RMSE (and the normalized shadow-pair count) against N and against K."""
    parts = []
    for param, label in (("n_particles", "N"), ("n_pairs", "K")):
        groups: dict[tuple[str, str], dict[int, list[dict]]] = {}
        for r in rows:
            value = agent_param(r, param)
            if value is not None:
                name = _family(r) or r["agent_spec"]["name"]
                groups.setdefault((name, r["scenario"]), {}).setdefault(int(value), []).append(r)
        if not groups or all(len(v) < 2 for v in groups.values()):
            continue
        values = sorted({v for g in groups.values() for v in g})
        parts += [f"## RMSE [m] against {label} (Figs. {'35-38' if label == 'N' else '39-42'})", "",
                  "| agent / scenario | " + " | ".join(f"{label} = {v}" for v in values)
                  + " | shadow pairs / K |",
                  "|---|" + "---|" * (len(values) + 1)]
        for (name, scenario), by in sorted(groups.items()):
            cells = [_fmt(pooled_rmse(by.get(v, []))) for v in values]
            sp = _nanmean([r.get("shadow_pairs_normalized") for rs in by.values() for r in rs])
            parts.append(f"| {name} / {scenario} | " + " | ".join(cells) + f" | {_fmt(sp, 3)} |")
        parts.append("")
    return "\n".join(parts)


def global_table(rows: Sequence[dict]) -> str:
    """Global localization (the second reference): fraction converged and time to converge, uniform start."""
    lines = ["## Global localization: converged from a uniform start", "",
             "| scenario | agent | trials | converged | median t conv. [s] | p90 t conv. [s] "
             "| final error [m] | RMSE after conv. [m] |", "|---|---|---|---|---|---|---|---|"]
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scenario"], r["agent"]), []).append(r)
    for (scenario, agent), rs in sorted(groups.items()):
        ttc = np.array([r["time_to_converge_s"] for r in rs if r.get("time_to_converge_s") is not None
                        and math.isfinite(r["time_to_converge_s"])])
        converged = np.mean([bool(r["converged"]) for r in rs])
        lines.append(f"| {scenario} | {agent} | {len(rs)} | {converged:.0%} "
                     f"| {_fmt(float(np.median(ttc)) if ttc.size else None, 1)} "
                     f"| {_fmt(float(np.percentile(ttc, 90)) if ttc.size else None, 1)} "
                     f"| {_fmt(float(np.median([r['final_error_m'] for r in rs])), 1)} "
                     f"| {_fmt(_nanmean([r.get('rmse_converged_m') for r in rs]))} |")
    return "\n".join(lines) + "\n"


def comparison_table(rows: Sequence[dict]) -> str:
    """Every agent on every scenario side by side (e.g. the paper's setting beside the realistic gap): RMSE /
    p95 [m] and converged trials per scenario, agents ordered by their worst RMSE over the scenarios."""
    cells = {(s["agent"], s["scenario"]): s for s in summarize(rows)}
    scenarios = list(dict.fromkeys(r["scenario"] for r in rows))
    agents = sorted(dict.fromkeys(r["agent"] for r in rows), key=lambda a: max(
        (cells[a, s]["rmse_m"] for s in scenarios if (a, s) in cells), default=math.inf))
    trials = {s: sorted({cells[a, s]["trials"] for a in agents if (a, s) in cells}) for s in scenarios}
    lines = ["## Scenarios side by side: RMSE / p95 [m] over all steps, trials converged", "",
             "| agent | " + " | ".join(f"{s}: RMSE / p95 [m] | converged ({'/'.join(map(str, trials[s]))} trials)"
                                      for s in scenarios) + " |",
             "|---|" + "---|---|" * len(scenarios)]
    for a in agents:
        vals = []
        for s in scenarios:
            c = cells.get((a, s))
            vals += ["-", "-"] if c is None else [f"{_fmt(c['rmse_m'])} / {_fmt(c['p95_error_m'])}",
                                                  f"{round(c['converged_frac'] * c['trials'])}/{c['trials']}"]
        lines.append(f"| {a} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"


#: resamples behind each bootstrap interval (``interval_table``, ``fidelity``)
BOOTSTRAP_RESAMPLES = 2000
#: the recall radii of ``interval_table`` [m]: the share of all steps whose error is within each
RECALL_RADII_M = (5.0, 10.0)


def two_stage_resample(groups: Sequence[np.ndarray], gen: np.random.Generator) -> np.ndarray:
    """One bootstrap resample of grouped items: the groups drawn with replacement, then each drawn group's items
    (trials nest in pairs or worlds: resampling the groups keeps their spread in the interval)."""
    chosen = [groups[i] for i in gen.integers(0, len(groups), len(groups))]
    return np.concatenate([g[gen.integers(0, g.size, g.size)] for g in chosen])


def _scenario_group(scenario: str) -> str:
    """The group a scenario label belongs to: the part before ": " (a pairs entry labels its pairs ``"<label>:
    <pair>"``), else the label itself."""
    return scenario.split(": ", 1)[0]


def _trial_figures(rows: Sequence[dict]) -> dict[str, np.ndarray]:
    """Per trial: its RMSE, squared-error sum, steps, steps within each recall radius, convergence time (NaN if
    it never converged)."""
    errs = [np.asarray(r["errors_m"], dtype=float) for r in rows]
    ttc = [r.get("time_to_converge_s") for r in rows]
    return {"rmse": np.array([r["rmse_m"] for r in rows], dtype=float),
            "sq": np.array([float(np.sum(e ** 2)) for e in errs]),
            "n": np.array([e.size for e in errs], dtype=float),
            **{f"within_{k}": np.array([float(np.sum(e <= d)) for e in errs]) for k, d in enumerate(RECALL_RADII_M)},
            "ttc": np.array([np.nan if t is None else float(t) for t in ttc], dtype=float),
            "converged": np.array([bool(r.get("converged")) for r in rows], dtype=float)}


def _figures(f: dict[str, np.ndarray], idx: np.ndarray) -> np.ndarray:
    """The interval table's figures of the trials ``idx`` (with repeats): median-trial RMSE, pooled RMSE, the
    recalls, median convergence time of the converged trials, converged share."""
    n = f["n"][idx].sum()
    ttc = f["ttc"][idx]
    ttc = ttc[np.isfinite(ttc)]
    return np.array([np.median(f["rmse"][idx]), math.sqrt(f["sq"][idx].sum() / n),
                     *(f[f"within_{k}"][idx].sum() / n for k in range(len(RECALL_RADII_M))),
                     np.median(ttc) if ttc.size else np.nan, f["converged"][idx].mean()])


def trial_intervals(rows: Sequence[dict], *, resamples: int = BOOTSTRAP_RESAMPLES,
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The figures of ``rows`` (one agent's trials on one scenario group; ``_figures``' order) and their 95 %
    bootstrap intervals (2, figures): scenarios resampled with replacement, then each chosen scenario's trials
    (``two_stage_resample``), ``resamples`` times from ``numpy.random.default_rng(seed)``."""
    f = _trial_figures(rows)
    by_scenario: dict[str, list[int]] = {}
    for i, r in enumerate(rows):
        by_scenario.setdefault(r["scenario"], []).append(i)
    groups = [np.asarray(v) for v in by_scenario.values()]
    gen = np.random.default_rng(seed)
    draws = np.empty((resamples, 6))
    for b in range(resamples):
        draws[b] = _figures(f, two_stage_resample(groups, gen))
    lo_hi = np.full((2, draws.shape[1]), np.nan)
    for k in range(draws.shape[1]):       # a figure undefined in some resamples (no trial converged): the rest
        column = draws[np.isfinite(draws[:, k]), k]
        if column.size:
            lo_hi[:, k] = np.percentile(column, [2.5, 97.5])
    return _figures(f, np.arange(len(rows))), lo_hi


def interval_table(rows: Sequence[dict]) -> str:
    """Every agent on every scenario group (a folder of real pairs, the held-out worlds, the real tiles: the label
    before ": "), each figure with its 95 % bootstrap interval over the trials (``trial_intervals``); agents
    ordered by their median-trial RMSE within each group."""
    groups: dict[str, dict[str, list[dict]]] = {}
    for r in rows:
        groups.setdefault(_scenario_group(r["scenario"]), {}).setdefault(r["agent"], []).append(r)
    radii = " | ".join(f"within {d:g} m" for d in RECALL_RADII_M)
    lines = ["## Every figure with its 95 % bootstrap interval over trials", "",
             "Median-trial RMSE and pooled RMSE [m], the share of all steps within each radius, the median time "
             "to converge of the converged trials [s] and the converged share; [low, high] is the 95 % interval "
             f"of {BOOTSTRAP_RESAMPLES} bootstrap resamples (the group's scenarios, then each one's trials).", "",
             f"| scenarios | agent | trials | median-trial RMSE | pooled RMSE | {radii} | time to converge "
             "| converged |", "|---|" + "---|" * (6 + len(RECALL_RADII_M))]
    for group, by_agent in groups.items():
        cells = {a: trial_intervals(rs) for a, rs in by_agent.items()}
        for agent in sorted(cells, key=lambda a: cells[a][0][0]):
            value, (lo, hi) = cells[agent]
            digits = (2, 2, 2, 2, 1, 2)
            shown = []
            for k, d in enumerate(digits):
                pct = 2 <= k < 2 + len(RECALL_RADII_M) or k == 5
                fmt = _pct if pct else (lambda x, d=d: _fmt(x, d))
                shown.append(f"{fmt(value[k])} [{fmt(lo[k])}, {fmt(hi[k])}]")
            lines.append(f"| {group} | {agent} | {len(by_agent[agent])} | " + " | ".join(shown) + " |")
    return "\n".join(lines) + "\n"


#: paper-section name (grid.PAPER_SECTION_NAMES, which experiment specs list) -> builder
PAPER_SECTIONS: dict[str, Callable[[Sequence[dict]], str]] = dict(zip(
    PAPER_SECTION_NAMES, (table5, table9, sweep_tables, global_table, comparison_table, interval_table), strict=True))


def paper_sections(names: Iterable[str], rows: Sequence[dict]) -> list[str]:
    return [PAPER_SECTIONS[n](rows) for n in names]
