"""Edge/line feature model after the second reference (Leung, Clark & Huissoon, II and IV).

Feature map (II), built once per episode from the DATABASE image:

1. Canny edges of the (lightly smoothed) gray image.
2. Shadow-edge removal using the illumination direction: an edge whose darker side is a shadow candidate (much
   darker than the image's median) and whose intensity gradient increases in the direction of the light
   (away from the sun, Sobel) is the far edge of a cast shadow on the ground and is removed; the edge a shadow
   shares with its building (intensity decreasing away from the sun) is kept. The direction comes from the
   agent's spec (``illumination = "parameter"``, ``sun_azimuth_deg``: compass bearing TOWARDS the sun) or is
   estimated from the database image itself (``"estimate"``: at edges bordering shadow candidates, the
   magnitude-weighted mean of the dark-to-bright gradient directions points to the sun, because the
   building side of a shadow is usually the brighter one); never from the simulator's sun. When the estimate
   is not consistent (resultant length below ``min_illumination_consistency``) no edge is removed.
3. Clutter mask from the Harris response: pixels whose response, relative to its 99.9th percentile, lies
   in ``[clutter_lo, clutter_hi]`` (textured areas such as vegetation; building corners lie above, straight
   edges below zero), closed morphologically, mask the edge map.
4. Line segments with OpenCV's progressive probabilistic Hough transform (the reference's base algorithm; its
   multi-edge-map variant, segment merging and building-closure test are not reproduced), rasterized into a
   layer of doubled-angle vectors ``(cos 2 theta, sin 2 theta)`` so that orientations (modulo 180 deg) can be
   averaged by the patch reconstruction.

Measurement (IV), adapted to a nadir camera: the reference's "view sections" become the cells of a
``cells_x x cells_y`` grid over the camera image. The camera image goes through steps 1, 3 and 4 (the
camera's shadows are not known); each cell with enough line pixels gives an observed orientation
``psi_s`` (its dominant one). For each particle the feature map is reconstructed at its pose (one compiled
sampling pass for all particles, ``PatchSampler.sample``: ``cv2.remap``'s values), rotated into the camera frame
by the particle's yaw, and each cell gives
its expected orientation ``psi_r`` (or none). Eq. (2): ``eta_e = 1 - 1 / (1 + exp((20 - |psi_s - psi_r|) / 2))``
(degrees, orientation difference in [0, 90]; 0 where the map has no line); eq. (3): ``rho_e`` = the cell's
share of the observed cells (equal cells); eq. (4): ``W = sum_e rho_e eta_e``. Log-likelihood:
``log max(W, floor)`` (the reference uses W as the importance factor).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import cv2
import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import build_config, rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.measurement import MeasurementModel, register_model
from aerial_loc_env.estimators.patches import PatchGeometry, PatchSampler, to_gray
from aerial_loc_env.estimators.protocol import parse_observation


@dataclass(frozen=True)
class FeatureMapConfig:
    """Image processing of one image into line features (reference 2, II)."""

    blur_sigma_px: float = field(default=1.0, metadata=rng(0.0, 20.0))
    canny_low: float = field(default=40.0, metadata=rng(0.0, 1000.0))
    canny_high: float = field(default=120.0, metadata=rng(0.0, 1000.0))
    illumination: str = field(default="estimate", metadata=rng(choices=("estimate", "parameter", "none")))
    sun_azimuth_deg: float | None = None    # compass bearing towards the sun (deg), for "parameter"
    dark_ratio: float = field(default=0.6, metadata=rng(0.0, 1.0, lo_open=True,
                                                        doc="shadow candidate: gray < ratio x median"))
    shadow_probe_px: int = field(default=3, metadata=rng(1, 50, doc="distance to the dark side of an edge"))
    min_illumination_consistency: float = field(default=0.15, metadata=rng(0.0, 1.0))
    clutter: bool = True
    harris_block_px: int = field(default=5, metadata=rng(2, 50))
    clutter_lo: float = field(default=0.002, metadata=rng(0.0, 1.0))
    clutter_hi: float = field(default=0.1, metadata=rng(0.0, 1.0))
    clutter_closing_px: int = field(default=9, metadata=rng(1, 101))
    clutter_min_density: float = field(default=0.2, metadata=rng(0.0, 1.0,
                                                                  doc="clutter-pixel fraction in the closing window"))
    hough_threshold: int = field(default=10, metadata=rng(1, 10000))
    min_line_px: int = field(default=8, metadata=rng(2, 10000))
    max_gap_px: int = field(default=3, metadata=rng(0, 1000))
    line_thickness_px: int = field(default=3, metadata=rng(1, 50))
    orientation_source: str = field(default="segments", metadata=rng(
        choices=("segments", "edges"), doc="orientation layer from Hough segments or every kept edge pixel"))

    def validate(self, where: str) -> None:
        if self.canny_low > self.canny_high:
            raise ConfigError(f"{where}: canny_low ({self.canny_low}) must not exceed canny_high ({self.canny_high})")
        if self.clutter_lo >= self.clutter_hi:
            raise ConfigError(f"{where}: clutter_lo ({self.clutter_lo}) must be below clutter_hi ({self.clutter_hi})")
        if self.illumination == "parameter" and self.sun_azimuth_deg is None:
            raise ConfigError(f"{where}: illumination = 'parameter' needs sun_azimuth_deg (compass bearing "
                              "towards the sun, 180 = sun in the south)")
        if self.sun_azimuth_deg is not None and not (isinstance(self.sun_azimuth_deg, (int, float))
                                                     and -360.0 <= self.sun_azimuth_deg <= 360.0):
            raise ConfigError(f"{where}: sun_azimuth_deg = {self.sun_azimuth_deg!r} must be in [-360, 360] degrees")


class FeatureMap(NamedTuple):
    """The layers of one processed image (all (H, W))."""

    edges: np.ndarray            # bool, Canny edges after shadow removal and clutter masking
    raw_edges: np.ndarray        # bool, Canny edges
    shadow_edges: np.ndarray     # bool, the removed shadow edges
    clutter: np.ndarray          # bool, the clutter mask
    segments: np.ndarray         # (S, 4) int32 x1, y1, x2, y2 (pixels)
    orientation: np.ndarray      # (H, W, 2) float32 doubled-angle vectors of the rasterized segments
    sun_azimuth_deg: float | None  # the direction used (given or estimated), None if none


def _gradients(gray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return (cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3), cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3))


def light_direction_px(sun_azimuth_deg: float) -> np.ndarray:
    """Unit vector (du, dv) in image pixels along which the light travels (away from the sun).

    Towards the sun is (east, north) = (sin A, cos A); image rows grow southwards, so away from it is
    (-sin A, +cos A) in (u, v).
    """
    a = math.radians(sun_azimuth_deg)
    return np.array([-math.sin(a), math.cos(a)])


def _dark_side(gray: np.ndarray, gx: np.ndarray, gy: np.ndarray, ys: np.ndarray, xs: np.ndarray,
               probe: int, dark: np.ndarray) -> np.ndarray:
    """Whether the pixel ``probe`` px against the gradient (towards the dark side) of each edge is dark."""
    g = np.hypot(gx[ys, xs], gy[ys, xs]) + 1e-6
    px = np.clip(np.rint(xs - probe * gx[ys, xs] / g), 0, gray.shape[1] - 1).astype(np.int64)
    py = np.clip(np.rint(ys - probe * gy[ys, xs] / g), 0, gray.shape[0] - 1).astype(np.int64)
    return dark[py, px]


def estimate_sun_azimuth(gray: np.ndarray, edges: np.ndarray, cfg: FeatureMapConfig) -> tuple[float, float]:
    """(azimuth_deg, consistency in [0, 1]) of the sun from the shadow borders among ``edges`` (pass edges
    outside the clutter mask: dark texture is not shadow)."""
    gx, gy = _gradients(gray)
    ys, xs = np.nonzero(edges)
    dark = gray < cfg.dark_ratio * float(np.median(gray))
    if len(xs) == 0:
        return 0.0, 0.0
    on_shadow = _dark_side(gray, gx, gy, ys, xs, cfg.shadow_probe_px, dark)
    vx, vy = gx[ys, xs][on_shadow].astype(np.float64), gy[ys, xs][on_shadow].astype(np.float64)
    total = float(np.hypot(vx, vy).sum())
    if total <= 0:
        return 0.0, 0.0
    mx, my = vx.sum() / total, vy.sum() / total        # mean dark -> bright direction: towards the sun
    # towards the sun in pixels is (sin A, -cos A)
    return math.degrees(math.atan2(mx, -my)) % 360.0, float(math.hypot(mx, my))


def clutter_mask(gray: np.ndarray, cfg: FeatureMapConfig) -> np.ndarray:
    """Textured (vegetation-like) areas: Harris response within the configured relative range, closed."""
    r = cv2.cornerHarris(gray, cfg.harris_block_px, 3, 0.04)
    scale = float(np.percentile(r, 99.9))
    if scale <= 0:
        return np.zeros(gray.shape, bool)
    rel = r / scale
    band = ((rel >= cfg.clutter_lo) & (rel <= cfg.clutter_hi)).astype(np.float32)
    k = cfg.clutter_closing_px
    density = cv2.blur(band, (k, k))
    mask = (density >= cfg.clutter_min_density).astype(np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    return cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel).astype(bool)


def rasterize_segments(segments: np.ndarray, shape: tuple[int, int], thickness: int) -> np.ndarray:
    """(H, W, 2) float32 layer of doubled-angle unit vectors along each segment (0 elsewhere)."""
    layer = np.zeros(shape + (2,), np.float32)
    for x1, y1, x2, y2 in np.asarray(segments, dtype=np.int64).reshape(-1, 4):
        t2 = 2.0 * math.atan2(y2 - y1, x2 - x1)
        cv2.line(layer, (int(x1), int(y1)), (int(x2), int(y2)), (math.cos(t2), math.sin(t2)), thickness)
    return layer


def edge_orientation_layer(gray: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32 doubled-angle unit vectors of the edge direction (gradient + 90 deg) on ``edges``."""
    gx, gy = _gradients(gray)
    t2 = 2.0 * (portable.arctan2(gy, gx) + np.pi / 2)
    layer = np.stack([np.cos(t2), np.sin(t2)], axis=-1).astype(np.float32)
    layer[~edges] = 0.0
    return layer


