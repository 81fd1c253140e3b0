"""Local registration on the learned encoder's correlation surface: the observation design, its policy in NumPy,
and the agent (``ppo-learned-registration``).

Per frame, the vehicle dead-reckons from its last estimate (the predicted position), embeds the camera frame with
the learned MCL encoder (``estimators.mcl.learned``: the full-resolution frame warped north-up by the measured
heading and altitude, box-filtered to the encoder's sampling) and correlates it with the map's embedding (embedded
once per map from the briefing's database) at a square grid of positions around the prediction:
``(2 half_cells + 1)^2`` positions ``step_m`` apart, row ``i`` at ``(i - half_cells) step_m`` metres north of it,
column ``j`` as many east. That surface (mean cosine similarities in [-1, 1]) is the policy's observation; its
action is the correction (east, north) in [-1, 1] times ``max_correction_m``, added to the prediction. With a
zero action it is dead reckoning.

The policy (``SurfacePolicy``) is a small CNN over the surface with a soft-argmax (the peak's position, which is the
correction when the peak is true) and pooled features, then an MLP: the same network as the SB3 features
extractor and policy head it was trained as (``learning.networks.SurfaceCNN``), run here in NumPy from a small
``.npz``, so the agent needs NumPy and OpenCV only; torch is for training (``learning.surface_train``).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.database import DatabaseWindow, WindowPolicy, read_by_window
from aerial_loc_env.estimators.dead_reckoning import DeadReckoningAgent
from aerial_loc_env.estimators.mcl.learned import (
    DEFAULT_WEIGHTS,
    LearnedConfig,
    LearnedModel,
    archive_bytes,
    checked_archive,
    write_archive,
)
from aerial_loc_env.estimators.protocol import Agent, Estimate, parse_observation, prior_estimate
from aerial_loc_env.paths import find_model_file
from aerial_loc_env.sensors.flight import footprint_radius_m

DEFAULT_POLICY = "models/ppo-learned-registration/policy.npz"
#: the policy file's format version (``meta["format"]``)
POLICY_FORMAT = 1
#: the observation's scale: the surface's mean cosines times this before the first convolution
SURFACE_GAIN = 10.0


@dataclass(frozen=True)
class SurfaceParams:
    """The observation's geometry: the grid of positions scored around the prediction, the correction's bound and
    the encoder's weights (package-relative, absolute or relative to the current directory)."""

    half_cells: int = field(default=16, metadata=rng(1, 64, doc="the grid has 2 half_cells + 1 positions a side"))
    step_m: float = field(default=2.5, metadata=rng(0.1, 50.0, doc="metres between the grid's positions"))
    max_correction_m: float = field(default=40.0, metadata=rng(0.1, 500.0, lo_open=True,
                                                                 doc="metres of correction per unit of action"))
    encoder: str = DEFAULT_WEIGHTS

    @property
    def side(self) -> int:
        return 2 * self.half_cells + 1

    def grid_m(self) -> np.ndarray:
        """(side * side, 2) the (east, north) offsets of the grid's positions, row-major (north, then east)."""
        k = (np.arange(self.side) - self.half_cells) * self.step_m
        north, east = np.meshgrid(k, k, indexing="ij")
        return np.stack([east.ravel(), north.ravel()], axis=1)


