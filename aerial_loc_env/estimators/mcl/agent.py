"""``MCLAgent``: the Monte-Carlo localization agent, configured by a spec (agents/mcl-*.toml).

Its ``Params`` extend the filter's ``FilterConfig`` with the motion model, the point estimator and the
measurement model (a name registered in ``measurement.MODELS`` or a dotted path, with its own
``measurement_params`` table). The estimate carries the weighted covariance (the MAVLink fix quality), a
status from its spread, and extras for rendering and reports: ``particles`` (N, 3), ``weights`` (N,), ``ess``
and the measurement model's ``stats`` (``shadow_pairs``, ``num_pairs``, ...).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.core import FilterConfig, ParticleFilter
from aerial_loc_env.estimators.mcl.estimate import (
    circular_mean_of_yaws,
    max_std_m,
    mean_shift,
    weighted_cov,
    weighted_mean,
)
from aerial_loc_env.estimators.mcl.measurement import make_model
from aerial_loc_env.estimators.mcl.motion import OdometryMotionModel
from aerial_loc_env.estimators.protocol import Agent, Estimate, prior_estimate

if TYPE_CHECKING:
    from aerial_loc_env.env.briefing import Briefing


@dataclass(frozen=True)
class MCLParams(FilterConfig):
    """Filter settings (inherited) plus motion, estimator and measurement model."""

    state: str = field(default="xy", metadata=rng(choices=("xy", "xyyaw"),
                                                   doc="xy: heading measured (the paper); xyyaw: yaw is a state"))
    motion_noise_scale: float = field(default=1.0, metadata=rng(0.0, 100.0, doc="x the briefing's odometry noise"))
    jitter_std_m: float = field(default=0.5, metadata=rng(0.0, 100.0, doc="roughening per step"))
    estimator: str = field(default="weighted_mean", metadata=rng(choices=("weighted_mean", "mean_shift")))
    mean_shift_bandwidth_m: float = field(default=5.0, metadata=rng(0.0, 1e4, lo_open=True))
    measurement: str = "intensity_pairs_shadow_aware"
    measurement_params: dict = field(default_factory=dict)
    status_ok_std_m: float = field(default=10.0, metadata=rng(0.0, 1e5, lo_open=True,
                                                              doc="1-sigma below which the status is ok"))
    status_lost_std_m: float = field(default=50.0, metadata=rng(0.0, 1e5, lo_open=True,
                                                                doc="1-sigma above which the status is lost"))
    particles_in_extras: bool = True

    def validate(self, where: str) -> None:
        super().validate(where)
        if self.status_lost_std_m < self.status_ok_std_m:
            raise ConfigError(f"{where}: status_lost_std_m ({self.status_lost_std_m}) must be >= "
                              f"status_ok_std_m ({self.status_ok_std_m})")
        make_model(self.measurement, self.measurement_params, where=f"{where}: measurement_params")


class MCLAgent(Agent):
    """Monte-Carlo localization with a pluggable measurement model (default: the paper's shadow-aware one)."""

    Params = MCLParams

    def __init__(self, params: MCLParams | None = None) -> None:
        self.params = params or MCLParams()
        self.measurement = make_model(self.params.measurement, self.params.measurement_params)
        self.uses_ground_truth = self.measurement.uses_ground_truth
        self.filter: ParticleFilter | None = None

    def reset(self, briefing: Briefing, *, seed: int | None = None) -> Estimate:
        p = self.params
        self.rng = np.random.default_rng(seed)
        motion = OdometryMotionModel(briefing.odometry_noise, briefing.dt_s, state=p.state,
                                     noise_scale=p.motion_noise_scale, jitter_std_m=p.jitter_std_m)
        self.filter = ParticleFilter(p, motion, self.measurement)
        self.filter.initialize(briefing, self.rng)
        if p.init == "prior" and briefing.prior.kind == "gaussian":
            return prior_estimate(briefing)
        return self._estimate(self.filter.states, self.filter.W, {}, ess=float(p.n_particles), injected=0)

    def step(self, observation: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> Estimate:
        if self.filter is None:
            raise ConfigError("MCLAgent.step called before reset(briefing, seed=...)")
        r = self.filter.step(observation, info)
        return self._estimate(r.states, r.W, r.stats, ess=r.ess, injected=r.injected)

    def _estimate(self, states: np.ndarray, W: np.ndarray, stats: dict, *, ess: float, injected: int) -> Estimate:
        p = self.params
        xy = states[:, :2]
        if p.estimator == "mean_shift":
            center = mean_shift(xy, W, p.mean_shift_bandwidth_m, rng=self.rng)
        else:
            center = weighted_mean(xy, W)
        cov = weighted_cov(xy, W, center)
        std = max_std_m(cov)
        status = "ok" if std <= p.status_ok_std_m else "degraded" if std <= p.status_lost_std_m else "lost"
        stats = dict(stats)
        if "K" in stats:
            stats.setdefault("num_pairs", stats["K"])
        extras: dict[str, Any] = {"ess": ess, "injected": injected, "stats": stats}
        if p.particles_in_extras:
            extras["particles"] = states.astype(np.float32)
            extras["weights"] = W.astype(np.float32)
        return Estimate(float(center[0]), float(center[1]), yaw_rad=circular_mean_of_yaws(states, W),
                        cov_xy_m2=cov, status=status, extras=extras)
