"""abBRIEF measurement model (Mantelli et al., "A novel measurement model based on abBRIEF for global
localization of a UAV over satellite images", Robotics and Autonomous Systems 112, 2019), the fourth comparison
model of Choi & Park (Tables 6 and 9, their reference [24]).

What abBRIEF is: a BRIEF descriptor (binary intensity comparisons ``tau = [I(x1) > I(x2)]`` between pixel
pairs of a smoothed image, compared by Hamming distance) computed not on the intensity but on the two
chromatic channels *a* and *b* of CIELab, dropping the lightness L so that the descriptor depends less on the
illumination. In the MCL the camera image's descriptor is compared with the descriptor of the database view
reconstructed at each particle's pose (Choi & Park's eq. (2)-(5) are this scheme with c channels).

Choices this implementation makes where the description leaves room (the original paper was not available to
check against; these are documented, configurable, and tested for behaviour, not for agreement with it):

- Colour: OpenCV's CIELab of sRGB (D65), 8-bit coding (a, b offset by 128). ``channels = "ab"`` (abBRIEF),
  ``"Lab"`` or ``"L"`` (plain BRIEF on lightness, for ablations).
- Smoothing: BRIEF smooths before testing; here both images are box-filtered to a ``grid_width_px x
  grid_height_px`` working grid (the camera with ``INTER_AREA``, the database by ``estimators.patches``), and
  the test points are nodes of that grid, so each particle's view is sampled at the pattern's nodes only and
  its bits compared with the camera's in the same compiled pass (``PatchSampler.score``).
- Keypoints: a regular ``keypoints_x x keypoints_y`` grid of keypoints over the frame (the camera is nadir and
  gimbaled, so no detector or orientation is needed); each keypoint has ``tests_per_keypoint`` pairs drawn once
  per episode (the agent's seeded Generator) from BRIEF's isotropic Gaussian G II, ``sigma = S / 5`` with
  ``S`` the keypoint's cell, clipped to the cell. The same pattern serves every frame (BRIEF's fixed pattern).
- Similarity: ``xi`` = fraction of agreeing bits over all keypoints and channels (1 - normalized Hamming
  distance; Choi & Park's eq. (4)). Likelihood: their eq. (5), ``xi ~ N(1, sigma)``:
  ``log p = -(1 - xi)^2 / (2 sigma^2)``. A particle whose view leaves the map or touches no-data scores the
  chance level ``xi = 1/2``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import cv2
import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.mcl.measurement import MeasurementModel, register_model
from aerial_loc_env.estimators.patches import BRIEF, PatchGeometry, PatchSampler, reduce_image
from aerial_loc_env.estimators.protocol import parse_observation

_CHANNELS = {"ab": (1, 2), "Lab": (0, 1, 2), "L": (0,)}


@dataclass(frozen=True)
class ABBriefConfig:
    channels: str = field(default="ab", metadata=rng(choices=tuple(_CHANNELS), doc="CIELab channels tested"))
    grid_width_px: int = field(default=60, metadata=rng(4, 1000, doc="working grid across the frame"))
    grid_height_px: int = field(default=40, metadata=rng(4, 1000, doc="working grid along the frame"))
    keypoints_x: int = field(default=4, metadata=rng(1, 64))
    keypoints_y: int = field(default=3, metadata=rng(1, 64))
    tests_per_keypoint: int = field(default=64, metadata=rng(1, 4096, doc="BRIEF bits per keypoint/channel"))
    sigma: float = field(default=0.1, metadata=rng(0.0, 10.0, lo_open=True, doc="std of xi in eq. (5)"))

    def validate(self, where: str) -> None:
        if self.grid_width_px < 2 * self.keypoints_x or self.grid_height_px < 2 * self.keypoints_y:
            raise ConfigError(f"{where}: the working grid {self.grid_width_px}x{self.grid_height_px} needs at "
                              f"least 2 x 2 nodes per keypoint cell ({self.keypoints_x}x{self.keypoints_y} cells)")


def brief_pattern(grid_w: int, grid_h: int, kx: int, ky: int, tests: int,
                  rng_: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """BRIEF G II test pairs around a kx x ky grid of keypoints: flat node indices (kx ky tests,) x 2.

    Points are drawn from N(centre, (S/5)^2) per axis (S = cell size), rounded to nodes and clipped to the
    cell; a pair whose two points coincide moves its second point by one node.
    """
    cw, ch = grid_w / kx, grid_h / ky
    cx = (np.arange(kx) + 0.5) * cw - 0.5
    cy = (np.arange(ky) + 0.5) * ch - 0.5
    centres = np.stack(np.meshgrid(cx, cy, indexing="xy"), axis=-1).reshape(-1, 1, 1, 2)   # (G, 1, 1, 2)
    scale = np.array([cw, ch]) / 5.0
    pts = centres + rng_.standard_normal((centres.shape[0], tests, 2, 2)) * scale          # (G, T, 2, 2)
    lo = np.floor(centres - np.array([cw, ch]) / 2 + 0.5)
    hi = np.ceil(centres + np.array([cw, ch]) / 2 - 0.5)
    pts = np.clip(np.rint(pts), lo, hi).astype(np.int64)
    pts[..., 0] = np.clip(pts[..., 0], 0, grid_w - 1)
    pts[..., 1] = np.clip(pts[..., 1], 0, grid_h - 1)
    p1, p2 = pts[:, :, 0].reshape(-1, 2), pts[:, :, 1].reshape(-1, 2)
    same = np.all(p1 == p2, axis=1)
    p2[same, 0] = np.where(p2[same, 0] + 1 < grid_w, p2[same, 0] + 1, p2[same, 0] - 1)
    return p1[:, 1] * grid_w + p1[:, 0], p2[:, 1] * grid_w + p2[:, 0]


def _lab(rgb: np.ndarray) -> np.ndarray:
    """OpenCV's 8-bit CIELab (H, W, 3) uint8 of an RGB uint8 image."""
    arr = np.asarray(rgb)
    if arr.ndim != 3 or arr.shape[2] != 3 or arr.dtype != np.uint8:
        raise ConfigError(f"abBRIEF: expected an (H, W, 3) uint8 RGB image, got {arr.shape} {arr.dtype}")
    return cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2Lab)


