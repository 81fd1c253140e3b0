"""Per-trial error statistics: the paper's RMSE and the second reference's mean / 95th percentile /
convergence."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: columns that measure time: they differ between two runs of the same trial, everything else is equal
TIMING_COLUMNS = ("step_time_median_ms", "step_time_p95_ms", "compute_time_total_s", "cpu_time_total_s",
                  "episode_render_cpu_s")


#: the paper's 10 m convergence threshold is 1/15 of its 150 m footprint; scaled scenarios keep that ratio
FOOTPRINT_FRACTION = 1.0 / 15.0
#: diverged: a final error this many times the convergence threshold (the paper's 50 m for 10 m)
DIVERGE_FACTOR = 5.0
#: estimate statuses that are an absolute fix (a dead-reckoned, degraded or lost estimate is not)
FIX_STATUSES = ("ok",)


@dataclass(frozen=True)
class MetricConfig:
    """Thresholds of 'converged' (the error falls below it and stays there to the end) and 'diverged' (a
    final error above it). ``None``: scaled with the scenario (``for_scenario``)."""

    converge_threshold_m: float | None = 10.0
    diverge_threshold_m: float | None = 50.0

    def for_scenario(self, scenario) -> MetricConfig:
        """Concrete thresholds for ``scenario`` (an ``env.Scenario``): the fixed ones where given, else
        ``converge = min(footprint width / 15, prior sigma)`` (the paper's 10 m at its 150 m footprint and
        15 m prior; never above the prior's own spread, so that dead reckoning from a tight prior does not
        'converge' at the first step) and ``diverge = 5 x converge``."""
        converge, diverge = self.converge_threshold_m, self.diverge_threshold_m
        if converge is None:
            converge = scaled_converge_threshold_m(scenario)
        if diverge is None:
            diverge = max(DIVERGE_FACTOR * converge, converge)
        return MetricConfig(float(converge), float(diverge))


def scaled_converge_threshold_m(scenario) -> float:
    """``min(footprint width * FOOTPRINT_FRACTION, prior sigma)`` of a scenario (see MetricConfig)."""
    width_m, _ = scenario.camera.footprint_m(scenario.flight.altitude_m)
    threshold = width_m * FOOTPRINT_FRACTION
    if scenario.episode.start == "tracking":
        threshold = min(threshold, float(scenario.episode.prior_std_m))
    return float(threshold)


def fix_rate(statuses) -> float:
    """Fraction of the steps whose estimate is an absolute fix (status 'ok'): a baseline that never fixes
    (and so equals dead reckoning) shows 0."""
    statuses = list(statuses)
    return float(np.mean([s in FIX_STATUSES for s in statuses])) if statuses else float("nan")


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
    if cfg.converge_threshold_m is None or cfg.diverge_threshold_m is None:
        raise ValueError("trial_metrics: resolve scaled thresholds first (MetricConfig.for_scenario)")
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
        "converge_threshold_m": float(cfg.converge_threshold_m),
        "diverge_threshold_m": float(cfg.diverge_threshold_m),
        "step_time_median_ms": float(np.median(st) * 1e3) if st.size else float("nan"),
        "step_time_p95_ms": float(np.percentile(st, 95) * 1e3) if st.size else float("nan"),
        "compute_time_total_s": float(np.sum(st)),
        "steps": int(e.size),
    }
