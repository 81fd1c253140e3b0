"""Plots (matplotlib, PNG): error against time per method with a band over trials (the paper's Figs. 13-17),
RMSE against a swept parameter (Figs. 35-41), the track over the map with particles and shadows (Fig. 12), and
likelihood surfaces around the true position with and without shadows (Figs. 26-34)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ..errors import require_extra


def _plt():
    mpl = require_extra("matplotlib", "plots", "Benchmark plots")
    mpl.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def error_vs_time(rows: Sequence[dict], path: Path, title: str = "") -> Path:
    """Mean horizontal error against time per agent, with a 10-90 % band over trials; one panel per scenario."""
    plt = _plt()
    scenarios = sorted({r["scenario"] for r in rows})
    fig, axes = plt.subplots(len(scenarios), 1, figsize=(9, 3.6 * len(scenarios)), squeeze=False)
    for ax, scenario in zip(axes[:, 0], scenarios, strict=True):
        agents = sorted({r["agent"] for r in rows if r["scenario"] == scenario})
        for agent in agents:
            rs = [r for r in rows if r["scenario"] == scenario and r["agent"] == agent]
            n = min(len(r["errors_m"]) for r in rs)
            e = np.array([r["errors_m"][:n] for r in rs], dtype=float)
            t = np.asarray(rs[0]["t_s"][:n], dtype=float)
            line, = ax.plot(t, e.mean(axis=0), label=f"{agent} (n={len(rs)})", lw=1.4)
            if len(rs) > 1:
                ax.fill_between(t, np.percentile(e, 10, axis=0), np.percentile(e, 90, axis=0),
                                color=line.get_color(), alpha=0.15, lw=0)
        ax.set_title(scenario)
        ax.set_xlabel("time [s]")
        ax.set_ylabel("horizontal error [m]")
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def rmse_vs_param(rows: Sequence[dict], param: str, path: Path, title: str = "") -> Path:
    """RMSE (pooled over trials) against a swept agent parameter, one line per agent spec name."""
    plt = _plt()
    groups: dict[str, dict[float, list[np.ndarray]]] = {}
    for r in rows:
        params = r["agent_spec"]["params"]
        if param not in params:
            continue
        key = f"{r['agent_spec']['name']} / {r['scenario']}"
        groups.setdefault(key, {}).setdefault(float(params[param]), []).append(np.asarray(r["errors_m"], float))
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for key, by_value in sorted(groups.items()):
        xs = sorted(by_value)
        ys = [float(np.sqrt(np.mean(np.concatenate(by_value[x]) ** 2))) for x in xs]
        ax.plot(xs, ys, marker="o", label=key)
    ax.set_xlabel(param)
    ax.set_ylabel("horizontal RMSE [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
