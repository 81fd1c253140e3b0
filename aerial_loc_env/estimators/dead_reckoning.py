"""Dead reckoning: the odometry alone from the prior mean, the floor every estimator must beat.

It integrates the same motion model as the MCL (the body-frame forward and lateral speeds rotated by the
mid-step heading = mean of the two measured headings) without noise, and grows the covariance by the odometry
noise per step on top of the prior's (each speed's noise along its body axis, the heading's across the step's
displacement), so that its reported uncertainty is honest. With a uniform prior it stays at the map centre
("lost" by its covariance).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

import numpy as np

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.motion import mid_heading
from aerial_loc_env.estimators.protocol import Agent, Estimate, parse_observation, prior_estimate

if TYPE_CHECKING:
    from aerial_loc_env.env.briefing import Briefing


class DeadReckoningAgent(Agent):
    """Integrates the measured body-frame velocity and heading from the prior's mean."""

    def reset(self, briefing: Briefing, *, seed: int | None = None) -> Estimate:
        self.briefing = briefing
        est = prior_estimate(briefing, status="dead_reckoning")
        self.xy = np.array([est.x_m, est.y_m])
        self.cov = np.asarray(est.cov_xy_m2, dtype=float)
        self.prev_yaw: float | None = None
        self.t = 0
        return est

    def anchor(self, xy_m: Any, cov_xy_m2: Any | None = None) -> None:
        """Restart the integration from a fix (a baseline's match, a policy's correction); the covariance is
        replaced when given, else kept."""
        self.xy = np.array(xy_m, dtype=float).reshape(2)
        if cov_xy_m2 is not None:
            self.cov = np.array(cov_xy_m2, dtype=float).reshape(2, 2)

    def step(self, observation: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> Estimate:
        if not hasattr(self, "briefing"):
            raise ConfigError("DeadReckoningAgent.step called before reset(briefing, seed=...)")
        obs = parse_observation(observation)
        dt = self.briefing.dt_s
        if self.t > 0:  # the first observation is taken at the start pose
            psi = mid_heading(self.prev_yaw, obs.yaw_rad, obs.yaw_rate_radps, dt)
            c, s = np.cos(psi), np.sin(psi)
            rot = np.array([[c, -s], [s, c]])
            step = rot @ np.array([obs.speed_mps * dt, obs.lateral_mps * dt])
            self.xy += step
            noise = self.briefing.odometry_noise
            speeds = np.diag([(noise.speed_std_mps * dt) ** 2, (noise.lateral_std_mps * dt) ** 2])
            across = np.array([-step[1], step[0]])      # a heading error turns the whole displacement
            self.cov = self.cov + rot @ speeds @ rot.T + (noise.heading_std_rad ** 2 / 2.0) * np.outer(across, across)
        self.prev_yaw = obs.yaw_rad
        self.t += 1
        return Estimate(float(self.xy[0]), float(self.xy[1]), yaw_rad=obs.yaw_rad, cov_xy_m2=self.cov.copy(),
                        status="dead_reckoning")
