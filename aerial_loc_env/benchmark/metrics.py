"""Per-trial error statistics: the paper's RMSE and the second reference's mean / 95th percentile /
convergence."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: columns that measure time: they differ between two runs of the same trial, everything else is equal
TIMING_COLUMNS = ("step_time_median_ms", "step_time_p95_ms", "compute_time_total_s", "cpu_time_total_s",
                  "episode_render_cpu_s")


@dataclass(frozen=True)
class MetricConfig:
    converge_threshold_m: float = 10.0   # "converged" = error below this and staying below it to the end
    diverge_threshold_m: float = 50.0    # a trial whose final error exceeds this has diverged


def time_to_convergence(errors_m: np.ndarray, t_s: np.ndarray, threshold_m: float) -> float:
    """First time after which the error stays below ``threshold_m`` to the end; NaN if it never does."""
    errors_m = np.asarray(errors_m, dtype=float)
    above = np.flatnonzero(~(errors_m < threshold_m))
    if above.size == 0:
        return float(t_s[0])
    last_above = above[-1]
    if last_above == errors_m.size - 1:
        return float("nan")
    return float(t_s[last_above + 1])


def trial_metrics(errors_m: np.ndarray, t_s: np.ndarray, step_times_s: np.ndarray,
                  cfg: MetricConfig = MetricConfig()) -> dict[str, float]:
    """The figures of one trial from its per-step horizontal errors and per-step compute times."""
    e = np.asarray(errors_m, dtype=float)
    t = np.asarray(t_s, dtype=float)
    if e.size == 0:
        raise ValueError("trial_metrics: a trial needs at least one step")
    ttc = time_to_convergence(e, t, cfg.converge_threshold_m)
    after = e[t >= ttc] if np.isfinite(ttc) else np.empty(0)
    st = np.asarray(step_times_s, dtype=float)
    return {
        "rmse_m": float(np.sqrt(np.mean(e**2))),
        "rmse_converged_m": float(np.sqrt(np.mean(after**2))) if after.size else float("nan"),
        "final_error_m": float(e[-1]),
        "mean_error_m": float(np.mean(e)),
        "p95_error_m": float(np.percentile(e, 95)),
        "max_error_m": float(np.max(e)),
        "time_to_converge_s": ttc,
        "converged": bool(np.isfinite(ttc)),
        "diverged": bool(e[-1] > cfg.diverge_threshold_m),
        "step_time_median_ms": float(np.median(st) * 1e3) if st.size else float("nan"),
        "step_time_p95_ms": float(np.percentile(st, 95) * 1e3) if st.size else float("nan"),
        "compute_time_total_s": float(np.sum(st)),
        "steps": int(e.size),
    }
