"""Reconstructed camera images ("virtual" views of the database) at many poses, in one compiled pass.

The dense measurement models (SSD, NCC, MI), abBRIEF and the edge model compare the camera image with the
database patch each particle would see (Choi & Park, II.B "reconstructed camera image"). Doing that with one
OpenCV warp per particle is a Python loop of N calls; here every particle's patch is sampled straight from the
stored level by its affine in ``patches_kernels.scan`` (cv2.remap's bilinear values, no coordinate maps) and, for
the models, scored in the same pass (``PatchSampler.score``): nothing of size N h w is materialized.

Geometry is not re-derived: the per-particle affine camera pixel -> map pixel is ``CameraModel.camera_to_map``
(eq. (3), ``s R(psi) x + T``). It is composed with two fixed affines (reduced camera grid -> full camera pixels,
full map pixels -> the pixels of an anti-aliased, downsampled copy of the database); a grid node's level
coordinates are the float32 ``e00 col + (e01 row + e02)``.

Anti-aliasing: the camera image is reduced with ``cv2.INTER_AREA`` (a box filter) and the database is
downsampled once at reset with ``INTER_AREA`` by the map-pixels-per-patch-pixel factor at the nominal altitude,
so both sides are low-passed alike before the comparison.

Out-of-map samples and the database's no-data pixels come out as NaN (float32 images); ``sample`` and ``score``
return a per-particle validity flag so that the models give such particles the worst likelihood, never NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.estimators import patches_kernels as kernels
from aerial_loc_env.estimators.database import DatabaseWindow
from aerial_loc_env.estimators.patches_kernels import BRIEF, HISTOGRAM, MOMENTS, SAMPLE

__all__ = ["BRIEF", "HISTOGRAM", "MOMENTS", "SAMPLE", "PatchGeometry", "PatchSampler", "reduce_image", "to_gray"]

#: footprints farther off the level than this (level pixels) are sampled by the kernel's general path only
_NEAR_PX = 2.0 ** 30


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

    ``orthomap`` may be a window of a map read by window (``database.DatabaseWindow``): ``image`` and ``nodata``
    are then the window's, and the level keeps the whole map's level grid (a ``SparseLayer`` filled over the
    window, equal there to the whole map's level bit for bit); a particle whose footprint leaves the filled part
    is an error (the estimator reads a new window before).
    """

    def __init__(self, orthomap, camera, geometry: PatchGeometry, image: np.ndarray, altitude_m: float, *,
                 nodata: np.ndarray | None = None, downsample: float | None = None) -> None:
        img = np.asarray(image)
        window = orthomap.box if isinstance(orthomap, DatabaseWindow) else None
        expected = (orthomap.height_px, orthomap.width_px) if window is None else \
            (window[3] - window[1], window[2] - window[0])
        if img.shape[:2] != expected:
            raise ConfigError(f"PatchSampler: database layer shape {img.shape[:2]} differs from the map's "
                              f"{'window ' if window else ''}{expected}")
        if img.ndim == 3 and img.shape[2] > 4:
            raise ConfigError(f"PatchSampler: at most 4 channels can be sampled at once, got {img.shape[2]}")
        self.orthomap = orthomap
        self.camera = camera
        self.geometry = geometry
        if downsample is None:
            # map pixels per patch sample at the nominal altitude (the box filter of reduce_image on the camera)
            step_m = camera.gsd_m(altitude_m) * camera.width_px / geometry.width_px
            downsample = max(1.0, step_m / max(orthomap.gsd_x_m, orthomap.gsd_y_m))
        h, w = orthomap.height_px, orthomap.width_px
        lw, lh = max(2, int(round(w / downsample))), max(2, int(round(h / downsample)))
        self.filled: tuple[int, int, int, int] | None = None     # a window's level pixels; None: all of them
        if lw * lh >= 2 ** 32:     # windowed or whole: the kernel's sample index is 32-bit
            raise MapError(f"PatchSampler: the level of map '{orthomap.name}' ({lw} x {lh} samples) exceeds the "
                           "kernel's 32-bit sample index; downsample it more (a coarser patch grid) or use a smaller "
                           "map")
        if window is not None:
            self._window_level(orthomap, img, nodata, (lw, lh))
        else:
            level = img.astype(np.float32)
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
            # the kernel reads channel planes (C, h, w): each channel's neighbours are adjacent floats
            self.planes = np.ascontiguousarray(np.moveaxis(self.level.reshape(lh, lw, -1), 2, 0))
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
        # the grid's points as the kernel takes them: (rows, cols) blocks of one grid row each
        gh, gw = geometry.height_px, geometry.width_px
        self.grid_points = (np.ascontiguousarray(np.broadcast_to(self._cols, (gh, gw))),
                            np.ascontiguousarray(np.broadcast_to(self._rows[:, None], (gh, gw))))

    def _window_level(self, window: DatabaseWindow, img: np.ndarray, nodata: np.ndarray | None,
                      size: tuple[int, int]) -> None:
        """The level of a window of a map read by window, on the whole map's level grid (see the class)."""
        lw, lh = size
        # NaN where the level averages no-data, as the whole map's; has_nan as there, whatever this window holds
        layer = window.level(img.astype(np.float32, copy=False), size, np.float32, planar=True, nan_on_nodata=True,
                             key=("PatchSampler", size, img.shape[2:]))
        self.has_nan = window.has_nodata
        self.planes = layer.array
        self.level = self.planes[0] if img.ndim == 2 else np.moveaxis(self.planes, 0, 2)
        self.filled = layer.box

    def _check_filled(self, cu: np.ndarray, cv: np.ndarray, active: np.ndarray) -> None:
        """A window's level: every active particle's footprint (its corners, a bilinear neighbour beyond) must lie
        in the filled part, or where the whole map's level holds nothing either (off the level)."""
        if self.filled is None or not active.any():
            return
        u0, v0, u1, v1 = self.filled
        lw, lh = self.level_size
        cu, cv = cu[active], cv[active]
        lo_u, hi_u = np.floor(cu.min(1)), np.floor(cu.max(1)) + 1
        lo_v, hi_v = np.floor(cv.min(1)), np.floor(cv.max(1)) + 1
        ok = (((lo_u >= u0) | (u0 == 0)) & ((hi_u < u1) | (u1 == lw)) & ((lo_v >= v0) | (v0 == 0))
              & ((hi_v < v1) | (v1 == lh)))
        if not ok.all():
            raise MapError(f"PatchSampler: {int((~ok).sum())} particle footprint(s) leave the database window read "
                           f"of map '{self.orthomap.name}' (level pixels {self.filled}); the estimator must read a "
                           "window covering every pose it scores")

    @property
    def channels(self) -> int:
        return self.planes.shape[0]

    def grid_to_level(self, states: np.ndarray, altitude_m: float) -> np.ndarray:
        """Affines (N, 2, 3): reduced-grid pixel -> stored-level pixel, from ``camera_to_map`` (eq. (3))."""
        states = _check_states(states)
        a = self.camera.camera_to_map(self.orthomap, states[:, 0], states[:, 1], states[:, 2], altitude_m)
        a3 = np.zeros((len(states), 3, 3))
        a3[:, :2] = a.reshape(-1, 2, 3)
        a3[:, 2, 2] = 1.0
        return (self._to_level @ a3 @ self._from_grid)[:, :2]

    def node_points(self, nodes: np.ndarray, block: int = 64) -> tuple[np.ndarray, np.ndarray]:
        """The grid nodes ``nodes`` (flat indices ``row * w + col``) as the kernel's point blocks (R, ``block``)
        float32 (cols, rows), the last block padded with the first node; node k is flat point k."""
        nodes = np.asarray(nodes, dtype=np.intp).ravel()
        gw = self.geometry.width_px
        nr = -(-nodes.size // block)
        padded = np.full(nr * block, nodes[0] if nodes.size else 0, np.intp)
        padded[:nodes.size] = nodes
        return (np.ascontiguousarray(self._cols[padded % gw].reshape(nr, block)),
                np.ascontiguousarray(self._rows[padded // gw].reshape(nr, block)))

    def _footprint_valid(self, e: np.ndarray) -> np.ndarray:
        """Footprint inside the level: an affine image of the grid has its extremes at the grid corners (the
        corner coordinates computed as the kernel computes every node's, so the same floats)."""
        cu, cv = self._corners(e)
        lw, lh = self.level_size
        return (cu.min(1) >= 0) & (cu.max(1) <= lw - 1) & (cv.min(1) >= 0) & (cv.max(1) <= lh - 1)

    def _corners(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        gh, gw = self.geometry.height_px, self.geometry.width_px
        return _node_coords(e, self._cols[[0, gw - 1, 0, gw - 1]], self._rows[[0, 0, gh - 1, gh - 1]])

    def sample(self, states: np.ndarray, altitude_m: float) -> tuple[np.ndarray, np.ndarray]:
        """Patches (N, h, w[, C]) float32 and validity (N,) bool (footprint inside the map, no no-data): every
        grid node's bilinear sample of the level (``cv2.remap``'s values; NaN outside the level)."""
        e = self.grid_to_level(states, altitude_m).astype(np.float32)
        n = e.shape[0]
        cols, rows = self.grid_points
        cu, cv = self._corners(e)
        near = np.isfinite(cu).all(1) & np.isfinite(cv).all(1) & (np.abs(cu) < _NEAR_PX).all(1) \
            & (np.abs(cv) < _NEAR_PX).all(1)
        self._check_filled(cu, cv, near)
        out = np.empty((n, self.channels) + cols.shape, np.float32)
        self._scan(e, cols, rows, near, self.channels, SAMPLE, samples=out)
        valid = self._footprint_valid(e)
        if self.has_nan:
            valid &= ~np.isnan(out.reshape(n, -1)).any(axis=1)
        patches = out[:, 0] if self.level.ndim == 2 else np.ascontiguousarray(np.moveaxis(out, 1, -1))
        return patches, valid

    def score(self, states: np.ndarray, altitude_m: float, mode: int, *, points=None, channels: int = 1,
              **inputs) -> tuple[np.ndarray, np.ndarray]:
        """Every particle's view scored in the kernel without materializing it (``patches_kernels.scan``'s
        ``mode`` and its inputs: ``ref``, ``shift``, ``ref_bins``, ``bins``, ``scale``, ``nlogn``, ``tests``,
        ``cam_bits``), at the grid or at ``points`` (``node_points``). Returns the statistics (N, 4) float64
        (rows of particles whose footprint leaves the level untouched) and that footprint validity (N,) bool."""
        cols, rows = self.grid_points if points is None else points
        self._check_score_inputs(cols, rows, mode, channels, **inputs)
        e = self.grid_to_level(states, altitude_m).astype(np.float32)
        valid = self._footprint_valid(e)
        if self.filled is not None:
            self._check_filled(*self._corners(e), valid)
        stats = np.zeros((e.shape[0], 4))
        self._scan(e, cols, rows, valid, channels, mode, stats=stats, **inputs)
        return stats, valid

    def _check_score_inputs(self, cols, rows, mode, channels, *, ref=None, ref_bins=None, bins=0, nlogn=None,
                            tests=None, cam_bits=None, **_) -> None:
        """The kernel indexes unchecked (``boundscheck=False``): a ``score`` input of the wrong shape or range
        would read or write out of bounds, so it is refused here."""
        def refuse(what: str) -> None:
            raise ConfigError(f"PatchSampler.score: {what}")

        cols, rows = np.asarray(cols), np.asarray(rows)
        if cols.ndim != 2 or rows.shape != cols.shape:
            refuse(f"points must be two (R, B) arrays of one shape, got {cols.shape} and {rows.shape}")
        if not 1 <= channels <= self.channels:
            refuse(f"channels = {channels} must be in [1, {self.channels}] (the level's)")
        if mode == MOMENTS:
            if ref is None or np.shape(ref) != cols.shape:
                refuse(f"MOMENTS needs ref of the points' shape {cols.shape}, got {np.shape(ref)}")
        elif mode == HISTOGRAM:
            if ref_bins is None or np.shape(ref_bins) != cols.shape:
                refuse(f"HISTOGRAM needs ref_bins of the points' shape {cols.shape}, got {np.shape(ref_bins)}")
            if bins < 1 or ref_bins.min() < 0 or ref_bins.max() >= bins:
                refuse(f"HISTOGRAM needs ref_bins in [0, bins) with bins >= 1, bins = {bins}")
            if nlogn is None or np.ndim(nlogn) != 1 or np.size(nlogn) <= cols.size:
                refuse(f"HISTOGRAM needs nlogn for the counts 0 .. {cols.size} (dense.nlogn_table)")
        elif mode == BRIEF:
            if tests is None or np.ndim(tests) != 2 or np.shape(tests)[1] != 3:
                refuse(f"BRIEF needs tests (T, 3), got {np.shape(tests)}")
            if cam_bits is None or np.shape(cam_bits) != (tests.shape[0],):
                refuse(f"BRIEF needs cam_bits ({tests.shape[0]},), got {np.shape(cam_bits)}")
            if tests.size and (tests.min() < 0 or tests.max() >= cols.size or tests[:, 2].max() >= channels):
                refuse(f"BRIEF tests must index the {cols.size} points and {channels} channels")
        else:
            refuse(f"mode = {mode!r} must be MOMENTS, HISTOGRAM or BRIEF (SAMPLE: use sample())")

    def _scan(self, e, cols, rows, active, channels, mode, *, ref=None, shift=0.0, ref_bins=None, bins=0,
              scale=0.0, nlogn=None, tests=None, cam_bits=None, samples=None, stats=None) -> None:
        """``patches_kernels.scan`` with every unused input an empty array of the used one's type (one compiled
        specialization serves every mode)."""
        kernels.scan(self.planes, e, cols, rows, active, int(channels), int(mode),
                     _EMPTY_F32_2D if ref is None else ref, float(shift),
                     _EMPTY_I32_2D if ref_bins is None else ref_bins, int(bins), np.float32(scale),
                     _EMPTY_F64 if nlogn is None else nlogn, _EMPTY_TESTS if tests is None else tests,
                     _EMPTY_BOOL if cam_bits is None else cam_bits,
                     _EMPTY_F32_4D if samples is None else samples, _EMPTY_STATS if stats is None else stats)


_EMPTY_F32_2D = np.zeros((0, 0), np.float32)
_EMPTY_I32_2D = np.zeros((0, 0), np.int32)
_EMPTY_F64 = np.zeros(0)
_EMPTY_TESTS = np.zeros((0, 3), np.int64)
_EMPTY_BOOL = np.zeros(0, np.bool_)
_EMPTY_F32_4D = np.zeros((0, 0, 0, 0), np.float32)
_EMPTY_STATS = np.zeros((0, 4))


def _node_coords(e: np.ndarray, cols: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Level-pixel coordinates (u, v), (N, M) float32, of the M grid nodes at (``cols[j]``, ``rows[j]``) under
    each particle's affine ``e`` (N, 2, 3): ``e_00 col + (e_01 row + e_02)``, the float32 sums the kernel
    computes for every node."""
    u = (e[:, 0, 0, None] * cols) + (e[:, 0, 1, None] * rows + e[:, 0, 2, None])
    v = (e[:, 1, 0, None] * cols) + (e[:, 1, 1, None] * rows + e[:, 1, 2, None])
    return u, v


def _check_states(states: np.ndarray) -> np.ndarray:
    s = np.asarray(states, dtype=np.float64)
    if s.ndim != 2 or s.shape[1] != 3:
        raise ConfigError(f"measurement model: states must have shape (N, 3) = [x_m, y_m, yaw_rad], got {s.shape}")
    return s
