"""Plots (matplotlib, PNG): error against time per method with a band over trials (the paper's Figs. 13-17),
RMSE against a swept parameter (Figs. 35-41), the normalized shadow-pair count over time (Figs. 38 and 42),
the track over the map with particles and the frame's shadow (Fig. 12), and likelihood surfaces around the
true position with and without shadows per measurement model (Figs. 26-34)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from aerial_loc_env.benchmark.grid import AgentEntry, ScenarioEntry
from aerial_loc_env.benchmark.report import agent_param
from aerial_loc_env.errors import require_extra


def _plt() -> Any:
    mpl = require_extra("matplotlib", "plots", "Benchmark plots")
    mpl.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    return path


def _series_by(rows: Sequence[dict], column: str) -> dict[str, dict[str, tuple[np.ndarray, np.ndarray, int]]]:
    """scenario -> agent -> (t, per-trial series (trials, steps), trials) truncated to the shortest trial."""
    out: dict[str, dict[str, tuple[np.ndarray, np.ndarray, int]]] = {}
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in rows:
        if r.get(column):
            groups.setdefault((r["scenario"], r["agent"]), []).append(r)
    for (scenario, agent), rs in groups.items():   # the grid's order
        n = min(len(r[column]) for r in rs)
        e = np.array([r[column][:n] for r in rs], dtype=float)
        out.setdefault(scenario, {})[agent] = (np.asarray(rs[0]["t_s"][:n], dtype=float), e, len(rs))
    return out


def _bands(rows: Sequence[dict], column: str, path: Path, ylabel: str, title: str, log: bool) -> Path | None:
    plt = _plt()
    data = _series_by(rows, column)
    if not data:
        return None
    fig, axes = plt.subplots(len(data), 1, figsize=(9, 3.6 * len(data)), squeeze=False)
    for ax, (scenario, agents) in zip(axes[:, 0], data.items(), strict=True):
        for agent, (t, e, n) in agents.items():
            line, = ax.plot(t, e.mean(axis=0), label=f"{agent} (n={n})", lw=1.4)
            if n > 1:
                ax.fill_between(t, np.percentile(e, 10, axis=0), np.percentile(e, 90, axis=0),
                                color=line.get_color(), alpha=0.15, lw=0)
        ax.set_title(scenario)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(ylabel)
        if log:
            ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    if title:
        fig.suptitle(_wrap(title), fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _wrap(text: str, width: int = 100) -> str:
    import textwrap

    return "\n".join(textwrap.wrap(text, width))


def error_vs_time(rows: Sequence[dict], path: Path, title: str = "") -> Path | None:
    """Mean horizontal error against time per agent, a 10-90 % band over trials; one panel per scenario."""
    return _bands(rows, "errors_m", path, "horizontal error [m] (mean, 10-90 % band)", title, log=True)


def shadow_pairs_vs_time(rows: Sequence[dict], path: Path, title: str = "") -> Path | None:
    """The normalized count of pair samples in shadow against time (Figs. 38 and 42); None if no agent
    reports one."""
    return _bands(rows, "shadow_pairs_series", path, "pairs with one end in shadow / K", title, log=False)


def rmse_vs_param(rows: Sequence[dict], param: str, path: Path, title: str = "") -> Path | None:
    """RMSE (pooled over trials) against a swept agent parameter (found in nested params by leaf name), one
    line per agent spec and scenario; None when no trial has that parameter."""
    plt = _plt()
    groups: dict[str, dict[float, list[np.ndarray]]] = {}
    for r in rows:
        value = agent_param(r, param)
        if value is None:
            continue
        key = f"{r['agent_spec']['name']} / {r['scenario']}"
        groups.setdefault(key, {}).setdefault(float(value), []).append(np.asarray(r["errors_m"], float))
    if not groups:
        return None
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
        ax.set_title(_wrap(title, 70), fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


def _world_extent(orthomap: Any, u0: int, u1: int, v0: int, v1: int) -> tuple[float, float, float, float]:
    gx, gy, h = orthomap.gsd_x_m, orthomap.gsd_y_m, orthomap.height_px
    return (u0 * gx, u1 * gx, (h - v1) * gy, (h - v0) * gy)


def _map_crop(orthomap: Any, u0: int, u1: int, v0: int, v1: int, max_px: int) -> np.ndarray:
    """The map's pixels [v0, v1) x [u0, u1) at most ``max_px`` on a side: a strided view of a map in memory, or
    on a map read by window the coarsest of the file's levels that keeps that size (then every ``stride``-th
    pixel of it), never the whole map."""
    from aerial_loc_env.estimators.database import DatabaseWindow
    from aerial_loc_env.world.maps.raster import RasterMap

    stride = max(1, int(np.ceil(max(u1 - u0, v1 - v0) / max_px)))
    frame = orthomap.frame if isinstance(orthomap, DatabaseWindow) else orthomap
    if not isinstance(frame, RasterMap):
        return np.asarray(orthomap.rgb[v0:v1:stride, u0:u1:stride])
    level = min(frame.n_overviews, stride.bit_length() - 1)        # 2**level <= stride
    f = 1 << level
    lw, lh = -(-frame.width_px // f), -(-frame.height_px // f)
    a0, b0 = min(u0 // f, lw - 1), min(v0 // f, lh - 1)
    a1, b1 = max(a0 + 1, min(-(-u1 // f), lw)), max(b0 + 1, min(-(-v1 // f), lh))
    rgb, _ = frame.read(a0, b0, a1 - a0, b1 - b0, level=level)
    step = max(1, stride // f)
    return rgb[::step, ::step]


def track_plot(scenario: ScenarioEntry, seed: int, agent: AgentEntry, path: Path, max_px: int = 1400) -> Path:
    """Fig. 12: the map around the track, the true track, the estimates, the final particles and the last
    frame's ground-truth shadow (its outline projected onto the map)."""
    import cv2

    from aerial_loc_env.benchmark.episodes import record_episode

    plt = _plt()
    rec = record_episode(scenario, seed, agent)
    om, cam = rec["briefing"].orthomap, rec["briefing"].camera
    truth, est = rec["truth"], rec["estimates"]
    pts = np.vstack([truth[:, :2], est])
    fw, fh = cam.footprint_m(float(truth[:, 3].max()))
    pad = 0.6 * max(fw, fh)
    x0, x1 = max(0.0, pts[:, 0].min() - pad), min(om.width_m, pts[:, 0].max() + pad)
    y0, y1 = max(0.0, pts[:, 1].min() - pad), min(om.height_m, pts[:, 1].max() + pad)
    u0, u1 = int(x0 / om.gsd_x_m), int(np.ceil(x1 / om.gsd_x_m))
    v0, v1 = int(om.height_px - y1 / om.gsd_y_m), int(np.ceil(om.height_px - y0 / om.gsd_y_m))
    crop = _map_crop(om, u0, u1, v0, v1, max_px)
    fig, ax = plt.subplots(figsize=(8, 8 * (y1 - y0) / max(x1 - x0, 1e-9)))
    ax.imshow(crop, extent=_world_extent(om, u0, u1, v0, v1), interpolation="bilinear")
    ax.plot(truth[:, 0], truth[:, 1], "-", color="lime", lw=2, label="true track")
    ax.plot(est[:, 0], est[:, 1], ".", color="orange", ms=3, label=f"{agent.display} estimates")
    if rec["particles"] is not None:
        p = np.asarray(rec["particles"])
        ax.scatter(p[:, 0], p[:, 1], s=2, c="red", alpha=0.5, lw=0, label="final particles")
    mask = rec["shadow_mask"]
    pose = truth[-1]
    if mask is not None and np.any(mask):
        h, w = mask.shape
        scale = np.diag([cam.width_px / w, cam.height_px / h, 1.0])
        a = cam.camera_to_world(pose[0], pose[1], pose[2], pose[3]).reshape(2, 3) @ scale
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        for i, c in enumerate(contours):
            c = c.reshape(-1, 2).astype(float)
            xy = c @ a[:, :2].T + a[:, 2]
            ax.plot(np.r_[xy[:, 0], xy[:1, 0]], np.r_[xy[:, 1], xy[:1, 1]], "-", color="cyan", lw=0.8,
                    label="shadow in the last frame" if i == 0 else None)
    corners = np.array([[0, 0], [cam.width_px, 0], [cam.width_px, cam.height_px], [0, cam.height_px], [0, 0]],
                       float)
    a = cam.camera_to_world(pose[0], pose[1], pose[2], pose[3]).reshape(2, 3)
    fp = corners @ a[:, :2].T + a[:, 2]
    ax.plot(fp[:, 0], fp[:, 1], "--", color="white", lw=1, label="last footprint")
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_xlabel("x east [m]")
    ax.set_ylabel("y north [m]")
    ax.set_title(f"{scenario.display}, seed {seed}: {agent.display}")
    ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    return _save(fig, path)


