"""Supervised examples from the simulator: a camera frame, map crops at its true pose and at offsets, the pose and
the map-camera gap it was made with, each a pure function of one integer seed.

The procedural worlds are an unlimited source of co-registered (camera frame, map database) pairs. An example is
drawn in two stages, both from the seed:

1. **the world**: one of the split's worlds (``learning.splits``: a city style and a city seed, never a world of
   another split), with everything that is built once per world drawn from the world alone (the same world
   always has the same gap): the city's parameters (``PRESET_CITIES``), the ground's epoch B (``[epoch]``), the
   map database's sensor (``[database]`` acquisition) and its sun (``shadows.database_sun_deg``);
2. **the frame**: the flight and camera parameters drawn per example (``[shadows]`` sun and clouds, altitude,
   ``[gimbal]``, ``[altimeter]``, ``[exposure]``, ``[haze]``, ``[photometry]``, ``[perspective]``), then one
   reset of the env (``AerialLocEnv``: the renderer, shadows and camera errors of the benchmark itself), whose
   frame 0 is the example's frame; the map crops are the database rendered through the same camera model
   (``CameraRenderer.database_patch``) at the true pose and at ``n_offsets`` positions drawn within
   ``max_offset_m`` of it.

Every range (``Randomization``) spans the scenarios' own values, from the paper's (no epoch, the database the
shadow-free scene, no camera errors) to RealisticPaper's, SeasonChange's and Downtown's. Worlds are built on
first use and cached like any scenario's (``world.scene``; the cities on disk), so the first example of a world
costs its build and later ones a reset. ``ExampleSampler`` needs only NumPy; ``learning.torch_dataset`` wraps it
as a PyTorch dataset (index -> seed).
"""

from __future__ import annotations

import copy
import json
import math
from collections import OrderedDict
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from aerial_loc_env.config import build_config, config_to_dict, rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.learning.splits import PRESETS, WorldRef, check_split, split_of, worlds

#: the scenario whose camera, flight and odometry each preset's examples use
PRESET_BASES = {"paper": "AerialLoc/RealisticPaper-v3", "downtown": "AerialLoc/Downtown-v3"}
#: each preset's city parameters: a fixed value or a (lo, hi) range drawn per world; ``downtown_radius``: a share
#: of the city's smaller side
PRESET_CITIES: dict[str, dict[str, Any]] = {
    "paper": {"building_density": (0.8, 1.1), "tree_density": (0.6, 1.6), "car_density": (0.6, 1.6),
              "park_fraction": (0.04, 0.14), "street_removal": (0.06, 0.2), "max_building_height_m": (40.0, 80.0),
              "downtown_radius": (0.25, 0.45)},
    "downtown": {"building_density": (1.0, 1.2), "tree_density": (0.4, 1.2), "car_density": (0.8, 1.8),
                 "park_fraction": (0.02, 0.08), "street_removal": (0.04, 0.12),
                 "max_building_height_m": (100.0, 150.0), "downtown_radius": (0.4, 0.6)},
}
#: the perspective camera sees heights up to a share of its altitude: the altitude is raised to this factor of
#: the world's tallest building when needed (``env.scenarios.check_relief``)
RELIEF_ALTITUDE_FACTOR = 1.1
EPOCH_FIELDS = ("car_turnover", "car_arrivals", "leaf_off", "grass_dryness", "roof_change", "demolished", "built",
                "construction_per_km2", "marking_renewal", "water_change")
#: the numbers of ``Example.gap``, in order (NaN where one does not apply, e.g. no database sun)
GAP_FIELDS = (
    "altitude_m", "measured_altitude_m", "heading_error_rad", "gimbal_roll_rad", "gimbal_pitch_rad",
    "sun_azimuth_deg", "sun_elevation_deg", "shadow_strength", "shadow_fraction", "cloud_cover", "exposure_gain",
    "exposure_strength", "haze_extinction_per_km", "perspective", "photometry_gamma", "vignetting",
    *(f"epoch_{name}" for name in EPOCH_FIELDS),
    "database_acquired", "database_gsd_m", "database_blur_m", "database_jpeg_quality", "database_gain_r",
    "database_gain_g", "database_gain_b", "database_tone_gamma", "database_saturation", "database_contrast",
    "database_haze", "database_georef_bias_east_m", "database_georef_bias_north_m", "database_lean_deg",
    "database_lean_azimuth_deg", "database_sun_azimuth_deg", "database_sun_elevation_deg",
)