def lab_channels(rgb: np.ndarray, channels: str) -> np.ndarray:
    """The selected CIELab channels (H, W, c) float32 of an RGB uint8 image (OpenCV 8-bit Lab coding)."""
    return _lab(rgb)[..., list(_CHANNELS[channels])].astype(np.float32)


def reduced_lab(rgb: np.ndarray, channels: str, width_px: int, height_px: int) -> np.ndarray:
    """``reduce_image(lab_channels(rgb, channels), width_px, height_px)`` as (h, w, c), the same floats faster:
    all three Lab planes are box-filtered together (OpenCV's area resize has a fast 3-channel path, not a
    2-channel one; each channel is filtered alike either way), straight from the converted frame (no copy of
    it that selects channels), then the selected ones are kept."""
    return np.ascontiguousarray(reduce_image(_lab(rgb), width_px, height_px)[..., list(_CHANNELS[channels])])


class PreparedBrief(NamedTuple):
    bits: np.ndarray          # (P c,) bool: the camera's descriptor


class ABBriefModel(MeasurementModel):
    """BRIEF on the CIELab a/b channels, Hamming similarity, eq. (5) likelihood."""

    Config = ABBriefConfig

    def __init__(self, config: ABBriefConfig | None = None) -> None:
        super().__init__(config or ABBriefConfig())
        self.sampler: PatchSampler | None = None

    def reset(self, briefing, rng: np.random.Generator) -> None:
        cfg: ABBriefConfig = self.config
        m = briefing.orthomap
        geometry = PatchGeometry(cfg.grid_width_px, cfg.grid_height_px)
        self.sampler = PatchSampler(m, briefing.camera, geometry, lab_channels(m.rgb, cfg.channels),
                                    briefing.altitude_m, nodata=m.nodata)
        idx1, idx2 = brief_pattern(cfg.grid_width_px, cfg.grid_height_px, cfg.keypoints_x,
                                   cfg.keypoints_y, cfg.tests_per_keypoint, rng)
        c = len(_CHANNELS[cfg.channels])
        # indices into (h w c) rows: test i on channel j is column i c + j
        self._i1 = (idx1[:, None] * c + np.arange(c)).ravel()
        self._i2 = (idx2[:, None] * c + np.arange(c)).ravel()
        # the particles' views are sampled at the pattern's distinct nodes only; with no-data in the database
        # at every node, since the whole patch decides the validity
        g = self.sampler.geometry
        nodes = np.arange(g.n_pixels) if self.sampler.has_nan else np.unique(np.concatenate([idx1, idx2]))
        self._points = self.sampler.node_points(nodes)
        position = np.empty(g.n_pixels, np.int64)
        position[nodes] = np.arange(nodes.size)
        # the kernel's tests, in the descriptor's order (test i on channel j at i c + j): (first, second, channel)
        self._tests = np.ascontiguousarray(np.stack([np.repeat(position[idx1], c), np.repeat(position[idx2], c),
                                                     np.tile(np.arange(c), idx1.size)], axis=1))
        self._channels = c

    def _descriptor(self, values: np.ndarray) -> np.ndarray:
        """Bits (M, P c) of grid values (M, h w c) (nodes x channels flattened, channel fastest)."""
        return np.take(values, self._i1, axis=1) > np.take(values, self._i2, axis=1)

    def prepare(self, observation: Mapping[str, np.ndarray], rng: np.random.Generator,
                info: Mapping[str, Any] | None = None) -> PreparedBrief:
        if self.sampler is None:
            raise ConfigError("abBRIEF: call reset(briefing, rng) before prepare()")
        obs = parse_observation(observation)
        g = self.sampler.geometry
        small = reduced_lab(obs.image, self.config.channels, g.width_px, g.height_px)
        bits = self._descriptor(small.reshape(1, -1))[0]
        self.last_stats = {"bits": int(bits.size)}
        return PreparedBrief(bits)

    def similarity(self, prepared: PreparedBrief, states: np.ndarray, altitude_m: float) -> np.ndarray:
        """xi (N,): fraction of the camera's bits that the view at each particle reproduces (eq. (4): the XNOR
        count over keypoints x tests x channels). The kernel samples each view at the pattern's nodes and counts
        the disagreeing bits exactly (integers: the same xi as comparing the bool descriptors); a view that
        leaves the map or touches no-data scores 1/2."""
        if self.sampler is None:
            raise ConfigError("abBRIEF: call reset(briefing, rng) before scoring particles")
        cam_bits = np.ascontiguousarray(prepared.bits, dtype=np.bool_)
        if cam_bits.shape != (self._tests.shape[0],):
            raise ConfigError(f"abBRIEF: the prepared descriptor has {cam_bits.size} bits, the pattern "
                              f"{self._tests.shape[0]}: prepare() and similarity() of different models")
        stats, valid = self.sampler.score(states, altitude_m, BRIEF, points=self._points, channels=self._channels,
                                          tests=self._tests, cam_bits=cam_bits)
        disagree = stats[:, 0]
        valid &= disagree >= 0
        n_bits = cam_bits.size
        return np.where(valid, (n_bits - disagree) / float(n_bits), 0.5)

    def similarity_reference(self, prepared: PreparedBrief, states: np.ndarray, altitude_m: float) -> np.ndarray:
        """The direct form (whole patches, bool descriptors, XNOR count): the tests' reference."""
        patches, valid = self.sampler.sample(states, altitude_m)
        db_bits = self._descriptor(patches.reshape(len(patches), -1))
        xi = np.count_nonzero(db_bits == prepared.bits, axis=1) / float(prepared.bits.size)
        return np.where(valid, xi, 0.5)

    def log_likelihood(self, prepared: PreparedBrief, states: np.ndarray, altitude_m: float) -> np.ndarray:
        xi = self.similarity(prepared, states, altitude_m)
        return -np.square(1.0 - xi) / (2.0 * self.config.sigma ** 2)


register_model("abbrief", ABBriefModel)
register_model("brief", ABBriefModel, channels="L")
