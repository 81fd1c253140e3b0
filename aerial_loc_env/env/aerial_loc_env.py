"""``AerialLocEnv``: image-based absolute localization of a drone over an orthomap, as a Gymnasium env.

The class docstring is the env's documentation, in Gymnasium's sections (Description, Action Space,
Observation Space, Rewards, Starting State, Episode End, Arguments, Version History).
"""

from __future__ import annotations

import copy
import math
from collections.abc import Mapping
from typing import Any

import cv2
import gymnasium as gym
import numpy as np
from gymnasium import spaces

from aerial_loc_env.env.briefing import Briefing, Prior
from aerial_loc_env.env.scenarios import Scenario, build_scenario, check_relief, load_scenario
from aerial_loc_env.errors import AerialLocError, ConfigError, MapError
from aerial_loc_env.sensors.camera import CameraModel, Pose, SceneExposure, apply_affine, world_to_map_affine
from aerial_loc_env.sensors.flight import (
    Measurements,
    Track,
    add_lateral_noise,
    footprint_radius_m,
    measure,
    sample_track,
    wrap_angle,
)
from aerial_loc_env.world.scene import WorldSpec, build_world

ODOMETRY_SPEED_MAX_MPS = 500.0
ODOMETRY_YAW_RATE_MAX_RADPS = 20.0
ALTITUDE_MAX_M = 20000.0
OVERVIEW_PX = 512
#: the stream index of the lateral odometry noise's generator (``AerialLocEnv.lateral_rng``)
LATERAL_NOISE_STREAM = 1


class InvalidActionError(AerialLocError, ValueError):
    """An action that is not a finite float (2,) estimate in [-1, 1]."""


# ------------------------------------------------------------------------------------ action <-> world
def world_to_action(orthomap: Any, x_m: Any, y_m: Any) -> np.ndarray:
    """Metres -> normalized action ``2 * (x / width_m, y / height_m) - 1`` (float32, last axis 2)."""
    x = np.asarray(x_m, dtype=np.float64)
    y = np.asarray(y_m, dtype=np.float64)
    a = np.stack([2.0 * x / orthomap.width_m - 1.0, 2.0 * y / orthomap.height_m - 1.0], axis=-1)
    return a.astype(np.float32)


def action_to_world(orthomap: Any, action: Any) -> tuple[Any, Any]:
    """Normalized action (..., 2) -> metres ``(x_m, y_m)``; the inverse of ``world_to_action``."""
    a = np.asarray(action, dtype=np.float64)
    x = (a[..., 0] + 1.0) * 0.5 * orthomap.width_m
    y = (a[..., 1] + 1.0) * 0.5 * orthomap.height_m
    return (float(x), float(y)) if a.ndim == 1 else (x, y)