class SurfaceRegistration:
    """Dead reckoning plus corrections read off the learned encoder's correlation surface (see the module doc);
    the same object serves the training env and the deployed agent."""

    def __init__(self, params: SurfaceParams | None = None) -> None:
        self.params = params or SurfaceParams()
        self.model = LearnedModel(LearnedConfig(weights=self.params.encoder))
        self._grid = self.params.grid_m()
        self._dr = DeadReckoningAgent()
        self.predicted = np.zeros(2)
        self.prepared: Any = None

    @property
    def xy(self) -> np.ndarray:
        return self._dr.xy.copy()

    def reset(self, briefing: Any, start_xy_m: Any = None) -> None:
        """Start from the prior's mean (or ``start_xy_m``); embed the briefing's map (cached per map)."""
        if briefing.prior.kind != "gaussian":
            raise ConfigError(f"learned registration: scenario {briefing.scenario_id} has a {briefing.prior.kind} "
                              "prior; this design tracks from a gaussian prior (episode.start = 'tracking')")
        self.briefing = briefing
        self._dr.reset(briefing)
        if start_xy_m is not None:
            self._dr.anchor(start_xy_m)
        self.window_policy, self._window = None, None
        if read_by_window(briefing.orthomap):      # embed the window around the surface's reach, not the map
            camera, reach_m = briefing.camera, self.params.half_cells * self.params.step_m
            footprint = lambda alt: footprint_radius_m(*camera.footprint_m(alt))           # noqa: E731
            # windows start on the whole map's cell grid (the encoder's stride at its sampling), so a window's
            # cells sample the ground where the whole map's do
            m, weights = briefing.orthomap, self.model.weights
            cell_px = weights.encoder.stride * float(weights.meta["gsd_m"]) / min(m.gsd_x_m, m.gsd_y_m)
            self.window_policy = WindowPolicy(m, footprint, radius_m=lambda alt: footprint(alt) + reach_m,
                                              align_px=max(1, int(round(cell_px))))
            self._read_window(briefing.altitude_m)
        else:
            self.model.reset(briefing, np.random.default_rng(0))

    def _read_window(self, altitude_m: float) -> None:
        """On a map read by window: embed a new window when the surface around the dead-reckoned position nears the
        current one's edge."""
        box = self.window_policy.update(self._dr.xy[None], altitude_m)
        if box is not None:
            self._window = DatabaseWindow(self.briefing.orthomap, box, where="learned registration",
                                          previous=self._window)
            self.model.reset(dataclasses.replace(self.briefing, orthomap=self._window), np.random.default_rng(0))

    def surfaces(self, centres_xy_m: np.ndarray) -> np.ndarray:
        """(n, side, side) float32 surfaces of the current frame around each of ``centres_xy_m`` (n, 2)."""
        centres = np.asarray(centres_xy_m, dtype=np.float64).reshape(-1, 2)
        states = np.zeros((len(centres) * len(self._grid), 3))
        states[:, :2] = (centres[:, None, :] + self._grid[None, :, :]).reshape(-1, 2)
        side = self.params.side
        return self.model.scores(self.prepared, states).astype(np.float32).reshape(len(centres), side, side)

    def prepare(self, observation: Mapping[str, np.ndarray]) -> None:
        """Embed the frame (once; the surfaces read it)."""
        self.prepared = self.model.prepare(observation, np.random.default_rng(0))

    def observe(self, observation: Mapping[str, np.ndarray]) -> np.ndarray:
        """Predict with the odometry, embed the frame, and return the surface (1, side, side) around the
        prediction."""
        if not hasattr(self, "briefing"):
            raise ConfigError("SurfaceRegistration.observe called before reset(briefing)")
        self._dr.step(observation)
        self.predicted = self._dr.xy.copy()
        if self.window_policy is not None:
            self._read_window(parse_observation(observation).altitude_m)
        self.prepare(observation)
        return self.surfaces(self.predicted[None])

    def correct(self, action: Any) -> np.ndarray:
        """Apply the correction (east, north) in [-1, 1] x max_correction_m; return the estimate (kept on the
        map)."""
        a = np.clip(np.asarray(action, dtype=float).reshape(2), -1.0, 1.0) * self.params.max_correction_m
        m = self.briefing.orthomap
        self._dr.anchor(np.clip(self.predicted + a, [0.0, 0.0], [m.width_m, m.height_m]))
        return self._dr.xy.copy()


