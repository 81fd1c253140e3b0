"""Training curves of a run folder written by ``train``: held-out evaluation RMSE (eval.csv) and training
episodes' RMSE (monitor files), each beside dead reckoning's on the same episodes."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np

from aerial_loc_env.errors import ConfigError, require_extra

EVAL_COLUMNS = ("timesteps", "rmse_m")


def _monitor_rows(run_dir: Path) -> np.ndarray:
    """(N, 4) [wall_s, length, episode_rmse_m, dead_reckoning_rmse_m] of the training episodes, by time."""
    rows = []
    for path in sorted((run_dir / "monitor").glob("*.monitor.csv")):
        try:
            with open(path, newline="", encoding="utf-8") as fh:
                fh.readline()  # the JSON header line
                for r in csv.DictReader(fh):
                    if r.get("episode_rmse_m"):
                        rows.append((float(r["t"]), float(r["l"]), float(r["episode_rmse_m"]),
                                     float(r["dead_reckoning_rmse_m"])))
        except (ValueError, KeyError, TypeError, UnicodeDecodeError, csv.Error) as exc:
            raise ConfigError(f"'{path}': not a monitor file written by `aerial-loc train` ({exc!r})") from None
    arr = np.asarray(rows, dtype=float).reshape(-1, 4)
    return arr[np.argsort(arr[:, 0], kind="stable")]


def _eval_rows(run_dir: Path) -> dict[str, np.ndarray]:
    path = run_dir / "eval.csv"
    if not path.is_file():
        raise ConfigError(f"'{path}' is missing: not a run folder written by `aerial-loc train`")
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = list(reader.fieldnames or [])
            rows = list(reader)
        missing = [k for k in EVAL_COLUMNS if k not in header]
        if missing:
            raise ValueError(f"no column(s) {missing} in its header {header[:6]}")
        return {k: np.array([float(r[k]) for r in rows if r.get(k)]) for k in header}
    except (ValueError, UnicodeDecodeError, csv.Error) as exc:
        raise ConfigError(f"'{path}': not an eval.csv written by `aerial-loc train` ({exc}); expected the "
                          f"columns {', '.join(EVAL_COLUMNS)}, ... with numbers") from None


def learning_curve(run_dir: str | os.PathLike, out_png: str | os.PathLike, *, window: int = 50,
                   title: str | None = None, compare: dict[str, str | os.PathLike] | None = None) -> Path:
    """Write the training curves of ``run_dir`` to ``out_png`` (needs matplotlib, the ``plots`` extra);
    ``compare`` (label -> run folder) adds other runs' held-out evaluations to the right panel."""
    run_dir, out_png = Path(run_dir), Path(out_png)
    ev = _eval_rows(run_dir)
    mon = _monitor_rows(run_dir)
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
    ax = axes[0]
    if mon.size:
        steps = np.cumsum(mon[:, 1])
        k = max(1, min(window, len(mon) // 5 or 1))
        kernel = np.ones(k) / k
        smooth = np.sqrt(np.convolve(mon[:, 2] ** 2, kernel, mode="valid"))
        smooth_dr = np.sqrt(np.convolve(mon[:, 3] ** 2, kernel, mode="valid"))
        ax.plot(steps[k - 1:], smooth, label="policy (stochastic, training episodes)")
        ax.plot(steps[k - 1:], smooth_dr, "--", color="gray", label="dead reckoning, same episodes")
        ax.set_title(f"training episodes (RMSE over a window of {k})")
        wall_min = mon[:, 0] / 60.0
        top = ax.secondary_xaxis("top", functions=(lambda x: np.interp(x, steps, wall_min),
                                                   lambda m: np.interp(m, wall_min, steps)))
        top.set_xlabel("wall time (min)")
    ax.set_xlabel("timesteps")
    ax.set_ylabel("RMSE (m)")
    ax.legend()
    ax.grid(alpha=0.3)
    ax = axes[1]
    if ev:
        ax.plot(ev["timesteps"], ev["rmse_m"], "o-", label=f"{run_dir.name} (deterministic policy)")
        if "dead_reckoning_rmse_m" in ev:  # the same episodes every time: one level
            dr = float(np.mean(ev["dead_reckoning_rmse_m"]))
            ax.axhline(dr, ls="--", color="gray", label="dead reckoning")
        n = int(ev["episodes"][0]) if "episodes" in ev and len(ev["episodes"]) else 0
        ax.set_title(f"held-out evaluation ({n} fixed seeds, pooled RMSE)")
        for x, y, w in zip(ev["timesteps"], ev["rmse_m"], ev.get("wall_s", []), strict=False):
            ax.annotate(f"{w / 60:.0f} min", (x, y), textcoords="offset points", xytext=(0, 6), ha="center",
                        fontsize=8)
    for label, other in (compare or {}).items():
        oe = _eval_rows(Path(other))
        if oe:
            ax.plot(oe["timesteps"], oe["rmse_m"], ".:", label=label)
    ax.set_xlabel("timesteps")
    ax.set_ylabel("RMSE (m)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(alpha=0.3)
    return _save(plt, fig, title or f"learning curves: {run_dir.name}", out_png, 110)


def _pyplot():
    """matplotlib's pyplot on the Agg backend (files only), or the clear error naming the ``plots`` extra."""
    require_extra("matplotlib", "plots", "Learning curves").use("Agg")
    return require_extra("matplotlib.pyplot", "plots", "Learning curves")


def _save(plt, fig, title: str, out_png: Path, dpi: int) -> Path:
    fig.suptitle(title)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=dpi)
    plt.close(fig)
    return out_png


def _csv_columns(path: Path) -> dict[str, np.ndarray]:
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
        return {k: np.array([float(r[k]) for r in rows]) for k in (rows[0] if rows else {})}
    except (OSError, ValueError, UnicodeDecodeError, csv.Error) as exc:
        raise ConfigError(f"'{path}': not a curve written by `aerial-loc train ppo-learned-registration` "
                          f"({exc})") from None


def registration_curve(run_dir: str | os.PathLike, out_png: str | os.PathLike, *, title: str | None = None) -> Path:
    """The curves of a learned-registration run (``learning.surface_train``): behaviour cloning's losses per epoch
    (RMS of the correction in metres, training and validation surfaces) and the closed-loop validation RMSE
    before PPO (the cloned policy, at 0) and along PPO's timesteps."""
    run_dir, out_png = Path(run_dir), Path(out_png)
    bc, ppo = _csv_columns(run_dir / "bc_curve.csv"), _csv_columns(run_dir / "ppo_curve.csv")
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
    ax = axes[0]
    if bc:
        scale = np.sqrt(bc["train_mse"] / np.maximum(bc["val_mse"], 1e-12))     # the same metres per unit
        ax.plot(bc["epoch"], bc["val_rms_m"] * scale, label="training surfaces")
        ax.plot(bc["epoch"], bc["val_rms_m"], label="validation surfaces (val worlds)")
    ax.set_xlabel("epoch")
    ax.set_ylabel("RMS correction error (m)")
    ax.set_title("behaviour cloning (open loop, one frame)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax = axes[1]
    if ppo:
        ax.plot(ppo["timesteps"], ppo["rmse_m"], "o-", label="pooled RMSE")
        ax.plot(ppo["timesteps"], ppo["median_episode_rmse_m"], "s--", label="median-episode RMSE")
        n = int(ppo["episodes"][0])
        ax.set_title(f"closed loop, {n} validation episodes (0: cloned)")
    ax.set_xlabel("PPO timesteps")
    ax.set_ylabel("RMSE (m)")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(plt, fig, title or f"learned registration: {run_dir.name}", out_png, 90)