class AerialLocEnv(gym.Env):
    """A drone flies over an orthomap; from its camera frames and odometry, estimate where it is.

    ## Description

    Image-based absolute localization without GNSS. One episode is one flight (``sensors.flight``): a track at
    constant altitude over valid map, drawn from the episode seed; per step a nadir, gimbaled camera frame
    rendered from the map with shadows (cast by buildings, or clouds) that the map database lacks, and the
    vehicle's noisy odometry, heading and altitude. The agent answers each frame with its position estimate.

    Time line: ``reset`` returns the frame taken at pose 0; ``step(action)`` scores ``action`` as the estimate
    of the pose where the *last returned* frame was taken, then returns the next frame. A track of ``n`` steps
    has ``n + 1`` poses; the last frame ends the episode and is not scored (the episode driver,
    ``aerial_loc_env.estimators.episode``, still lets agents estimate on it).

    What an estimator may know besides the observations is ``env.unwrapped.briefing`` (a ``Briefing``: the
    database map, the camera model, the prior, the odometry noise model, the time step): its map is the
    shadow-free scene, or with ``shadows.database_sun_deg`` the scene under another sun, or with
    ``[database]`` the scene as a real map was acquired; with ``[epoch]`` the camera flies over epoch B of the
    ground (``env.orthomap``) while the map shows epoch A (``env.database``). ``info`` is the simulator's
    ground truth, for scoring, reports and oracles; agents must not read it: ``true_pose`` (x_m, y_m, yaw_rad,
    altitude_m) of the returned frame, ``time_s``, ``step``, ``prior``, ``shadow_fraction``, ``sun_azimuth_deg``,
    ``sun_elevation_deg``, ``shadow_strength``; after a step ``position_error_m`` and ``estimate_xy_m`` of the
    scored action; with ``observation.info_shadow_mask`` the frame's ground-truth ``shadow_mask`` (H, W) bool;
    with ``[gimbal]`` jitter the frame's ``gimbal_roll_pitch_rad``, with auto-exposure its ``exposure_gain``, with
    ``[wind]`` the wind at the frame ``wind_en_mps`` (east, north; ``env.unwrapped.wind`` holds the episode's).

    The camera is the map re-projected by one affine warp unless ``[perspective]`` renders the height model as
    a pinhole camera sees it (relief displacement, facades, occlusion); ``[gimbal]``, ``[altimeter]``,
    ``[exposure]`` and ``[haze]`` add attitude jitter and a heading offset, barometric bias and drift,
    auto-exposure and haze. All are off by default.

    ``render_mode="rgb_array"``: a north-up overview around the vehicle with the camera frame (and its shadows)
    in its footprint, the true track so far (green), the estimates (red), the prior (cyan) and the points an
    agent hands to ``set_overlay`` (e.g. particles, magenta).

    ## Action Space

    ``Box(-1, 1, (2,), float32)``: the position estimate normalized over the map extent,
    ``a = 2 * (x_m / width_m, y_m / height_m) - 1`` in the world frame (x east, y north, origin at the map's
    south-west corner); convert with ``aerial_loc_env.env.world_to_action`` / ``action_to_world``. Wrong
    shapes or dtypes, NaN/inf and values outside [-1, 1] raise ``InvalidActionError``.

    ## Observation Space

    A flat ``Dict`` (SB3's ``MultiInputPolicy`` takes it as is):

    | key | space | meaning |
    |---|---|---|
    | ``image`` | ``Box(0, 255, (H, W, 3), uint8)`` | the camera frame; the top of the image points along the heading |
    | ``odometry`` | ``Box((3,), float32)`` | measured ``[forward_speed_mps, yaw_rate_radps, lateral_speed_mps]`` |
    | ``yaw`` | ``Box(-pi, pi, (1,), float32)`` | measured heading ``yaw_rad`` (ENU, counter-clockwise from east) |
    | ``altitude`` | ``Box(0, ALTITUDE_MAX_M, (1,), float32)`` | measured altitude above ground, metres |

    The odometry is what a flow sensor or the autopilot's velocity estimate gives over the last step: the ground
    velocity in the body frame, forward along the heading and lateral (positive to the left), and the yaw rate.
    In wind the vehicle crabs (its heading is not its course), and the lateral speed is what moves it sideways.
    ``H, W`` are ``observation.height_px/width_px`` (default: the camera's). Bounds are finite (speeds
    +-``ODOMETRY_SPEED_MAX_MPS``, yaw rate +-``ODOMETRY_YAW_RATE_MAX_RADPS``, altitude ``[0, ALTITUDE_MAX_M]``;
    measurements are clipped to them) so that both checkers stay silent.

    ## Rewards

    ``-position_error_m / reward.scale_m`` per step (default scale 100 m): the horizontal error of the action
    against the true position of the frame it answers. The benchmark reports errors in metres instead (RMSE,
    convergence, final error); the reward is for learned policies.

    ## Starting State

    ``reset(seed=...)`` draws everything from ``self.np_random``: with ``[wind]`` on, the wind first (the mean
    and the gusts, ``world.wind``) from a child of its seed sequence (``wind_rng``; off, nothing is drawn), and
    a windy episode is the calm episode of its seed plus the wind (``_fly_track``); the track (start uniformly
    over the flyable region, the part of the map whose footprint clearance ``flight.margin_m`` stays on valid
    data; waypoint legs at the airspeed ``flight.speed_mps`` and ``flight.altitude_m``, the course held through
    the wind), the odometry noise (the lateral speed's from a generator seeded by the episode's draws,
    ``lateral_rng``), the sun and the shadow strength, the clouds, and the renderer's noise; then the prior and,
    when their sections are on, the gimbal jitter, the heading offset and the altimeter's bias and drift (off,
    they draw nothing). The prior: with ``episode.start = "tracking"`` a Gaussian whose mean is drawn
    ``episode.prior_std_m`` (1-sigma per axis) around the true start; with ``"global"`` uniform over the map.
    Same seed, same episode, bit for bit.

    ## Episode End

    Truncation at the end of the track (``flight.duration_s`` at ``flight.rate_hz``; shorter only when the
    region cannot hold the full track, never below ``flight.min_steps``). Termination only on the documented
    failure: the error above ``episode.failure_error_m`` for ``episode.failure_steps`` consecutive steps (off
    by default, ``failure_error_m = 0``); ``info["failure"]`` then says why. No time limit wrapper is needed.

    ## Arguments

    ``gym.make("AerialLoc/<Name>-v<N>", render_mode=None, **overrides)`` or
    ``AerialLocEnv(scenario, render_mode=None, **overrides)``:

    - ``scenario``: a registered id (one spec file in ``envs/``; ``aerial-loc scenarios`` lists them,
      ``--show ID`` prints one in full) or a ``Scenario``;
    - ``render_mode``: None or ``"rgb_array"``;
    - ``overrides``: any field of the spec's sections (``map``, ``city``, ``epoch``, ``flight``, ``wind``, ``camera``,
      ``perspective``, ``gimbal``, ``altimeter``, ``exposure``, ``haze``, ``odometry``, ``shadows``,
      ``database``, ``photometry``, ``observation``, ``episode``, ``reward``; see
      ``aerial_loc_env.env.scenarios``) as a section dict (``flight={"altitude_m": 150}``), a dotted key
      (``**{"flight.altitude_m": 150}``) or a bare field owned by one section (``altitude_m=150``). Unknown keys
      and out-of-range values raise ``ConfigError`` naming the key and the allowed values.

    ## Version History

    An id's version is bumped whenever what it renders changes for the same seed (a new generator, a changed
    spec); the benchmark's trial keys also carry the generator versions (``env.fingerprint``), so rows of two
    generations never mix.

    * v0: the paper's setting (``PaperShadows``, ``PaperNoShadows``, ...): shadow-free database, the camera is
      the map plus shadows and sensor effects, city generator 4.
    * v0 of ``RealisticPaper``, ``SeasonChange``, ``Downtown`` (new): the realistic map-camera gap, calibrated
      on real two-epoch pairs (``aerial-loc gap``): epoch B of the city (``[epoch]``), the map acquired by
      another sensor under another sun (``[database]``, ``shadows.database_sun_deg``), the perspective camera
      (``[perspective]``), the camera's errors (``[gimbal]``, ``[altimeter]``, ``[exposure]``, ``[haze]``).
    * v1 (every id): the same scenes, frames changed for the same seed: integer photometry (noise drawn once per
      episode into an int16 bank, read at random offsets; vignetting and gains in uint8, within 2 DN of the
      float path), cast shadows baked into the map per episode (masks differ only where the occlusion is near
      0.5), the perspective camera's block-grid ray march and baked shadows (perspective v5). ``gym.make`` of a
      v0 id names the v1 id (Gymnasium's deprecation error).
    * v2 (every id): the observation changed: ``odometry`` is ``[forward_speed_mps, yaw_rate_radps,
      lateral_speed_mps]`` (the body-frame ground velocity; the lateral speed appended, so indices 0 and 1 keep
      their meaning) with the noise ``odometry.lateral_std_mps``, and the ``[wind]`` section (off in every v1
      spec) in which the vehicle crabs. Without wind the frames, tracks, priors and the other measurements are
      those of v1 for the same seed (the lateral noise comes from a stream of its own, as the wind does: a windy
      episode has the start, sun, prior and noise of the calm one of its seed); agents' estimates change
      as their motion models now use (and draw noise for) the lateral term. ``AerialLoc/Crosswind-v2`` (new):
      RealisticPaper in 3-8 m/s of wind with gusts. ``gym.make`` of a v1 id names the v2 id.
    * v2, the procedural city's appearance (city generator 5, epoch generator 3; every id on the city renders
      other frames than v1 for the same seed): tree crowns of several foliage clumps (irregular, lit, leaf
      grain), leaf-off trees as branches over the ground whose trunk and thick limbs alone cast shadows, varied
      construction sites, rooftop vents, AC units and skylights, stains on paving, roofs and lawns, worn
      markings, plaza furniture, a less saturated palette; the realistic presets' shaded walls lit by sky and
      ground (``perspective.ambient`` 0.4) and a colour-enhanced map product (``database.saturation`` 1.2).
    * v3 of ``RealisticPaper``, ``SeasonChange``, ``Downtown``, ``Crosswind`` (the other ids stay v2: their frames
      did not change): the same floats on every CPU. NumPy's ``exp``, ``log``, ``power``, ``arctan2`` ... and
      OpenBLAS's products rounded differently with AVX-512 than without, so a v2 world, its frames and the
      estimates on them depended on the machine. Now ``portable`` computes them (libm per element, products in
      index order): the map product's tone and grey (acquisition generator 2), the epoch's palette (epoch
      generator 4), facade light (perspective 6), the wind's gusts (wind generator 2). On an AVX-512 machine v3
      differs from v2 in the last bits: 550 of the map's 80 million bytes, a few bytes of the epochs, facade
      light and gusts. ``gym.make`` of their v2 ids names the v3 id.
    * v3 of ``Small`` (the only shipped scene whose frames come from a coarser pyramid level): the cast shadows
      baked into that level (``sensors.render.BakedShadows``: the level's pixels shaded, then warped, as level-0
      frames always were) instead of the level and the shadow grid warped, then shaded. Frames differ at shadow
      edges, within the bound tests/sensors/test_render_bake.py derives; the world, the tracks and the draws are
      v2's. ``gym.make`` of ``AerialLoc/Small-v2`` names the v3 id. A user's map with a height model (a city
      bundle on ``RealMap``), or an altitude override, that puts a camera pixel over two or more map pixels
      changes the same way under the same id.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 4}

    def __init__(self, scenario: str | Scenario = "AerialLoc/Small-v3", render_mode: str | None = None,
                 **overrides: Any) -> None:
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise AerialLocError(f"render_mode {render_mode!r} is not supported; use None or 'rgb_array'")
        if isinstance(scenario, Scenario):
            self.scenario = build_scenario(scenario.to_dict(), overrides, where=scenario.source) \
                if overrides else scenario
        else:
            self.scenario = load_scenario(scenario, overrides)
        sc = self.scenario
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": sc.flight.rate_hz}
        self.world = build_world(WorldSpec(sc.map, sc.city, sc.epoch, sc.shadows, sc.database, where=sc.id))
        check_relief(sc, self.world)                 # a perspective camera above the tallest building
        self.orthomap = self.world.ground            # the ground the camera sees (epoch B, or the map's own)
        self.database = self.world.database          # what the estimators get as the map
        sensor: CameraModel = sc.camera
        obs = sc.observation
        w = obs.width_px or sensor.width_px
        h = obs.height_px or sensor.height_px
        self.camera = sensor if (w, h) == (sensor.width_px, sensor.height_px) else sensor.resized(w, h)
        self._window_px: tuple[int, int, int, int] | None = None   # a map read by window: the episode's window
        self._build_renderer()
        self._scene_exposure = SceneExposure(sc.haze, sc.exposure, sc.flight.dt_s)   # pickled with its state
        fw, fh = self.camera.footprint_m(sc.flight.altitude_m + 3.0 * sc.flight.altitude_noise_m)
        clearance = footprint_radius_m(fw, fh) + sc.flight.margin_m
        self.region = self.world.flyable_region(clearance, name=f"{sc.id} map '{self.orthomap.name}'")
        if self.region.area_m2 <= 0.0:
            raise self.region.too_small_error()
        odometry_max = np.float32([ODOMETRY_SPEED_MAX_MPS, ODOMETRY_YAW_RATE_MAX_RADPS, ODOMETRY_SPEED_MAX_MPS])
        self.observation_space = spaces.Dict({
            "image": spaces.Box(0, 255, (h, w, 3), dtype=np.uint8),
            "odometry": spaces.Box(-odometry_max, odometry_max, dtype=np.float32),
            "yaw": spaces.Box(np.float32([-math.pi]), np.float32([math.pi]), dtype=np.float32),
            "altitude": spaces.Box(np.float32([0.0]), np.float32([ALTITUDE_MAX_M]), dtype=np.float32),
        })
        self.action_space = spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)
        self.briefing: Briefing | None = None
        self._overlay: dict[str, np.ndarray] = {}
        self._track: Track | None = None
        self.wind = None      # the episode's WindField (ground truth, like info: not for agents)

    # ------------------------------------------------------------------ construction helpers
    def _build_renderer(self) -> None:
        from aerial_loc_env.sensors.render import CameraRenderer

        sc = self.scenario
        om, window = self.orthomap, {}
        if self.world.windowed:   # the episode's window of a map read by window (none before the first reset)
            if self._window_px is None:
                self._renderer = None
                return
            om = self.orthomap.window(*self._window_px, name=f"{self.orthomap.name}-episode-window")
            window = {"frame": self.orthomap, "origin_px": self._window_px[:2]}
        self._renderer = CameraRenderer(om, self.camera, sc.photometry, strict=True,
                                        perspective=sc.perspective if sc.map.use_dsm else None, **window)

    def _read_window(self) -> None:
        """A map read by window: read the window the episode's frames see (the track's box plus the widest
        footprint, tilted and with the pyramid's kernels) and render from it; the world frame stays the map's."""
        from aerial_loc_env.world.maps.raster import check_memory, window_for_box

        sc, track, om = self.scenario, self._track, self.orthomap
        alt = float(track.altitude_m.max())
        fw, fh = self.camera.footprint_m(alt)
        level = max(0, round(math.log2(max(self.camera.gsd_m(alt) / min(om.gsd_x_m, om.gsd_y_m), 1e-12))))
        pad = 1.25 * footprint_radius_m(fw, fh) + sc.flight.margin_m + (8 << level) * max(om.gsd_x_m, om.gsd_y_m)
        window = window_for_box(om, track.bounds_m(), pad)
        if window == self._window_px and self._renderer is not None:
            return
        w, h = window[2], window[3]
        check_memory(f"{sc.id}: the episode's window of map '{om.name}'", w, h, 12 * w * h,
                     "Shorten the flight (flight.duration_s, flight.speed_mps) or lower flight.altitude_m")
        self._window_px = window
        self._build_renderer()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state.pop("_renderer", None)
        state.pop("_baked", None)      # a copy of the map's box: baked again on arrival
        return state

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._build_renderer()
        if self._track is not None:
            self._renderer.reset(np.random.default_rng(self._noise_seed))
            self._bake_shadows()

    # ------------------------------------------------------------------ episode
    def reset(self, *, seed: int | None = None, options: Mapping[str, Any] | None = None):
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0):
            raise ConfigError(f"{self.scenario.id}: reset(seed={seed!r}): the seed must be a non-negative "
                                 "integer (or None for a fresh random episode)")
        super().reset(seed=None if seed is None else int(seed))
        if options:
            raise AerialLocError(f"{self.scenario.id}: reset options {sorted(options)} are not supported; "
                                 "configure the scenario with gym.make overrides instead")
        sc, rng = self.scenario, self.np_random
        self._track = self._fly_track(rng)
        if self.world.windowed:
            self._read_window()
        on = sc.odometry
        self._meas: Measurements = measure(
            self._track, rng, speed_std_mps=on.speed_std_mps, yaw_rate_std_radps=on.yaw_rate_std_radps,
            heading_std_rad=on.heading_std_rad, altitude_std_m=on.altitude_std_m)
        self._sun = sc.shadows.draw_sun(rng)
        self._strength = sc.shadows.draw_strength(rng)
        self._shading = {"strength": self._strength, **sc.shadows.shading_kwargs()}   # the episode's shading
        self._occlusion = self._episode_occlusion(rng)
        self._noise_seed = int(rng.integers(0, 2**63 - 1))
        self._renderer.reset(np.random.default_rng(self._noise_seed))
        if sc.episode.start == "tracking":
            std = sc.episode.prior_std_m
            mean = (self._track.x_m[0] + rng.normal(0.0, std), self._track.y_m[0] + rng.normal(0.0, std))
            self._prior = Prior("gaussian", (float(mean[0]), float(mean[1])), float(std))
        else:
            self._prior = Prior("uniform")
        self._draw_sensor_errors(rng)
        self._bake_shadows()
        # the lateral speed's noise from a stream of its own: every other draw (the frames' too, which read
        # np_random as they render) stays the one of the odometry without a lateral term
        self._meas = add_lateral_noise(self._meas, self._track, self.lateral_rng(), on.lateral_std_mps)
        self.briefing = Briefing(orthomap=self.database, camera=self.camera, prior=self._prior,
                                 dt_s=sc.flight.dt_s, altitude_m=sc.flight.altitude_m,
                                 odometry_noise=sc.odometry, scenario_id=sc.id)
        self._i = 0
        self._bad_steps = 0
        self._estimates: list[tuple[float, float]] = []
        self._overlay = {}
        obs, info = self._observe(0)
        return obs, info

    def _fly_track(self, rng: np.random.Generator) -> Track:
        """The episode's track, through the episode's wind (``self.wind``, drawn here; calm air draws nothing).

        A windy episode is the calm episode of its seed plus the wind: the wind comes from a generator of its own
        (``wind_rng``), the track flies from a copy of ``rng``'s state (the same start, first waypoint and noise
        banks as the calm track), and ``rng`` then draws what the calm track drew, so the sun, the clouds, the
        prior's offset and the frames' noise that follow are the calm episode's."""
        sc = self.scenario
        t_s = np.arange(sc.flight.steps + 1) * sc.flight.dt_s
        self.wind = sc.wind.draw(self.wind_rng() if sc.wind.enabled else rng, t_s)
        if self.wind.calm:
            return sample_track(sc.flight, self.region, rng)
        track = sample_track(sc.flight, self.region, copy.deepcopy(rng), self.wind)
        try:
            sample_track(sc.flight, self.region, rng)          # the calm track's draws
        except MapError:
            pass                                               # no calm track there: its draws are spent anyway
        return track

    def wind_rng(self) -> np.random.Generator:
        """The episode's generator of the wind: a child of ``np_random``'s seed sequence (spawning draws nothing
        from ``np_random``; ``reset(seed=s)`` gives the same child again, a reset without a seed the next one)."""
        bits = self.np_random.bit_generator
        try:
            return np.random.default_rng(bits.seed_seq.spawn(1)[0])
        except (AttributeError, TypeError, ValueError):    # a generator set by hand without a seed sequence
            return np.random.default_rng(int(self.np_random.integers(0, 2**63 - 1)))

    def lateral_rng(self) -> np.random.Generator:
        """The episode's generator of the lateral odometry noise: seeded from the episode's draws (the renderer's
        noise seed) with a stream index of its own, so it leaves ``np_random`` untouched."""
        return np.random.default_rng([self._noise_seed, LATERAL_NOISE_STREAM])

    def _draw_sensor_errors(self, rng: np.random.Generator) -> None:
        """Gimbal attitude jitter (rendered, unknown to the vehicle), the heading offset and the barometric
        bias/drift (in the measurements). Draws nothing when the sections are off: same episodes as before."""
        sc, track = self.scenario, self._track
        gimbal = sc.gimbal
        self._attitude = (gimbal.draw_attitude(rng, len(track), sc.flight.dt_s)
                          if gimbal.roll_pitch_std_deg > 0.0 else None)
        bias = gimbal.draw_heading_bias(rng)
        alt_err = sc.altimeter.draw_error(rng, track.t_s)
        if bias or alt_err.any():
            m = self._meas
            yaw = np.clip(wrap_angle(m.yaw_rad.astype(np.float64) + bias), -math.pi, math.pi)
            alt = np.maximum(m.altitude_m.astype(np.float64) + alt_err, 0.0)
            self._meas = Measurements(odometry=m.odometry, yaw_rad=yaw.astype(np.float32),
                                      altitude_m=alt.astype(np.float32))
        self._scene_exposure.reset()

    def _episode_occlusion(self, rng: np.random.Generator) -> list | None:
        """The episode's occluders for the renderer: cast shadows (a ``ShadowGrid``) and/or a ``CloudField``.

        Cast shadows are computed only over the track's bounding box plus the footprint (and the casters up to
        one shadow length towards the sun); the rest of the map-wide grid stays zero and is never read, since
        every footprint stays inside the box. The sweep's digital lines start at the box, so shadow edges may
        sit one grid pixel off a whole-map sweep (the sweep's own tolerance); the box, hence the field, is a
        function of the episode seed. Clouds drift with time; the renderer samples them per frame.
        """
        sc, om = self.scenario, self.orthomap
        cfg = sc.shadows
        if cfg.strength_range[1] <= 0.0:
            return None
        sources: list = []
        self._shadow_box_px: tuple[int, int, int, int] | None = None
        if sc.map.use_dsm and om.dsm_m is not None:
            sources.append(self._cast_shadows())
        # clouds only over the window the episode sees (the track's box plus the footprint): the field is
        # periodic, so a field that size (plus the drift, added by draw_clouds) covers it without repeating
        x0, y0, x1, y1 = self._track.bounds_m()
        fw, fh = self.camera.footprint_m(float(self._track.altitude_m.max()))
        pad = 2.0 * footprint_radius_m(fw, fh)
        clouds = cfg.draw_clouds(rng, min(om.width_m, x1 - x0 + pad), min(om.height_m, y1 - y0 + pad),
                                 duration_s=float(self._track.t_s[-1]))
        if clouds is not None:
            sources.append(clouds)
        return sources or None

    def _bake_shadows(self) -> None:
        """Cast shadows alone: shade them into the map over the track's box once per episode
        (``CameraRenderer.bake``), so that each frame is one warp of the pre-shaded map (a perspective or tilted
        view samples it through its maps; a footprint leaving the box falls back to the grid). Draws nothing."""
        self._baked = self._baked_from = None
        occ = self._occlusion
        if occ is None or len(occ) != 1 or self._shadow_box_px is None:
            return
        self._baked = self._renderer.bake(occ[0], self._shading, self._shadow_box_px)
        self._baked_from = occ

    def _cast_shadows(self) -> Any:
        from aerial_loc_env.world.shadows import ShadowGrid, sun_occlusion

        om, cfg, sun = self.orthomap, self.scenario.shadows, self._sun
        f = int(cfg.downsample)
        coarse = self.world.coarse_dsm(f)
        hc, wc = coarse.shape
        gx, gy = om.gsd_x_m * f, om.gsd_y_m * f
        x0, y0, x1, y1 = self._track.bounds_m()
        fw, fh = self.camera.footprint_m(float(self._track.altitude_m.max()))
        pad = footprint_radius_m(fw, fh) + 2.0 * max(gx, gy)
        # the box in grid pixels (grid rows grow south from the map's north edge)
        j0, j1 = max(0, int((x0 - pad) / gx)), min(wc, int(math.ceil((x1 + pad) / gx)))
        i0 = max(0, int((om.height_m - y1 - pad) / gy))
        i1 = min(hc, int(math.ceil((om.height_m - y0 + pad) / gy)))
        # casters up to one shadow length towards the sun may shade the box
        reach_m = sun.shadow_length_m(self.world.dsm_max_m)
        tx, ty = sun.towards_sun_en
        dj, di = tx * reach_m / gx, -ty * reach_m / gy
        cj0, cj1 = max(0, int(j0 + min(0.0, dj))), min(wc, int(math.ceil(j1 + max(0.0, dj))))
        ci0, ci1 = max(0, int(i0 + min(0.0, di))), min(hc, int(math.ceil(i1 + max(0.0, di))))
        grid = sun_occlusion(coarse[ci0:ci1, cj0:cj1], gx, gy, sun, downsample=1,
                             penumbra_scale=cfg.penumbra_scale, antialias_px=cfg.antialias_px,
                             azimuth_samples=cfg.penumbra_azimuth_samples)
        field = np.zeros((hc, wc), dtype=np.float32)
        field[i0:i1, j0:j1] = grid.data[i0 - ci0:i1 - ci0, j0 - cj0:j1 - cj0]
        self._shadow_box_px = (j0 * f, i0 * f, j1 * f, i1 * f)
        return ShadowGrid(field, gx, gy, f)

    def _ground_speed_mps(self, i: int) -> float:
        """The ground speed over the step ending at pose ``i`` (the motion blur's length; the airspeed without
        wind)."""
        return math.hypot(float(self._track.forward_mps[i]), float(self._track.lateral_mps[i]))

    def _pose(self, i: int) -> Pose:
        t = self._track
        return Pose(float(t.x_m[i]), float(t.y_m[i]), float(t.yaw_rad[i]), float(t.altitude_m[i]))

    def _observe(self, i: int) -> tuple[dict, dict]:
        pose = self._pose(i)
        sc = self.scenario
        tilt = (0.0, 0.0) if self._attitude is None else (float(self._attitude[i, 0]), float(self._attitude[i, 1]))
        exposure = self._scene_exposure
        # the baked shadows while the occluders are the ones baked (env.external swaps in the whole map's)
        occlusion = self._baked if self._baked is not None and self._occlusion is self._baked_from else self._occlusion
        frame = self._renderer.render(pose, self.np_random, occlusion, self._shading,
                                      t_s=float(self._track.t_s[i]), speed_mps=self._ground_speed_mps(i),
                                      tilt_rad=tilt, pre_sensor=(lambda image: exposure(image, pose.altitude_m))
                                      if exposure.active else None,
                                      sun_deg=None if self._occlusion is None else
                                      (self._sun.azimuth_deg, self._sun.elevation_deg))
        self._frame = frame
        m = self._meas
        obs = {
            "image": frame.image,
            "odometry": np.clip(m.odometry[i], self.observation_space["odometry"].low,
                                self.observation_space["odometry"].high),
            "yaw": m.yaw_rad[i:i + 1].copy(),
            "altitude": np.minimum(m.altitude_m[i:i + 1], np.float32(ALTITUDE_MAX_M)),
        }
        info: dict[str, Any] = {
            "true_pose": np.array(pose, dtype=np.float64),
            "time_s": float(self._track.t_s[i]),
            "step": i,
            "prior": self._prior,
            "shadow_fraction": float(frame.shadow_fraction),
            "sun_azimuth_deg": float(self._sun.azimuth_deg),
            "sun_elevation_deg": float(self._sun.elevation_deg),
            "shadow_strength": float(self._strength) if self._occlusion is not None else 0.0,
        }
        if sc.observation.info_shadow_mask:
            info["shadow_mask"] = frame.shadow_mask
        if self._attitude is not None:
            info["gimbal_roll_pitch_rad"] = np.array(tilt)
        if exposure.gain is not None:
            info["exposure_gain"] = exposure.gain
        if self.wind is not None and not self.wind.calm:
            info["wind_en_mps"] = np.array(self.wind.at(min(i, len(self.wind.t_s) - 1)))
        return obs, info

    def _check_action(self, action: Any) -> np.ndarray:
        if self._track is None:
            raise AerialLocError(f"{self.scenario.id}: call reset() before step()")
        a = np.asarray(action)
        if a.shape == (2,) and a.dtype.char in "fd":    # the usual action, checked in plain Python (a step's
            x, y = a.tolist()                           # NumPy calls on 2 values cost more than its frame's
            if abs(x) <= 1.0 and abs(y) <= 1.0:         # Python): within [-1, 1] (not NaN), nothing to clip
                return np.array((x, y))
        if not np.issubdtype(a.dtype, np.floating):
            raise InvalidActionError(f"{self.scenario.id}: action must be a float array (float32), got dtype "
                                     f"{a.dtype}; convert positions with aerial_loc_env.env.world_to_action")
        if a.shape != (2,):
            raise InvalidActionError(f"{self.scenario.id}: action must have shape (2,) (the normalized x, y "
                                     f"estimate), got shape {a.shape}")
        if not np.all(np.isfinite(a)):
            raise InvalidActionError(f"{self.scenario.id}: action {a.tolist()} has NaN/inf; an estimate must "
                                     "be finite")
        if np.any(np.abs(a) > 1.0 + 1e-5):
            raise InvalidActionError(f"{self.scenario.id}: action {a.tolist()} is outside [-1, 1] (the map "
                                     "extent); clip it or convert metres with world_to_action")
        return np.clip(a.astype(np.float64), -1.0, 1.0)

    def step(self, action: Any):
        a = self._check_action(action)
        if self._i >= len(self._track) - 1:
            raise AerialLocError(f"{self.scenario.id}: the episode is over; call reset()")
        sc = self.scenario
        x, y = action_to_world(self.orthomap, a)
        tx, ty = float(self._track.x_m[self._i]), float(self._track.y_m[self._i])
        err = math.hypot(x - tx, y - ty)
        self._estimates.append((x, y))
        reward = -err / sc.reward.scale_m
        fail = sc.episode.failure_error_m
        self._bad_steps = self._bad_steps + 1 if (fail > 0.0 and err > fail) else 0
        terminated = fail > 0.0 and self._bad_steps >= sc.episode.failure_steps
        self._i += 1
        truncated = self._i >= len(self._track) - 1
        obs, info = self._observe(self._i)
        info["position_error_m"] = err
        info["estimate_xy_m"] = np.array([x, y])
        if terminated:
            info["failure"] = (f"position error above {fail:g} m for {sc.episode.failure_steps} "
                               "consecutive steps")
        return obs, float(reward), bool(terminated), bool(truncated and not terminated), info

    # ------------------------------------------------------------------ rendering
    def set_overlay(self, points_xy_m: Any = None, weights: Any = None) -> None:
        """Points (N, 2+) in world metres (e.g. particles) drawn by ``render``; ``weights`` (N,) scale
        their brightness. Call with no argument to clear. Purely visual."""
        self._overlay = {}
        if points_xy_m is not None:
            pts = np.asarray(points_xy_m, dtype=np.float64)
            if pts.ndim != 2 or pts.shape[1] < 2:
                raise AerialLocError(f"set_overlay: points_xy_m must be (N, 2) metres, got shape {pts.shape}")
            self._overlay["points"] = pts[:, :2]
            if weights is not None:
                w = np.asarray(weights, dtype=np.float64).ravel()
                if w.shape[0] != pts.shape[0]:
                    raise AerialLocError(f"set_overlay: {w.shape[0]} weights for {pts.shape[0]} points")
                self._overlay["weights"] = w

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; use gym.make(id, render_mode='rgb_array')")
            return None
        if self._track is None:
            return np.zeros((OVERVIEW_PX, OVERVIEW_PX, 3), dtype=np.uint8)
        return self._overview()

    def _overview(self) -> np.ndarray:
        om, n = self.orthomap, OVERVIEW_PX
        pose = self._pose(self._i)
        fw, fh = self.camera.footprint_m(pose.altitude_m)
        side = min(max(4.0 * footprint_radius_m(fw, fh), 100.0), max(om.width_m, om.height_m))
        cx = min(max(pose.x_m, side / 2), max(om.width_m - side / 2, side / 2))
        cy = min(max(pose.y_m, side / 2), max(om.height_m - side / 2, side / 2))
        s = side / n                                   # metres per overview pixel
        view_to_world = np.array([[s, 0.0, cx - side / 2 + 0.5 * s], [0.0, -s, cy + side / 2 - 0.5 * s]])
        to_map = world_to_map_affine(om)
        view_to_map = to_map[:, :2] @ view_to_world
        view_to_map[:, 2] += to_map[:, 2]
        img = self._renderer.warp_map(view_to_map, (n, n))
        world_to_view = np.array([[1 / s, 0.0, -(cx - side / 2) / s - 0.5],
                                  [0.0, -1 / s, (cy + side / 2) / s - 0.5]])
        # the camera frame (with its shadows) pasted into its footprint
        cam_to_world = self.camera.camera_to_world(*pose)
        cam_to_view = world_to_view[:, :2] @ cam_to_world
        cam_to_view[:, 2] += world_to_view[:, 2]
        frame = cv2.warpAffine(self._frame.image, cam_to_view, (n, n), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT)
        inside = cv2.warpAffine(np.full(self._frame.image.shape[:2], 255, np.uint8), cam_to_view, (n, n),
                                flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT) > 0
        img[inside] = frame[inside]

        def px(xy: np.ndarray) -> np.ndarray:
            return np.round(apply_affine(world_to_view, np.atleast_2d(xy)) * 16).astype(np.int32)

        corners = self.camera.footprint_corners_m(*pose)
        cv2.polylines(img, [px(corners)], True, (255, 220, 0), 2, cv2.LINE_AA, shift=4)
        if "points" in self._overlay:
            pts = px(self._overlay["points"])
            w = self._overlay.get("weights")
            bright = np.ones(len(pts)) if w is None else 0.3 + 0.7 * w / max(float(w.max()), 1e-12)
            for (u, v), b in zip(pts, bright, strict=True):
                cv2.circle(img, (int(u), int(v)), 2 * 16, (int(255 * b), 0, int(255 * b)), -1, cv2.LINE_AA, shift=4)
        if self._prior.kind == "gaussian":
            c = px(np.array(self._prior.mean_xy_m))[0]
            cv2.circle(img, (int(c[0]), int(c[1])), int(16 * self._prior.std_xy_m / s), (0, 255, 255), 1,
                       cv2.LINE_AA, shift=4)
        track_xy = np.stack([self._track.x_m[:self._i + 1], self._track.y_m[:self._i + 1]], axis=1)
        cv2.polylines(img, [px(track_xy)], False, (0, 255, 0), 2, cv2.LINE_AA, shift=4)
        if self._estimates:
            est = px(np.array(self._estimates))
            cv2.polylines(img, [est], False, (255, 0, 0), 1, cv2.LINE_AA, shift=4)
            cv2.circle(img, (int(est[-1][0]), int(est[-1][1])), 4 * 16, (255, 0, 0), -1, cv2.LINE_AA, shift=4)
        cv2.putText(img, f"t={self._track.t_s[self._i]:5.2f}s  {side:.0f} m", (6, n - 8),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        return img