def likelihood_surface(agent: AgentEntry, scenario: ScenarioEntry, seed: int, *, radius_m: float = 40.0,
                       step_m: float = 1.0, frame: int | None = None) -> dict[str, Any] | None:
    """The agent's measurement model's log-likelihood on a grid of positions around the true pose (true yaw
    and altitude) for one frame (default: the middle of the episode); None for agents without one."""
    from aerial_loc_env.benchmark.episodes import make_benchmark_env
    from aerial_loc_env.estimators.episode import oracle_info, uses_ground_truth
    from aerial_loc_env.estimators.registry import make_agent

    ag = make_agent(agent.name, **agent.params)
    model = getattr(ag, "measurement", None)
    if model is None:
        return None
    env = make_benchmark_env(scenario, shadow_mask=uses_ground_truth(model))
    obs, info = env.reset(seed=seed)
    n_frames = int(round(env.scenario.flight.duration_s * env.scenario.flight.rate_hz))
    target = n_frames // 2 if frame is None else frame
    for _ in range(max(0, target)):
        obs, _r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        if terminated or truncated:
            break
    rng = np.random.default_rng(seed)
    model.reset(env.briefing, rng)
    prepared = model.prepare(obs, rng, oracle_info(model, info))
    x, y, yaw, alt = (float(v) for v in info["true_pose"])
    offs = np.arange(-radius_m, radius_m + step_m / 2, step_m)
    gx, gy = np.meshgrid(x + offs, y + offs)
    states = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, yaw)])
    om = env.briefing.orthomap
    inside = ((states[:, 0] >= 0) & (states[:, 0] <= om.width_m)
              & (states[:, 1] >= 0) & (states[:, 1] <= om.height_m))
    ll = np.full(gx.size, np.nan)
    ll[inside] = model.log_likelihood(prepared, states[inside], float(obs["altitude"][0]))
    return {"offsets_m": offs, "log_likelihood": ll.reshape(gx.shape),
            "shadow_fraction": info["shadow_fraction"], "stats": dict(getattr(model, "last_stats", {}))}