def build_feature_map(rgb_or_gray: np.ndarray, cfg: FeatureMapConfig | None = None, *,
                      remove_shadow_edges: bool = True) -> FeatureMap:
    """Run steps 1-4 of the module docstring on one image (database: with shadow removal; camera: without)."""
    cfg = cfg or FeatureMapConfig()
    img = np.asarray(rgb_or_gray)
    gray = to_gray(img) if img.ndim == 3 else img.astype(np.float32)
    if cfg.blur_sigma_px > 0:
        gray = cv2.GaussianBlur(gray, (0, 0), cfg.blur_sigma_px)
    g8 = np.clip(gray, 0, 255).astype(np.uint8)
    raw = cv2.Canny(g8, cfg.canny_low, cfg.canny_high, L2gradient=True).astype(bool)
    edges = raw.copy()
    shadow = np.zeros_like(raw)
    clutter = clutter_mask(gray, cfg) if cfg.clutter else np.zeros_like(raw)
    azimuth: float | None = None
    if remove_shadow_edges and cfg.illumination != "none":
        if cfg.illumination == "parameter":
            azimuth = float(cfg.sun_azimuth_deg)
        else:
            az, consistency = estimate_sun_azimuth(gray, raw & ~clutter, cfg)
            azimuth = az if consistency >= cfg.min_illumination_consistency else None
        if azimuth is not None:
            gx, gy = _gradients(gray)
            ys, xs = np.nonzero(raw)
            dark = gray < cfg.dark_ratio * float(np.median(gray))
            on_shadow = _dark_side(gray, gx, gy, ys, xs, cfg.shadow_probe_px, dark)
            light = light_direction_px(azimuth)
            increases = gx[ys, xs] * light[0] + gy[ys, xs] * light[1] > 0   # brighter away from the sun
            drop = on_shadow & increases
            shadow[ys[drop], xs[drop]] = True
            edges[ys[drop], xs[drop]] = False
    edges &= ~clutter
    lines = cv2.HoughLinesP(edges.astype(np.uint8) * 255, 1, np.pi / 180, cfg.hough_threshold,
                            minLineLength=cfg.min_line_px, maxLineGap=cfg.max_gap_px)
    segments = np.zeros((0, 4), np.int32) if lines is None else lines.reshape(-1, 4).astype(np.int32)
    if cfg.orientation_source == "segments":
        orientation = rasterize_segments(segments, gray.shape, cfg.line_thickness_px)
    else:
        orientation = edge_orientation_layer(gray, edges)
    return FeatureMap(edges, raw, shadow, clutter, segments, orientation, azimuth)