def _span(lo: float, hi: float, doc: str = "") -> Any:
    return field(default=(lo, hi), metadata=rng(0.0, 1e6, doc=doc))


@dataclass(frozen=True)
class Randomization:
    """The ranges examples are drawn from (uniform within each; build with ``build_config`` to change some).

    World-level (per world): ``p_epoch`` the share of worlds whose ground is a later epoch (else the map's own,
    as in the paper), ``epoch_*`` each epoch field's range; ``p_acquired`` the share whose database is acquired
    by another sensor (else the scene itself), ``database_*`` that sensor's; ``p_database_sun`` the share whose
    database carries its own sun's shadows. Frame-level (per example): the rest."""

    p_epoch: float = field(default=0.8, metadata=rng(0.0, 1.0))
    epoch_car_turnover: tuple[float, float] = _span(0.0, 0.9)
    epoch_car_arrivals: tuple[float, float] = _span(0.0, 1.0)
    epoch_leaf_off: tuple[float, float] = _span(0.0, 0.95)
    epoch_grass_dryness: tuple[float, float] = _span(0.0, 1.0)
    epoch_roof_change: tuple[float, float] = _span(0.0, 0.3)
    epoch_demolished: tuple[float, float] = _span(0.0, 0.08)
    epoch_built: tuple[float, float] = _span(0.0, 0.12)
    epoch_construction_per_km2: tuple[float, float] = _span(0.0, 8.0)
    epoch_marking_renewal: tuple[float, float] = _span(0.0, 0.6)
    epoch_water_change: tuple[float, float] = _span(0.0, 0.6)
    p_acquired: float = field(default=0.8, metadata=rng(0.0, 1.0))
    database_gsd_m: tuple[float, float] = _span(0.3, 0.6, "the acquiring sensor's ground sampling")
    database_blur_m: tuple[float, float] = _span(0.1, 0.6)
    database_jpeg_quality: tuple[float, float] = _span(50.0, 95.0)
    database_gain: tuple[float, float] = _span(0.9, 1.1, "per channel")
    database_tone_gamma: tuple[float, float] = _span(0.8, 1.1)
    database_saturation: tuple[float, float] = _span(0.7, 1.1)
    database_contrast: tuple[float, float] = _span(0.75, 1.1)
    database_haze: tuple[float, float] = _span(0.0, 0.12)
    database_georef_bias_m: tuple[float, float] = _span(0.0, 2.0, "magnitude; the direction is uniform")
    database_lean_deg: tuple[float, float] = _span(0.0, 12.0)
    p_database_sun: float = field(default=0.75, metadata=rng(0.0, 1.0))
    database_sun_azimuth_deg: tuple[float, float] = _span(100.0, 220.0)
    database_sun_elevation_deg: tuple[float, float] = _span(35.0, 70.0)
    altitude_m: tuple[float, float] = _span(100.0, 250.0)
    sun_azimuth_deg: tuple[float, float] = _span(90.0, 270.0)
    sun_elevation_deg: tuple[float, float] = _span(15.0, 65.0)
    p_clouds: float = field(default=0.15, metadata=rng(0.0, 1.0))
    cloud_cover: tuple[float, float] = _span(0.1, 0.5)
    gimbal_roll_pitch_std_deg: tuple[float, float] = _span(0.0, 0.5)
    gimbal_heading_bias_std_deg: tuple[float, float] = _span(0.0, 2.0)
    altimeter_bias_std_m: tuple[float, float] = _span(0.0, 3.0)
    altimeter_drift_std_m_per_sqrt_s: tuple[float, float] = _span(0.0, 0.15)
    exposure_strength: tuple[float, float] = _span(0.0, 1.0)
    exposure_time_constant_s: tuple[float, float] = _span(0.2, 1.0)
    haze_extinction_per_km: tuple[float, float] = _span(0.0, 0.5)
    photometry_exposure_std: tuple[float, float] = _span(0.05, 0.15)
    photometry_white_balance_std: tuple[float, float] = _span(0.01, 0.05)
    photometry_gamma: tuple[float, float] = _span(1.0, 1.2)
    photometry_gamma_std: tuple[float, float] = _span(0.03, 0.1)
    photometry_vignetting: tuple[float, float] = _span(0.3, 0.9)
    p_perspective: float = field(default=0.75, metadata=rng(0.0, 1.0))

    def validate(self, where: str) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, tuple) and (len(value) != 2 or value[0] > value[1]):
                raise ConfigError(f"{where}: field '{f.name}' = {list(value)} must be a range [lo, hi] with lo <= hi")

    def draw_world(self, world: WorldRef, size_m: float) -> dict[str, Any]:
        """The world-level sections (``city``, ``epoch``, ``database``, ``shadows.database_sun_deg``) of ``world``,
        drawn from the world alone."""
        g = np.random.default_rng([world.city_seed, PRESETS.index(world.preset), 23])
        city: dict[str, Any] = {"seed": world.city_seed, "width_m": size_m, "height_m": size_m, "gsd_m": 0.25,
                                "name": f"{world.preset}-{world.city_seed}", "river": bool(g.random() < 0.7)}
        for name, value in PRESET_CITIES[world.preset].items():
            drawn = float(g.uniform(*value)) if isinstance(value, tuple) else value
            if name == "downtown_radius":
                city["downtown_radius_m"] = max(50.0, drawn * size_m)
            else:
                city[name] = drawn
        epoch: dict[str, Any] = {}
        if g.random() < self.p_epoch:
            epoch = {"seed": int(g.integers(0, 2**31))}
            epoch.update({name: float(g.uniform(*getattr(self, f"epoch_{name}"))) for name in EPOCH_FIELDS})
        database: dict[str, Any] = {}
        if g.random() < self.p_acquired:
            bias, direction = g.uniform(*self.database_georef_bias_m), g.uniform(0.0, 2.0 * math.pi)
            database = {
                "gsd_m": float(g.uniform(*self.database_gsd_m)), "blur_m": float(g.uniform(*self.database_blur_m)),
                "jpeg_quality": int(round(g.uniform(*self.database_jpeg_quality))),
                "gain_rgb": [float(v) for v in g.uniform(*self.database_gain, 3)],
                "tone_gamma": float(g.uniform(*self.database_tone_gamma)),
                "saturation": float(g.uniform(*self.database_saturation)),
                "contrast": float(g.uniform(*self.database_contrast)),
                "haze": float(g.uniform(*self.database_haze)),
                "georef_bias_m": [float(bias * math.cos(direction)), float(bias * math.sin(direction))],
                "lean_deg": float(g.uniform(*self.database_lean_deg)),
                "lean_azimuth_deg": float(g.uniform(0.0, 360.0)) % 360.0,
            }
        sun = None
        if g.random() < self.p_database_sun:
            sun = [float(g.uniform(*self.database_sun_azimuth_deg)) % 360.0,
                   float(g.uniform(*self.database_sun_elevation_deg))]
        return {"city": city, "epoch": epoch, "database": database, "database_sun_deg": sun}

    def draw_frame(self, g: np.random.Generator) -> dict[str, Any]:
        """The frame-level sections of one example (the env then draws the sun, the jitter and the noise)."""
        clouds = float(g.uniform(*self.cloud_cover)) if g.random() < self.p_clouds else 0.0
        return {
            "altitude_m": float(g.uniform(*self.altitude_m)),
            "shadows": {"sun_azimuth_range_deg": [float(v) for v in self.sun_azimuth_deg],
                        "sun_elevation_range_deg": [float(v) for v in self.sun_elevation_deg],
                        "cloud_cover": clouds},
            "gimbal": {"roll_pitch_std_deg": float(g.uniform(*self.gimbal_roll_pitch_std_deg)),
                       "heading_bias_std_deg": float(g.uniform(*self.gimbal_heading_bias_std_deg))},
            "altimeter": {"bias_std_m": float(g.uniform(*self.altimeter_bias_std_m)),
                          "drift_std_m_per_sqrt_s": float(g.uniform(*self.altimeter_drift_std_m_per_sqrt_s))},
            "exposure": {"strength": float(g.uniform(*self.exposure_strength)),
                         "time_constant_s": float(g.uniform(*self.exposure_time_constant_s))},
            "haze": {"extinction_per_km": float(g.uniform(*self.haze_extinction_per_km))},
            "photometry": {"exposure_std": float(g.uniform(*self.photometry_exposure_std)),
                           "white_balance_std": float(g.uniform(*self.photometry_white_balance_std)),
                           "gamma": float(g.uniform(*self.photometry_gamma)),
                           "gamma_std": float(g.uniform(*self.photometry_gamma_std)),
                           "vignetting": float(g.uniform(*self.photometry_vignetting))},
            "perspective": {"enabled": bool(g.random() < self.p_perspective)},
        }


