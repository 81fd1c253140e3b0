"""Markdown reports whose tables mirror the paper's, with our figures beside the paper's."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

# Choi & Park (2020), Table 5 (RMSE [m], simulation with shadows, N = 700, 100 trials).
PAPER_TABLE5 = {
    "conventional": {10: 7.05, 30: 8.32, 50: 8.51, 70: 8.26},
    "restoration": {10: 8.37, 30: 7.01, 50: 7.13, 70: 7.06},
    "shadow-aware": {10: 6.35, 30: 3.91, 50: 2.84, 70: 2.33},
}
# Table 9: RMSE [m] without / with shadows (simulation), and computation time [s].
PAPER_TABLE9 = {
    "SSD": (7.7, 12.5, 60.6),
    "NCC": (8.6, 9.6, 16401.0),
    "MI": (4.7, 5.9, 6004.0),
    "abBRIEF": (5.9, 8.9, 53.3),
    "Proposed": (4.2, 5.0, 56.0),
}


def _fmt(x: float | None, digits: int = 2) -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return f"{x:.{digits}f}"


def summarize(rows: Sequence[dict]) -> list[dict]:
    """One summary per (agent, scenario): the paper's RMSE over all trials pooled, plus per-trial statistics."""
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        groups.setdefault((r["agent"], r["scenario"]), []).append(r)
    out = []
    for (agent, scenario), rs in groups.items():
        errs = np.concatenate([np.asarray(r["errors_m"], dtype=float) for r in rs])
        ttc = [r["time_to_converge_s"] for r in rs if r.get("time_to_converge_s") is not None
               and math.isfinite(r["time_to_converge_s"])]
        out.append({
            "agent": agent, "scenario": scenario, "trials": len(rs),
            "rmse_m": float(np.sqrt(np.mean(errs**2))),
            "rmse_converged_m": _nanmean([r.get("rmse_converged_m") for r in rs]),
            "mean_error_m": float(np.mean(errs)),
            "p95_error_m": float(np.percentile(errs, 95)),
            "final_error_m": _nanmean([r.get("final_error_m") for r in rs]),
            "converged_frac": float(np.mean([bool(r.get("converged")) for r in rs])),
            "diverged_frac": float(np.mean([bool(r.get("diverged")) for r in rs])),
            "time_to_converge_s": float(np.median(ttc)) if ttc else float("nan"),
            "step_ms": _nanmean([r.get("step_time_median_ms") for r in rs]),
            "step_p95_ms": _nanmean([r.get("step_time_p95_ms") for r in rs]),
            "shadow_pairs_normalized": _nanmean([r.get("shadow_pairs_normalized") for r in rs]),
        })
    return sorted(out, key=lambda s: (s["scenario"], s["rmse_m"]))


def _nanmean(values: Iterable) -> float:
    arr = np.asarray([np.nan if v is None else v for v in values], dtype=float)
    return float(np.nanmean(arr)) if np.isfinite(arr).any() else float("nan")


def summary_table(summaries: Sequence[dict]) -> str:
    head = ("| scenario | agent | trials | RMSE [m] | RMSE after conv. [m] | mean [m] | p95 [m] | final [m] | "
            "converged | diverged | t conv. [s] | step median [ms] | step p95 [ms] | shadow pairs / K |")
    lines = [head, "|" + "---|" * 14]
    for s in summaries:
        lines.append(
            f"| {s['scenario']} | {s['agent']} | {s['trials']} | {_fmt(s['rmse_m'])} | {_fmt(s['rmse_converged_m'])} "
            f"| {_fmt(s['mean_error_m'])} | {_fmt(s['p95_error_m'])} | {_fmt(s['final_error_m'])} "
            f"| {s['converged_frac']:.0%} | {s['diverged_frac']:.0%} | {_fmt(s['time_to_converge_s'], 1)} "
            f"| {_fmt(s['step_ms'], 3)} | {_fmt(s['step_p95_ms'], 3)} | {_fmt(s['shadow_pairs_normalized'], 3)} |")
    return "\n".join(lines)


def markdown_report(title: str, description: str, rows: Sequence[dict], machine: str,
                    extra_sections: Sequence[str] = ()) -> str:
    summaries = summarize(rows)
    parts = [f"# {title}", "", description, "", f"Machine: {machine}.", "",
             "RMSE is the root mean square horizontal error over all steps of all trials (the paper's figure); "
             "'after conv.' is over the steps after the error fell below the convergence threshold for good.", "",
             summary_table(summaries), ""]
    parts.extend(extra_sections)
    return "\n".join(parts)


def paper_sections(experiment: str, rows: Sequence[dict]) -> list[str]:
    """Tables beside the paper's, for the experiments that reproduce one (matched by agent-spec name)."""
    if experiment == "table5":
        return [_table5(rows)]
    return []


def _family(name: str) -> str | None:
    for fam in ("shadow-aware", "restoration", "conventional"):
        if fam in name:
            return fam
    return None


def _table5(rows: Sequence[dict]) -> str:
    cells: dict[tuple[str, int], list[np.ndarray]] = {}
    for r in rows:
        fam = _family(r["agent_spec"]["name"])
        k = r["agent_spec"]["params"].get("num_pairs")
        if fam and k is not None:
            cells.setdefault((fam, int(k)), []).append(np.asarray(r["errors_m"], float))
    ks = sorted({k for _, k in cells})
    lines = ["## Table 5 (RMSE [m], ours / paper)", "", "| RMSE [m] | " + " | ".join(f"K = {k}" for k in ks) + " |",
             "|---|" + "---|" * len(ks)]
    for fam in ("conventional", "restoration", "shadow-aware"):
        vals = []
        for k in ks:
            errs = cells.get((fam, k))
            ours = _fmt(float(np.sqrt(np.mean(np.concatenate(errs) ** 2)))) if errs else "-"
            vals.append(f"{ours} / {_fmt(PAPER_TABLE5[fam].get(k))}")
        lines.append(f"| {fam} | " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"