# ---------------------------------------------------------------------- the policy in NumPy
def conv2d(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Zero-padded ('same', odd k) stride-1 convolution of x (C, H, W) by w (O, C, k, k): torch's Conv2d."""
    c, h, wd = x.shape
    k = w.shape[2]
    p = k // 2
    xp = np.pad(x, ((0, 0), (p, p), (p, p)))
    cols = np.stack([xp[:, dy:dy + h, dx:dx + wd] for dy in range(k) for dx in range(k)], axis=1)  # (C, k*k, H, W)
    out = portable.matmul(w.reshape(w.shape[0], c * k * k), cols.reshape(c * k * k, h * wd))   # (no BLAS: the same
    return out.reshape(-1, h, wd) + b[:, None, None]                                         # floats on every CPU)


def surface_features(surface: np.ndarray, layers: list[tuple[np.ndarray, np.ndarray]], pool: int) -> np.ndarray:
    """``SurfaceCNN``'s features of one surface (side, side): the soft-argmax (east, north) in units of the half
    side, the peak's probability, the surface's max, mean and std, and the last hidden layer average-pooled to
    ``pool`` x ``pool`` (see ``learning.networks.SurfaceCNN``, which this mirrors)."""
    s = np.asarray(surface, np.float32)
    side = s.shape[-1]
    x = (s * SURFACE_GAIN)[None]
    hidden = x
    for i, (w, b) in enumerate(layers):
        x = conv2d(x, w, b)
        if i < len(layers) - 1:
            x = np.maximum(x, 0.0)
            hidden = x
    logits = x.reshape(-1)
    p = np.exp(logits - logits.max())
    p /= p.sum()
    half = (side - 1) / 2.0
    k = (np.arange(side, dtype=np.float32) - half) / half
    pm = p.reshape(side, side)
    soft = np.array([float((pm.sum(0) * k).sum()), float((pm.sum(1) * k).sum())], np.float32)
    c = hidden.shape[0]
    q = side // pool
    pooled = hidden[:, :q * pool, :q * pool].reshape(c, pool, q, pool, q).mean(axis=(2, 4)).reshape(-1)
    stats = np.array([p.max(), s.max(), s.mean(), s.std()], np.float32)
    return np.concatenate([soft, stats, pooled]).astype(np.float32)


class SurfacePolicy:
    """The trained policy's deterministic action (its Gaussian's mean) in NumPy, from a ``policy.npz``."""

    def __init__(self, arrays: Mapping[str, np.ndarray], meta: dict) -> None:
        self.meta = meta
        n_conv, n_mlp = int(meta["n_conv"]), int(meta["n_mlp"])
        self.conv = [(arrays[f"conv{i}_w"], arrays[f"conv{i}_b"]) for i in range(n_conv)]
        self.mlp = [(arrays[f"mlp{i}_w"], arrays[f"mlp{i}_b"]) for i in range(n_mlp)]
        self.head = (arrays["action_w"], arrays["action_b"])
        self.pool = int(meta["pool"])
        self.params = SurfaceParams(**meta["surface"])

    def features(self, surface: np.ndarray) -> np.ndarray:
        return surface_features(surface.reshape(self.params.side, self.params.side), self.conv, self.pool)

    def __call__(self, surface: np.ndarray) -> np.ndarray:
        h = self.features(surface).astype(np.float64)
        for w, b in self.mlp:
            h = np.tanh(portable.matmul(w, h) + b)
        w, b = self.head
        return np.clip(portable.matmul(w, h) + b, -1.0, 1.0)


def write_policy(arrays: Mapping[str, np.ndarray], meta: dict, path: Any, overwrite: bool = False) -> Any:
    """Write a policy ``.npz`` (float32 arrays and ``meta`` JSON); an existing file only with ``overwrite``."""
    return write_archive({**{k: np.asarray(v, np.float32) for k, v in arrays.items()},
                          "meta": np.array(json.dumps(meta))}, path, overwrite=overwrite, who="learned registration")


_POLICIES: dict[str, SurfacePolicy] = {}


def load_policy(path: str) -> SurfacePolicy:
    """Read and check a policy ``.npz`` (cached by path and content)."""
    file = find_model_file(path, "learned registration: params.policy", "train it with `aerial-loc train "
                           "ppo-learned-registration --out DIR` and point params.policy to DIR/policy.npz")
    raw, _digest, key = archive_bytes(file)
    if key in _POLICIES:
        return _POLICIES[key]
    why = f"learned registration: policy file '{file}'"
    remedy = "`aerial-loc train ppo-learned-registration`"
    arrays, meta = checked_archive(raw, why, "policy", remedy)
    try:
        if meta.get("format") != POLICY_FORMAT:
            raise ValueError(f"format {meta.get('format')!r}, expected {POLICY_FORMAT}")
        policy = SurfacePolicy(arrays, meta)
    except (ValueError, KeyError, TypeError) as exc:
        raise ConfigError(f"{why} is not a policy archive ({type(exc).__name__}: {exc}); write it again with "
                          f"{remedy}") from exc
    if not all(np.isfinite(a).all() for a in arrays.values()):
        raise ConfigError(f"{why}: the weights hold NaN or infinite values")
    _POLICIES[key] = policy
    return policy


# ---------------------------------------------------------------------- the agent
@dataclass(frozen=True)
class SurfaceAgentParams:
    policy: str = DEFAULT_POLICY      # a policy.npz written by `aerial-loc train ppo-learned-registration`


class SurfaceRegistrationAgent(Agent):
    """The trained local-registration policy on the learned encoder's surface (NumPy inference; module doc)."""

    Params = SurfaceAgentParams

    def __init__(self, params: SurfaceAgentParams = SurfaceAgentParams()) -> None:
        self.params = params
        self.policy = load_policy(params.policy)
        self.core = SurfaceRegistration(self.policy.params)

    def reset(self, briefing: Any, *, seed: int | None = None) -> Estimate:
        self.briefing = briefing
        self.core.reset(briefing)
        return prior_estimate(briefing)

    def step(self, observation: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> Estimate:
        if not hasattr(self, "briefing"):
            raise ConfigError("SurfaceRegistrationAgent.step called before reset(briefing, seed=...)")
        obs = parse_observation(observation, self.briefing, self.altitude_range_m(self.briefing), type(self).__name__)
        surface = self.core.observe(observation)
        x, y = self.core.correct(self.policy(surface))
        return Estimate(float(x), float(y), yaw_rad=float(obs.yaw_rad))


__all__ = ["SurfaceAgentParams", "SurfaceParams", "SurfacePolicy", "SurfaceRegistration", "SurfaceRegistrationAgent",
           "conv2d", "load_policy", "surface_features", "write_policy"]