def most_shadowed_frame(scenario: ScenarioEntry, seed: int) -> int:
    """The index of the episode's frame with the largest ground-truth shadow fraction."""
    from aerial_loc_env.benchmark.episodes import make_benchmark_env

    env = make_benchmark_env(scenario)
    _obs, info = env.reset(seed=seed)
    fractions = [info["shadow_fraction"]]
    while True:
        _obs, _r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
        fractions.append(info["shadow_fraction"])
        if terminated or truncated:
            return int(np.argmax(fractions))


def likelihood_plot(agents: Sequence[AgentEntry], scenarios: Sequence[ScenarioEntry], seed: int, path: Path,
                    **kwargs: Any) -> Path | None:
    """Figs. 26-34: one panel per (measurement model, scenario), the log-likelihood relative to its maximum
    around the true position (the cross), colours from its 5th percentile to 0; scenarios side by side. The
    frame (unless ``frame=`` is given) is the first scenario's most shadowed one, the same index in all."""
    plt = _plt()
    if kwargs.get("frame") is None:
        kwargs["frame"] = most_shadowed_frame(scenarios[0], seed)
    surfaces = []
    for agent in agents:
        row = [likelihood_surface(agent, s, seed, **kwargs) for s in scenarios]
        if all(r is not None for r in row):
            surfaces.append((agent, row))
    if not surfaces:
        return None
    fig, axes = plt.subplots(len(surfaces), len(scenarios),
                             figsize=(3.4 * len(scenarios), 3.0 * len(surfaces)), squeeze=False)
    for i, (agent, row) in enumerate(surfaces):
        for j, (scenario, surf) in enumerate(zip(scenarios, row, strict=True)):
            ax = axes[i, j]
            ll = surf["log_likelihood"]
            rel = ll - np.nanmax(ll) if np.isfinite(ll).any() else ll
            lo = float(np.nanpercentile(rel, 5)) if np.isfinite(rel).any() else -1.0
            r = float(surf["offsets_m"][-1])
            im = ax.imshow(rel, origin="lower", extent=(-r, r, -r, r), cmap="viridis",
                           vmin=min(lo, -1e-6), vmax=0)
            ax.plot(0, 0, "r+", ms=10)
            shade = surf["shadow_fraction"]
            ax.set_title(f"{agent.display}\n{scenario.display} (frame {kwargs['frame']}, shadow {shade:.0%})",
                         fontsize=8)
            ax.set_xlabel("east offset [m]", fontsize=7)
            ax.set_ylabel("north offset [m]", fontsize=7)
            ax.tick_params(labelsize=7)
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04)
    fig.tight_layout()
    return _save(fig, path)