# ---------------------------------------------------------------------- measurement model
@dataclass(frozen=True)
class EdgeModelConfig:
    map_params: dict = field(default_factory=dict)          # -> FeatureMapConfig for the database
    camera_clutter: bool = True
    cells_x: int = field(default=6, metadata=rng(1, 100, doc="view sections across the frame"))
    cells_y: int = field(default=4, metadata=rng(1, 100, doc="view sections along the frame"))
    nodes_per_cell: int = field(default=8, metadata=rng(1, 100, doc="samples per cell side"))
    min_coverage: float = field(default=0.04, metadata=rng(0.0, 1.0, lo_open=True,
                                                           doc="line coverage for a cell to hold a feature"))
    sigmoid_center_deg: float = field(default=20.0, metadata=rng(0.0, 90.0))
    sigmoid_width_deg: float = field(default=2.0, metadata=rng(0.0, 90.0, lo_open=True))
    floor: float = field(default=0.05, metadata=rng(0.0, 1.0, lo_open=True, doc="log max(W, floor)"))

    def validate(self, where: str) -> None:
        build_config(FeatureMapConfig, self.map_params, where=f"{where}: map_params")


def orientation_similarity(diff_rad: np.ndarray, center_deg: float = 20.0, width_deg: float = 2.0) -> np.ndarray:
    """Eq. (2) of reference 2: ``1 - 1 / (1 + exp((center - |d|) / width))``, ``d`` in degrees."""
    d = np.degrees(np.abs(diff_rad))
    return 1.0 - 1.0 / (1.0 + portable.exp(np.clip((center_deg - d) / width_deg, -60.0, 60.0)))


