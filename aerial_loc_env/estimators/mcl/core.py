"""The MCL filter loop (Choi & Park, Tables 1 and 3), kept apart from the state-space model.

One ``step``: propagate by the odometry (``motion.py``), add the measurement model's log-likelihoods to the
log-weights, normalize (log-sum-exp), take the point estimate, then resample (every step as in the paper, or
when the effective sample size falls below ``ess_threshold * N``) and inject fresh particles when the weights
collapse. Everything is vectorized over particles.

Initialisation: from the briefing's Gaussian prior (tracking), or uniform over the valid map (global
localization: points where the whole camera footprint, whatever the yaw, lies on valid map).

A map read by window (a city-scale COG, ``estimators/database.py``): the measurement model is reset with the
window around the particles (``DatabaseWindow``) and again, with the random generator as it was at the episode's
reset (so the same per-episode draws), whenever the cloud nears that window's edge; the estimates are those on the
map loaded whole. Global localization there is refused (it searches the whole map), and injected particles are
drawn in the current window (there is no whole map to draw them from).

Recovery (augmented MCL, Thrun et al., Probabilistic Robotics 8.3.5): running averages of the mean
likelihood, ``w_slow`` and ``w_fast`` (rates ``alpha_slow < alpha_fast``), kept in the log domain; when the
recent likelihood falls below the long-term one, a fraction ``max(floor, 1 - w_fast / w_slow)`` (capped) of the
particles is replaced by uniform draws over the valid map. ``injection_fraction`` is a constant floor, which
also recovers from a wrong prior when the filter never saw a good likelihood to compare with.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.estimators import protocol
from aerial_loc_env.estimators.database import DatabaseWindow, WindowPolicy, read_by_window, refuse_global_search
from aerial_loc_env.estimators.mcl import resampling
from aerial_loc_env.estimators.mcl.measurement import MeasurementModel
from aerial_loc_env.estimators.mcl.motion import OdometryMotionModel

if TYPE_CHECKING:
    from collections.abc import Mapping

    from aerial_loc_env.env.briefing import Briefing


@dataclass(frozen=True)
class FilterConfig:
    """Particle-filter settings (the paper: 700 particles, multinomial resampling every step)."""

    n_particles: int = field(default=700, metadata=rng(1, 10_000_000))
    resampling: str = field(default="multinomial", metadata=rng(choices=tuple(resampling.SCHEMES)))
    resample: str = field(default="always", metadata=rng(choices=("always", "ess")))
    ess_threshold: float = field(default=0.5, metadata=rng(0.0, 1.0, doc="resample when ESS < this * N"))
    init: str = field(default="prior", metadata=rng(choices=("prior", "uniform"),
                                                     doc="prior: the briefing's; uniform: global localization"))
    injection_fraction: float = field(default=0.0, metadata=rng(0.0, 1.0, doc="uniform particles per step"))
    injection_alpha_slow: float = field(default=0.0, metadata=rng(0.0, 1.0, doc="0 disables augmented MCL"))
    injection_alpha_fast: float = field(default=0.0, metadata=rng(0.0, 1.0))
    injection_max_fraction: float = field(default=0.25, metadata=rng(0.0, 1.0))

    def validate(self, where: str) -> None:
        if self.injection_alpha_slow > 0 and not self.injection_alpha_fast > self.injection_alpha_slow:
            raise ConfigError(f"{where}: injection_alpha_fast ({self.injection_alpha_fast}) must exceed "
                              f"injection_alpha_slow ({self.injection_alpha_slow})")


class ValidRegion:
    """Uniform sampling over the points where the camera footprint fits on valid map."""

    def __init__(self, briefing: Briefing) -> None:
        from aerial_loc_env.sensors.flight import footprint_radius_m
        from aerial_loc_env.world.maps.region import FlyableRegion

        m = briefing.orthomap
        radius = footprint_radius_m(*briefing.camera.footprint_m(briefing.altitude_m))
        self.offset_m = np.zeros(2)
        width_m, height_m, nodata = m.width_m, m.height_m, m.nodata
        if isinstance(m, DatabaseWindow):   # the window's part of the map (its south-west corner at offset_m)
            u0, v0, u1, v1 = m.box
            width_m, height_m = (u1 - u0) * m.gsd_x_m, (v1 - v0) * m.gsd_y_m
            self.offset_m = np.array([u0 * m.gsd_x_m, (m.height_px - v1) * m.gsd_y_m])
        self.region = FlyableRegion(width_m, height_m, radius, nodata=nodata, name=m.name)
        if self.region.area_m2 <= 0:  # a map smaller than the footprint: any point of it
            self.region = FlyableRegion(width_m, height_m, 0.0, nodata=nodata, name=m.name)

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        return self.region.sample(rng, n) + self.offset_m


@dataclass
class StepResult:
    """What one filter step leaves: the weighted states before resampling (for the estimate), their normalized
    weights, the ESS, the log mean likelihood, whether it resampled, and how many particles it injected."""

    states: np.ndarray
    W: np.ndarray
    ess: float
    log_mean_likelihood: float
    resampled: bool
    injected: int
    stats: dict[str, Any] = field(default_factory=dict)


class ParticleFilter:
    """Sequential importance resampling over (N, 3) states [x_m, y_m, yaw_rad] with log-weights."""

    def __init__(self, config: FilterConfig, motion: OdometryMotionModel, measurement: MeasurementModel) -> None:
        self.config, self.motion, self.measurement = config, motion, measurement
        self.resample_fn = resampling.get_scheme(config.resampling)
        self.states = np.zeros((config.n_particles, 3))
        self.log_w = np.zeros(config.n_particles)
        self.W = np.full(config.n_particles, 1.0 / config.n_particles)
        self._uniform_log_w = True
        self.t = 0

    # ---------------------------------------------------------------- initialization
    def initialize(self, briefing: Briefing, rng: np.random.Generator) -> None:
        n = self.config.n_particles
        self.briefing, self.rng = briefing, rng
        prior = briefing.prior
        tracking = self.config.init == "prior" and prior.kind == "gaussian"
        self.policy: WindowPolicy | None = None
        self._window: DatabaseWindow | None = None
        if read_by_window(briefing.orthomap):
            self._check_windowed(briefing, tracking)
        else:
            self.region = ValidRegion(briefing)
        self.states = np.zeros((n, 3))
        if tracking:
            self.states[:, :2] = np.asarray(prior.mean_xy_m) + rng.normal(0.0, prior.std_xy_m, (n, 2))
        else:
            self.states[:, :2] = self.region.sample(n, rng)
        self.yaw_initialized = False
        self.log_w = np.zeros(n)
        self._uniform_log_w = True       # log_w all zeros (step: its log-mean is then the likelihoods')
        self.W = np.full(n, 1.0 / n)
        self.log_w_slow = self.log_w_fast = None
        self.motion.reset()
        if self.policy is not None:
            self._reset_rng = copy.deepcopy(rng)     # the per-episode draws, made again for every window
            self._read_window(briefing.altitude_m, rng)
        else:
            self.measurement.reset(briefing, rng)
        self.t = 0

    # ---------------------------------------------------------------- maps read by window
    def _check_windowed(self, briefing: Briefing, tracking: bool) -> None:
        from aerial_loc_env.sensors.flight import footprint_radius_m

        m, where = briefing.orthomap, "MCL"
        if not tracking:
            why = "init = 'uniform'" if self.config.init == "uniform" else f"a {briefing.prior.kind} prior"
            refuse_global_search(m, where, f"global localization ({why})")
        if not _reads_windows(self.measurement):
            raise MapError(f"{where}: measurement model {type(self.measurement).__name__} reads its whole database at "
                           f"reset, but map '{m.name}' is read by window; give the model a class attribute "
                           "reads_windows = True once its reset takes an estimators.database.DatabaseWindow (the "
                           "window's pixels, the whole map's geometry), or load the map whole (map.read = 'whole')")
        camera = briefing.camera
        self.policy = WindowPolicy(m, lambda alt: footprint_radius_m(*camera.footprint_m(alt)))

    def _read_window(self, altitude_m: float, rng: np.random.Generator | None = None) -> None:
        """Reset the measurement model with a new window when the cloud nears the current one's edge (with
        ``rng`` at the episode's reset, else with a copy of the generator as it was then)."""
        box = self.policy.update(self.states[:, :2], altitude_m)
        if box is None:
            return
        self._window = window = DatabaseWindow(self.briefing.orthomap, box, where="MCL",
                                               previous=self._window)
        briefing = dataclasses.replace(self.briefing, orthomap=window)
        self.measurement.reset(briefing, rng if rng is not None else copy.deepcopy(self._reset_rng))
        self.region = None                            # (made when particles are injected: _inject)

    # ---------------------------------------------------------------- one step
    def step(self, observation: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> StepResult:
        cfg, rng = self.config, self.rng
        obs = protocol.parse_observation(observation, self.briefing)
        if not self.yaw_initialized:
            self.states[:, 2] = self.motion.init_yaw(self.states.shape[0], obs.yaw_rad, rng)
            self.yaw_initialized = True
        if self.t > 0:  # the first observation is taken at the start pose: nothing has been flown yet
            self.motion.propagate(self.states, obs, rng)
        else:
            self.motion.prev_yaw_rad = obs.yaw_rad
        self.t += 1
        if self.policy is not None:
            self._read_window(obs.altitude_m)
        prepared = self.measurement.prepare(observation, rng, info)
        ll = self.measurement.log_likelihood(prepared, self.states, obs.altitude_m)
        if self.motion.state != "xy":     # (the "xy" layout's compass factor is zero)
            ll = ll + self.motion.compass_log_likelihood(self.states, obs.yaw_rad)
        uniform = self._uniform_log_w
        self.log_w = self.log_w + ll
        self.W, log_mean_w = resampling.normalize_log_weights(self.log_w)
        # after a resampling the log-weights were zeros, so log_w holds ll's values: their log-mean is at hand
        log_mean_lik = log_mean_w if uniform else resampling.log_mean_weight(ll)
        ess = resampling.ess(self.W)
        n_inject = self._injection_count(log_mean_lik)
        resampled = cfg.resample == "always" or ess < cfg.ess_threshold * self.W.shape[0] or n_inject > 0
        states_est, W_est = self.states, self.W
        if resampled:
            idx = self.resample_fn(self.W, self.W.shape[0], rng)
            self.states = self.states[idx]
            self.log_w = np.zeros(self.W.shape[0])
            self.W = np.full(self.W.shape[0], 1.0 / self.W.shape[0])
            if n_inject > 0:
                self._inject(n_inject, obs.yaw_rad)
        else:
            self.log_w = self.log_w - float(np.max(self.log_w))  # keep log-weights bounded
        self._uniform_log_w = resampled
        return StepResult(states_est, W_est, ess, log_mean_lik, resampled, n_inject, dict(self.measurement.last_stats))

    def _injection_count(self, log_mean_lik: float) -> int:
        cfg = self.config
        frac = cfg.injection_fraction
        if cfg.injection_alpha_slow > 0 and math.isfinite(log_mean_lik):
            if self.log_w_slow is None:
                self.log_w_slow = self.log_w_fast = log_mean_lik
            else:
                self.log_w_slow = _log_ema(self.log_w_slow, log_mean_lik, cfg.injection_alpha_slow)
                self.log_w_fast = _log_ema(self.log_w_fast, log_mean_lik, cfg.injection_alpha_fast)
            frac = max(frac, 1.0 - math.exp(min(0.0, self.log_w_fast - self.log_w_slow)))
        elif not math.isfinite(log_mean_lik):  # every particle impossible: restart from the valid map
            frac = 1.0
        frac = min(frac, max(cfg.injection_max_fraction, cfg.injection_fraction)) if frac < 1.0 else 1.0
        return int(round(frac * self.states.shape[0]))

    def _inject(self, n: int, yaw_rad: float) -> None:
        idx = self.rng.choice(self.states.shape[0], size=n, replace=False)
        if self.region is None:     # a map read by window: the current window's valid part
            self.region = ValidRegion(dataclasses.replace(self.briefing, orthomap=self._window))
        self.states[idx, :2] = self.region.sample(n, self.rng)
        self.states[idx, 2] = self.motion.init_yaw(n, yaw_rad, self.rng)

    # ---------------------------------------------------------------- summaries
    @property
    def xy(self) -> np.ndarray:
        return self.states[:, :2]


def _reads_windows(model: MeasurementModel) -> bool:
    """Whether ``model``'s reset takes a ``DatabaseWindow``: the built-in models (through ``PatchSampler`` or their
    own window branch), or a model that says so (``reads_windows = True``)."""
    from aerial_loc_env.estimators.mcl.abbrief import ABBriefModel
    from aerial_loc_env.estimators.mcl.dense import DenseModel
    from aerial_loc_env.estimators.mcl.edges import EdgeOrientationModel
    from aerial_loc_env.estimators.mcl.intensity_pairs import IntensityPairsModel

    builtin = (ABBriefModel, DenseModel, EdgeOrientationModel, IntensityPairsModel)
    return bool(getattr(model, "reads_windows", False)) or isinstance(model, builtin)


def _log_ema(log_avg: float, log_x: float, alpha: float) -> float:
    """log((1 - alpha) exp(log_avg) + alpha exp(log_x)) without overflow."""
    return float(np.logaddexp(math.log1p(-alpha) + log_avg, math.log(alpha) + log_x))
