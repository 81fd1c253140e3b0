"""Reconstructed camera images ("virtual" views of the database) at many poses, with one ``cv2.remap``.

The dense measurement models (SSD, NCC, MI), abBRIEF and the edge model compare the camera image with the
database patch each particle would see (Choi & Park, II.B "reconstructed camera image"). Doing that with one
OpenCV warp per particle is a Python loop of N calls; here the N patches are sampled in ONE ``cv2.remap`` over
stacked coordinate maps of shape (N * h, w).

Geometry is not re-derived: the per-particle affine camera pixel -> map pixel is ``CameraModel.camera_to_map``
(eq. (3), ``s R(psi) x + T``). It is composed with two fixed affines (reduced camera grid -> full camera pixels,
full map pixels -> the pixels of an anti-aliased, downsampled copy of the database), and, because an affine map
of a regular grid is separable, the (N, h, w) coordinates are built with two broadcast additions.

Anti-aliasing: the camera image is reduced with ``cv2.INTER_AREA`` (a box filter) and the database is
downsampled once at reset with ``INTER_AREA`` by the map-pixels-per-patch-pixel factor at the nominal altitude,
so both sides are low-passed alike before the comparison.

Out-of-map samples and the database's no-data pixels come out as NaN (float32 images); ``sample`` returns a
per-particle validity flag so that the models give such particles the worst likelihood, never NaN.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import ConfigError

#: cv2.remap refuses maps with more rows than this (SHRT_MAX); larger particle sets are sampled in chunks.
_MAX_REMAP_ROWS = 32000
#: samples per chunk of ``PatchSampler.sample_chunks``: the chunk's two maps and its samples (1.4 MB at
#: 120 000 float32 samples) stay in a 2 MB L2 cache until they are scored (50 particles of 60 x 40)
_CHUNK_SAMPLES = 120_000


def reduce_image(image: np.ndarray, width_px: int, height_px: int) -> np.ndarray:
    """Box-filter ``image`` down (or up) to ``width_px x height_px`` (``cv2.INTER_AREA``), as float32."""
    img = np.asarray(image)
    if img.shape[1] == width_px and img.shape[0] == height_px:
        return img.astype(np.float32, copy=False)
    return cv2.resize(img.astype(np.float32, copy=False), (int(width_px), int(height_px)),
                      interpolation=cv2.INTER_AREA)


def to_gray(rgb: np.ndarray) -> np.ndarray:
    """Luma (ITU-R 601, as ``cv2.COLOR_RGB2GRAY``) of an (H, W, 3) RGB image, float32 in [0, 255]."""
    arr = np.asarray(rgb)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ConfigError(f"to_gray: expected an (H, W, 3) RGB image, got shape {arr.shape}")
    return cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2GRAY).astype(np.float32)


@dataclass(frozen=True)
class PatchGeometry:
    """The reduced sampling grid: ``width_px x height_px`` samples spread over the whole camera frame."""

    width_px: int
    height_px: int

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 2 <= v <= 4000:
                raise ConfigError(f"patch geometry: '{name}' = {v!r} must be an integer in [2, 4000]")

    @property
    def n_pixels(self) -> int:
        return int(self.width_px * self.height_px)


class PatchSampler:
    """Samples database patches (the reconstructed camera images) for many poses at once.

    ``image`` is the database layer to sample: (H, W) or (H, W, C<=4), any dtype, already in the model's
    representation (gray, CIELab a/b, edge orientation ...); ``nodata`` (H, W) bool marks pixels to treat as
    missing. ``downsample`` (default: automatic) is the map-pixel size of one sample of the stored level.
    """

    def __init__(self, orthomap, camera, geometry: PatchGeometry, image: np.ndarray, altitude_m: float, *,
                 nodata: np.ndarray | None = None, downsample: float | None = None) -> None:
        img = np.asarray(image)
        if img.shape[:2] != (orthomap.height_px, orthomap.width_px):
            raise ConfigError(f"PatchSampler: database layer shape {img.shape[:2]} differs from the map's "
                              f"({orthomap.height_px}, {orthomap.width_px})")
        if img.ndim == 3 and img.shape[2] > 4:
            raise ConfigError(f"PatchSampler: at most 4 channels can be sampled at once, got {img.shape[2]}")
        self.orthomap = orthomap
        self.camera = camera
        self.geometry = geometry
        if downsample is None:
            # map pixels per patch sample at the nominal altitude (the box filter of reduce_image on the camera)
            step_m = camera.gsd_m(altitude_m) * camera.width_px / geometry.width_px
            downsample = max(1.0, step_m / max(orthomap.gsd_x_m, orthomap.gsd_y_m))
        level = img.astype(np.float32)
        h, w = img.shape[:2]
        lw, lh = max(2, int(round(w / downsample))), max(2, int(round(h / downsample)))
        if (lw, lh) != (w, h):
            level = cv2.resize(level, (lw, lh), interpolation=cv2.INTER_AREA)
        if nodata is not None and np.any(nodata):
            # INTER_AREA does not propagate NaN: mark every level pixel that averages any no-data pixel
            bad = np.asarray(nodata, dtype=np.float32)
            if (lw, lh) != (w, h):
                bad = cv2.resize(bad, (lw, lh), interpolation=cv2.INTER_AREA)
            level[bad > 0] = np.nan                 # (all channels; level is a copy of the layer)
        self.level = np.ascontiguousarray(level)
        self.has_nan = bool(np.isnan(self.level).any())
        # OpenCV's remap has vectorized paths for 1 and 4 float channels only: a 2- or 3-channel level is
        # sampled as 4 channels (zero padding) and cut back, the same values 4x faster (2 channels)
        self._channels = 1 if self.level.ndim == 2 else self.level.shape[2]
        self._remap_level = self.level
        if self._channels in (2, 3):
            pad = np.zeros(self.level.shape[:2] + (4 - self._channels,), np.float32)
            self._remap_level = np.ascontiguousarray(np.concatenate([self.level, pad], axis=2))
        self.level_size = (lw, lh)
        # full map pixel -> level pixel (pixel centres at integers on both)
        fx, fy = w / lw, h / lh
        self._to_level = np.array([[1.0 / fx, 0.0, 0.5 / fx - 0.5],
                                   [0.0, 1.0 / fy, 0.5 / fy - 0.5],
                                   [0.0, 0.0, 1.0]])
        # reduced camera grid -> full camera pixel
        sx, sy = camera.width_px / geometry.width_px, camera.height_px / geometry.height_px
        self._from_grid = np.array([[sx, 0.0, 0.5 * sx - 0.5],
                                    [0.0, sy, 0.5 * sy - 0.5],
                                    [0.0, 0.0, 1.0]])
        self._cols = np.arange(geometry.width_px, dtype=np.float32)
        self._rows = np.arange(geometry.height_px, dtype=np.float32)
        self._map_buffers: tuple[np.ndarray, np.ndarray] | None = None

    def grid_to_level(self, states: np.ndarray, altitude_m: float) -> np.ndarray:
        """Affines (N, 2, 3): reduced-grid pixel -> stored-level pixel, from ``camera_to_map`` (eq. (3))."""
        states = _check_states(states)
        a = self.camera.camera_to_map(self.orthomap, states[:, 0], states[:, 1], states[:, 2], altitude_m)
        a3 = np.zeros((len(states), 3, 3))
        a3[:, :2] = a.reshape(-1, 2, 3)
        a3[:, 2, 2] = 1.0
        return (self._to_level @ a3 @ self._from_grid)[:, :2]

    def sample_nodes(self, states: np.ndarray, altitude_m: float,
                     nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Only the grid nodes ``nodes`` (flat indices ``row * w + col``) of every patch: (N, len(nodes)[, S])
        float32 with ``S = node_channels`` (a 2- or 3-channel level comes back with its zero padding to 4
        channels, the real ones first: no copy to cut it), the same values as
        ``sample(...)[0].reshape(N, h * w, ...)[:, nodes]`` bit for bit (the same float32 map arithmetic per
        node), and the same validity. For models that read a few nodes of the grid (abBRIEF's test points).
        With no-data in the database the whole patch decides the validity, so the whole patch is sampled."""
        nodes = np.asarray(nodes, dtype=np.intp)
        if self.has_nan:
            patches, valid = self.sample(states, altitude_m)
            n = patches.shape[0]
            values = patches.reshape((n, -1) + patches.shape[3:])[:, nodes]
            if self.node_channels != self._channels:
                values = np.concatenate([values, np.zeros(values.shape[:2] + (4 - self._channels,),
                                                          np.float32)], axis=2)
            return np.ascontiguousarray(values), valid
        e = self.grid_to_level(states, altitude_m).astype(np.float32)
        gw = self.geometry.width_px
        cols, rows = self._cols[nodes % gw], self._rows[nodes // gw]
        mx, my = _node_coords(e, cols, rows)
        chans = () if self._remap_level.ndim == 2 else (self._remap_level.shape[2],)
        out = np.empty((e.shape[0], nodes.size) + chans, np.float32)
        for start in range(0, e.shape[0], _MAX_REMAP_ROWS):
            stop = min(e.shape[0], start + _MAX_REMAP_ROWS)
            self._remap_into(out[start:stop], mx[start:stop], my[start:stop])
        return out, self._footprint_valid(e)

    @property
    def node_channels(self) -> int:
        """Channels of ``sample_nodes``' values: the level's, or 4 where it is padded (2 or 3 channels)."""
        return 1 if self._remap_level.ndim == 2 else self._remap_level.shape[2]

    def _maps(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Level-pixel coordinates (N, h, w) of every grid node, float32: ``e_00 col + (e_01 row + e_02)``.

        Written into two buffers kept across calls (fresh 7 MB arrays cost their page faults on every step),
        as a copy of the per-column term then one in-place add of the per-row term: the same float32 sums as
        a broadcast ``np.add``, in passes with longer inner loops. Valid until the next call.
        """
        n = e.shape[0]
        gh, gw = self.geometry.height_px, self.geometry.width_px
        if self._map_buffers is None or self._map_buffers[0].shape[0] < n:
            self._map_buffers = (np.empty((n, gh, gw), np.float32), np.empty((n, gh, gw), np.float32))
        maps = tuple(b[:n] for b in self._map_buffers)
        for i, m in enumerate(maps):
            m[...] = (e[:, i, 0, None] * self._cols)[:, None, :]
            m += (e[:, i, 1, None] * self._rows + e[:, i, 2, None])[:, :, None]
        return maps

    def _remap_into(self, out: np.ndarray, mx: np.ndarray, my: np.ndarray) -> None:
        """Bilinear samples of the level at (mx, my) (any (M, ...) shape, at most 32000 rows once flattened to
        2-D) written straight into ``out`` (dst=): no second copy of the samples."""
        cols = mx.shape[-1]
        dst = out.reshape((-1, cols) + out.shape[mx.ndim:])
        level = self._remap_level
        direct = level.ndim == dst.ndim and (level.ndim == 2 or level.shape[2] == dst.shape[2])
        res = cv2.remap(level, mx.reshape(-1, cols), my.reshape(-1, cols), cv2.INTER_LINEAR,
                        dst=dst if direct else None, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))
        if not direct:                       # a padded level: keep the real channels
            dst[...] = res[..., :dst.shape[-1]]
        elif not np.shares_memory(res, dst):   # OpenCV reallocated (never expected): copy instead
            dst[...] = res.reshape(dst.shape)

    def _footprint_valid(self, e: np.ndarray) -> np.ndarray:
        """Footprint inside the level: an affine image of the grid has its extremes at the grid corners (the
        corner coordinates computed as ``_maps`` computes them, so the same floats)."""
        gh, gw = self.geometry.height_px, self.geometry.width_px
        cols, rows = self._cols[[0, gw - 1, 0, gw - 1]], self._rows[[0, 0, gh - 1, gh - 1]]
        cu, cv = _node_coords(e, cols, rows)
        lw, lh = self.level_size
        return (cu.min(1) >= 0) & (cu.max(1) <= lw - 1) & (cv.min(1) >= 0) & (cv.max(1) <= lh - 1)

    def sample(self, states: np.ndarray, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Patches (N, h, w[, C]) float32 and validity (N,) bool (footprint inside the map, no no-data)."""
        e = self.grid_to_level(states, altitude_m).astype(np.float32)
        n = e.shape[0]
        gh, gw = self.geometry.height_px, self.geometry.width_px
        mx, my = self._maps(e)
        chans = () if self.level.ndim == 2 else (self.level.shape[2],)
        out = np.empty((n, gh, gw) + chans, np.float32)
        per = max(1, _MAX_REMAP_ROWS // gh)
        for start in range(0, n, per):  # one remap for N <= 32000 / h particles (800 at h = 40)
            stop = min(n, start + per)
            self._remap_into(out[start:stop], mx[start:stop], my[start:stop])
        valid = self._footprint_valid(e)
        if self.has_nan:
            valid &= ~np.isnan(out.reshape(n, -1)).any(axis=1)
        return out, valid


    def sample_chunks(self, states: np.ndarray, altitude_m: float, samples_per_chunk: int = _CHUNK_SAMPLES
                      ) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
        """``sample`` a chunk of particles at a time: yields (the chunk's slice of the particles, its patches
        (k, h, w[, C]) float32, its validity (k,) bool), the same values as ``sample`` bit for bit (the same
        float32 maps and remap per sample). The patches live in one buffer that the next chunk overwrites:
        score them before advancing. Scoring a chunk while its maps and samples are still in the cache is
        ~7 % faster than scoring the (N, h, w) stack once it is all sampled (SSD at N = 700)."""
        e = self.grid_to_level(states, altitude_m).astype(np.float32)
        n = e.shape[0]
        gh, gw = self.geometry.height_px, self.geometry.width_px
        per = max(1, min(samples_per_chunk // (gh * gw), _MAX_REMAP_ROWS // gh))
        chans = () if self.level.ndim == 2 else (self.level.shape[2],)
        buffer = np.empty((min(per, n), gh, gw) + chans, np.float32)
        valid = self._footprint_valid(e)
        for start in range(0, n, per):
            stop = min(n, start + per)
            patches = buffer[:stop - start]
            mx, my = self._maps(e[start:stop])
            self._remap_into(patches, mx, my)
            ok = valid[start:stop]
            if self.has_nan:
                ok = ok & ~np.isnan(patches.reshape(stop - start, -1)).any(axis=1)
            yield slice(start, stop), patches, ok


def _node_coords(e: np.ndarray, cols: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Level-pixel coordinates (u, v), (N, M) float32, of the M grid nodes at (``cols[j]``, ``rows[j]``) under
    each particle's affine ``e`` (N, 2, 3): ``e_00 col + (e_01 row + e_02)``, the float32 sums ``_maps``
    computes for every node."""
    u = (e[:, 0, 0, None] * cols) + (e[:, 0, 1, None] * rows + e[:, 0, 2, None])
    v = (e[:, 1, 0, None] * cols) + (e[:, 1, 1, None] * rows + e[:, 1, 2, None])
    return u, v


def _check_states(states: np.ndarray) -> np.ndarray:
    s = np.asarray(states, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3:
        raise ConfigError(f"measurement model: states must have shape (N, 3) = [x_m, y_m, yaw_rad], got {s.shape}")
    return s