@dataclass(frozen=True, eq=False)
class Example:
    """One supervised example (arrays are C-contiguous; ``map_crops[0]`` is at the true pose).

    - ``frame``: (H, W, 3) uint8, the camera frame as the env returns it (top along the heading);
    - ``map_crops``: (1 + n_offsets, H, W, 3) uint8, the database through the same camera model at the true
      position (true heading and altitude), then at ``offsets_m``;
    - ``offsets_m``: (1 + n_offsets, 2) float32, (east, north) metres of each crop from the true position;
    - ``pose``: (4,) float64, the true (x_m, y_m, yaw_rad, altitude_m); ``measured``: (2,) float32, the measured
      (yaw_rad, altitude_m) the vehicle knows;
    - ``gap``: (len(GAP_FIELDS),) float32, the gap's numbers; ``meta``: the split, the world and every drawn
      section (JSON-able)."""

    seed: int
    frame: np.ndarray
    map_crops: np.ndarray
    offsets_m: np.ndarray
    pose: np.ndarray
    measured: np.ndarray
    gap: np.ndarray
    meta: dict

    def arrays(self) -> dict[str, np.ndarray]:
        """The example's arrays by name (what a byte-for-byte comparison covers)."""
        return {"frame": self.frame, "map_crops": self.map_crops, "offsets_m": self.offsets_m, "pose": self.pose,
                "measured": self.measured, "gap": self.gap}