def cell_orientations(layer: np.ndarray, cells_x: int, cells_y: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-cell (doubled angle, coverage) of doubled-angle layers (..., h, w, 2) -> (..., cy, cx) each."""
    *lead, h, w, _ = layer.shape
    blocks = layer.reshape(*lead, cells_y, h // cells_y, cells_x, w // cells_x, 2).sum(axis=(-4, -2))
    n = (h // cells_y) * (w // cells_x)
    return portable.arctan2(blocks[..., 1], blocks[..., 0]), np.hypot(blocks[..., 0], blocks[..., 1]) / n


class PreparedEdges(NamedTuple):
    angle2: np.ndarray       # (cy, cx) observed doubled angles (camera frame)
    observed: np.ndarray     # (cy, cx) bool: cells holding an observed feature


class EdgeOrientationModel(MeasurementModel):
    """Line-orientation matching per view section with the reference's sigmoid similarity (eq. 2-4)."""

    Config = EdgeModelConfig

    def __init__(self, config: EdgeModelConfig | None = None) -> None:
        super().__init__(config or EdgeModelConfig())
        self.map_cfg = build_config(FeatureMapConfig, self.config.map_params, where="edges: map_params")
        # the camera's image gets the same processing without shadow-edge removal (its shadows are unknown)
        self.cam_cfg = replace(self.map_cfg, illumination="none", clutter=self.config.camera_clutter)
        self.sampler: PatchSampler | None = None
        self.segments: np.ndarray | None = None
        self.sun_azimuth_deg: float | None = None

    def reset(self, briefing, rng: np.random.Generator) -> None:
        cfg: EdgeModelConfig = self.config
        m = briefing.orthomap
        fm = build_feature_map(np.asarray(m.rgb), self.map_cfg)
        geometry = PatchGeometry(cfg.cells_x * cfg.nodes_per_cell, cfg.cells_y * cfg.nodes_per_cell)
        self.sampler = PatchSampler(m, briefing.camera, geometry, fm.orientation, briefing.altitude_m,
                                    nodata=m.nodata)
        # keep the vector features for reports; the full-resolution raster layers (hundreds of MB on the
        # paper's map) live on only in the sampler's downsampled level
        self.segments, self.sun_azimuth_deg = fm.segments, fm.sun_azimuth_deg

    def prepare(self, observation: Mapping[str, np.ndarray], rng: np.random.Generator,
                info: Mapping[str, Any] | None = None) -> PreparedEdges:
        if self.sampler is None:
            raise ConfigError("edges: call reset(briefing, rng) before prepare()")
        cfg: EdgeModelConfig = self.config
        obs = parse_observation(observation)
        fm = build_feature_map(obs.image, self.cam_cfg, remove_shadow_edges=False)
        g = self.sampler.geometry
        small = cv2.resize(fm.orientation, (g.width_px, g.height_px), interpolation=cv2.INTER_AREA)
        angle2, coverage = cell_orientations(small, cfg.cells_x, cfg.cells_y)
        observed = coverage >= cfg.min_coverage
        self.last_stats = {"segments": int(len(fm.segments)), "observed_cells": int(observed.sum())}
        return PreparedEdges(angle2, observed)

    def log_likelihood(self, prepared: PreparedEdges, states: np.ndarray, altitude_m: float) -> np.ndarray:
        cfg: EdgeModelConfig = self.config
        if self.sampler is None:
            raise ConfigError("edges: call reset(briefing, rng) before log_likelihood()")
        n = len(states)
        n_obs = int(prepared.observed.sum())
        if n_obs == 0:
            return np.zeros(n)                   # nothing observed: no information, equal weights
        layers, valid = self.sampler.sample(states, altitude_m)
        layers[~valid] = 0.0
        map2, coverage = cell_orientations(layers, cfg.cells_x, cfg.cells_y)          # (N, cy, cx)
        # map -> camera orientation: theta_cam = theta_map - pi/2 + yaw (doubled: + 2 yaw - pi)
        exp2 = map2 + (2.0 * np.asarray(states, float)[:, 2] - math.pi)[:, None, None]
        turn = np.exp(1j * (exp2 - prepared.angle2[None]))
        diff2 = portable.arctan2(turn.imag, turn.real)                              # wrapped to (-pi, pi]
        eta = orientation_similarity(diff2 / 2.0, cfg.sigmoid_center_deg, cfg.sigmoid_width_deg)
        eta = np.where(coverage >= cfg.min_coverage, eta, 0.0)
        w = (eta * prepared.observed[None]).sum(axis=(1, 2)) / n_obs                  # eq. (3)-(4)
        w = np.where(valid, w, 0.0)
        return portable.log(np.maximum(w, cfg.floor))


register_model("edges", EdgeOrientationModel)