def example_seed(base_seed: int, split: str, index: int) -> int:
    """The seed of a dataset's ``index``-th example (a dataset of ``base_seed`` over ``split``)."""
    ss = np.random.SeedSequence([int(base_seed), ("train", "val", "test").index(check_split(split)), int(index)])
    return int(ss.generate_state(2, np.uint32).astype(np.uint64) @ np.array([1 << 32, 1], np.uint64) >> np.uint64(1))


class ExampleSampler:
    """Draws ``Example``s of one split (see the module doc); ``sample(seed)`` is a pure function of the seed.

    - ``split``: ``"train"``, ``"val"`` or ``"test"``; ``n_worlds``: how many of its worlds (``splits.worlds``);
      ``presets``: restrict to these city styles (default: every one the split has);
    - ``city_size_m``: the side of each world's city (a smaller city builds faster; at least 300 m);
    - ``frame_px``: (width, height) of frames and crops (None: the preset camera's 600 x 400);
    - ``n_offsets``, ``max_offset_m``: the crops besides the true pose's, uniform in that disc;
    - ``randomization``: the ranges (``Randomization``), or a dict of fields to change.
    """

    #: database renderers kept per sampler (each holds its map's pyramid levels once used)
    CACHE_SIZE = 2

    def __init__(self, split: str = "train", *, n_worlds: int = 16, presets: tuple[str, ...] | None = None,
                 city_size_m: float = 600.0, frame_px: tuple[int, int] | None = None, n_offsets: int = 4,
                 max_offset_m: float = 30.0, randomization: Randomization | dict | None = None) -> None:
        self.split = check_split(split)
        self.worlds = worlds(split, n_worlds, presets)
        if not 300.0 <= float(city_size_m) <= 8000.0:
            raise ConfigError(f"ExampleSampler: city_size_m = {city_size_m!r} must be in [300, 8000] metres (the "
                              "footprint and the crops' offsets must fit in the city)")
        self.city_size_m = float(city_size_m)
        if frame_px is not None and (len(frame_px) != 2 or not all(isinstance(v, int) and 8 <= v <= 4000
                                                                   for v in frame_px)):
            raise ConfigError(f"ExampleSampler: frame_px = {frame_px!r} must be (width, height) integers in "
                              "[8, 4000], or None for the preset camera's size")
        self.frame_px = None if frame_px is None else (int(frame_px[0]), int(frame_px[1]))
        if isinstance(n_offsets, bool) or not isinstance(n_offsets, int) or not 0 <= n_offsets <= 256:
            raise ConfigError(f"ExampleSampler: n_offsets = {n_offsets!r} must be an integer in [0, 256]")
        if not 0.0 <= float(max_offset_m) <= 200.0:
            raise ConfigError(f"ExampleSampler: max_offset_m = {max_offset_m!r} must be in [0, 200] metres")
        self.n_offsets, self.max_offset_m = n_offsets, float(max_offset_m)
        if isinstance(randomization, Randomization):
            self.randomization = randomization
        else:
            self.randomization = build_config(Randomization, randomization or {}, where="ExampleSampler randomization")
        self._bases: dict[str, dict] = {}
        self._renderers: OrderedDict[tuple, Any] = OrderedDict()

    # ------------------------------------------------------------------ scenario of one example
    def _base(self, preset: str) -> dict:
        if preset not in self._bases:
            import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
            from aerial_loc_env.env.scenarios import resolve

            self._bases[preset] = resolve(PRESET_BASES[preset])[1]
        return copy.deepcopy(self._bases[preset])

    def scenario(self, world: WorldRef, frame_draw: dict[str, Any]) -> Any:
        """The ``Scenario`` of one example: the preset's base with the world's and the frame's draws."""
        from aerial_loc_env.env.scenarios import build_scenario
        from aerial_loc_env.world.scene import WorldSpec, build_world

        drawn = self.randomization.draw_world(world, self.city_size_m)
        raw = self._base(world.preset)
        raw["id"] = "AerialLoc/TrainingExamples-v1"
        raw["city"] = drawn["city"]
        raw["epoch"] = drawn["epoch"]
        raw["database"] = drawn["database"]
        for name in ("gimbal", "altimeter", "exposure", "haze", "photometry", "perspective"):
            raw[name] = {**raw.get(name, {}), **frame_draw[name]}
        raw["shadows"] = {**raw.get("shadows", {}), **frame_draw["shadows"]}
        raw["shadows"].pop("database_sun_deg", None)
        if drawn["database_sun_deg"] is not None:
            raw["shadows"]["database_sun_deg"] = drawn["database_sun_deg"]
        # one frame per example: the shortest track; the margin keeps every offset crop on the map
        raw["flight"] = {**raw.get("flight", {}), "altitude_m": frame_draw["altitude_m"], "duration_s": 0.25,
                         "min_steps": 1, "margin_m": self.max_offset_m + 5.0}
        if self.frame_px is not None:
            raw["observation"] = {**raw.get("observation", {}), "width_px": self.frame_px[0],
                                  "height_px": self.frame_px[1]}
        sc = build_scenario(raw, where=f"training example over world {world.name}")
        if sc.perspective.enabled:
            tallest = build_world(WorldSpec(sc.map, sc.city, sc.epoch, sc.shadows, sc.database, where=sc.id)).dsm_max_m
            if RELIEF_ALTITUDE_FACTOR * tallest > sc.flight.altitude_m:
                raw["flight"]["altitude_m"] = float(math.ceil(RELIEF_ALTITUDE_FACTOR * tallest))
                sc = build_scenario(raw, where=f"training example over world {world.name}")
        return sc

    def _renderer(self, env: Any) -> Any:
        """The database's renderer for the env's camera (kept for the next examples of the same world)."""
        from aerial_loc_env.sensors.render import CameraRenderer, Photometry

        key = (env.world.key, env.camera)
        if key in self._renderers:
            self._renderers.move_to_end(key)
        else:   # no sensor model: a database patch is the map's pixels warped, and the ideal camera draws no noise
            self._renderers[key] = CameraRenderer(env.database, env.camera, Photometry.ideal(), strict=False,
                                                  rgba=False)
            while len(self._renderers) > self.CACHE_SIZE:
                self._renderers.popitem(last=False)
        return self._renderers[key]

    # ------------------------------------------------------------------ one example
    def sample(self, seed: int) -> Example:
        """The example of ``seed`` (a non-negative integer): the same seed gives the same bytes."""
        from aerial_loc_env.env.aerial_loc_env import AerialLocEnv
        from aerial_loc_env.sensors.camera import Pose

        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"ExampleSampler.sample: the seed must be a non-negative integer, got {seed!r}")
        g = np.random.default_rng([int(seed), 29])
        world = self.worlds[int(g.integers(len(self.worlds)))]
        frame_draw = self.randomization.draw_frame(g)
        episode_seed = int(g.integers(0, 2**63 - 1))
        radius = self.max_offset_m * np.sqrt(g.random(self.n_offsets))
        angle = g.uniform(0.0, 2.0 * math.pi, self.n_offsets)
        offsets = np.zeros((self.n_offsets + 1, 2), np.float32)
        offsets[1:, 0], offsets[1:, 1] = radius * np.cos(angle), radius * np.sin(angle)

        sc = self.scenario(world, frame_draw)
        env = AerialLocEnv(sc)
        obs, info = env.reset(seed=episode_seed)
        pose = np.asarray(info["true_pose"], dtype=np.float64)
        renderer = self._renderer(env)
        crops = np.stack([renderer.database_patch(Pose(pose[0] + float(dx), pose[1] + float(dy), pose[2], pose[3]))
                          for dx, dy in offsets.astype(np.float64)])
        measured = np.array([obs["yaw"][0], obs["altitude"][0]], np.float32)
        gap = self._gap(sc, info, pose, measured, env)
        meta = {"split": self.split, "preset": world.preset, "city_seed": world.city_seed, "world": world.name,
                "world_split": split_of(world.preset, world.city_seed), "episode_seed": episode_seed,
                "scenario": sc.to_dict()}
        env.close()
        return Example(int(seed), np.ascontiguousarray(obs["image"]), np.ascontiguousarray(crops), offsets, pose,
                       measured, gap, meta)

    @staticmethod
    def _gap(sc: Any, info: dict, pose: np.ndarray, measured: np.ndarray, env: Any) -> np.ndarray:
        db, sun = sc.database, sc.shadows.database_sun_deg
        acquired = not (db == type(db)())
        heading_error = math.remainder(float(measured[0]) - float(pose[2]), 2.0 * math.pi)
        roll, pitch = info.get("gimbal_roll_pitch_rad", (0.0, 0.0))
        values = {
            "altitude_m": pose[3], "measured_altitude_m": measured[1], "heading_error_rad": heading_error,
            "gimbal_roll_rad": roll, "gimbal_pitch_rad": pitch, "sun_azimuth_deg": info["sun_azimuth_deg"],
            "sun_elevation_deg": info["sun_elevation_deg"], "shadow_strength": info["shadow_strength"],
            "shadow_fraction": info["shadow_fraction"], "cloud_cover": sc.shadows.cloud_cover,
            "exposure_gain": info.get("exposure_gain", 1.0), "exposure_strength": sc.exposure.strength,
            "haze_extinction_per_km": sc.haze.extinction_per_km, "perspective": float(sc.perspective.enabled),
            "photometry_gamma": sc.photometry.gamma, "vignetting": sc.photometry.vignetting,
            **{f"epoch_{name}": getattr(sc.epoch, name) for name in EPOCH_FIELDS},
            "database_acquired": float(acquired),
            "database_gsd_m": db.gsd_m if db.gsd_m is not None else env.world.surveyed.gsd_x_m,
            "database_blur_m": db.blur_m, "database_jpeg_quality": db.jpeg_quality,
            "database_gain_r": db.gain_rgb[0], "database_gain_g": db.gain_rgb[1], "database_gain_b": db.gain_rgb[2],
            "database_tone_gamma": db.tone_gamma, "database_saturation": db.saturation,
            "database_contrast": db.contrast, "database_haze": db.haze,
            "database_georef_bias_east_m": db.georef_bias_m[0], "database_georef_bias_north_m": db.georef_bias_m[1],
            "database_lean_deg": db.lean_deg, "database_lean_azimuth_deg": db.lean_azimuth_deg,
            "database_sun_azimuth_deg": math.nan if sun is None else sun[0],
            "database_sun_elevation_deg": math.nan if sun is None else sun[1],
        }
        return np.array([float(values[name]) for name in GAP_FIELDS], np.float32)


def meta_json(example: Example) -> str:
    """The example's metadata as one JSON line (what the PyTorch dataset hands for it)."""
    return json.dumps(example.meta, sort_keys=True, default=list)


def randomization_dict(randomization: Randomization) -> dict:
    """The ranges as a plain dict (``build_config(Randomization, d)`` gives them back)."""
    return config_to_dict(randomization)
