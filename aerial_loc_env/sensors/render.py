"""Camera frames from the orthomap: one affine warp, then cast/cloud shadows, then photometric realism.

Why it is built this way:

- Geometry is ``CameraModel.camera_to_map`` (eq. (3)); the frame is ONE ``cv2.warpAffine`` with
  ``WARP_INVERSE_MAP`` from a level of a Gaussian pyramid of the map chosen so that a camera pixel covers about
  one pyramid pixel: no aliasing when the camera is coarser than the database (``pyrDown``'s 5-tap kernel
  removes the map's Nyquist frequency exactly).
- The estimators' "reconstructed camera image" (``database_patch``) goes through the same warp, so a perfect
  pose gives the same picture minus shadows and sensor effects.
- Footprints that leave the map or touch no-data are detected, never silently padded: strict mode raises
  ``FootprintError``; the non-strict path fills with black and flags the frame invalid.
- Cast shadows are static over an episode, so ``bake`` shades them into the map once per reset (over the box the
  episode's footprints stay in, the occlusion quantized into the alpha channel the RGBA warp carries anyway): a
  frame is then ONE warp of the pre-shaded map plus the photometry, instead of the map warp, a float occlusion
  warp and three shading passes. Shading before interpolation differs from shading after it only at shadow edges
  (tests/sensors/test_render_bake.py derives the bound). A frame warped from a coarser pyramid level takes the box
  baked at that level (made on first use), so every level is shaded before its interpolation. Cloud shadows drift
  and keep the per-frame path, and so do frames the bake cannot serve (a footprint leaving the box, a perspective
  or tilted view at level > 0). Such a frame with a shadow grid
  warps the map level and the grid inside its finishing pass (``render_kernels.level_finish``, row by row: bit for
  bit the two ``warpAffine`` calls and the float occlusion's shading, without a warped RGBA frame or a float
  occlusion frame in memory); the float occlusion is warped only if a caller reads it. After the warp a baked frame
  is one compiled pass (below) that also copies the alpha out (the quantized occlusion) and counts the shadowed pixels;
  the shadow mask and the float occlusion are made only if a caller reads them (the env and the estimators do
  not). The baked box's warp itself is done inside that pass (``render_kernels.warp_finish``, row by row: no warped
  RGBA frame in memory, and the box stays in cache between frames), bit for bit OpenCV's ``warpAffine``.
- Everything after the warp is ONE pass of a numba kernel (``sensors.render_kernels.finish``), uint8 in and uint8
  out, row by row while the row is in cache, the frame written into the warp's own memory: the shading of a
  per-frame float occlusion (``jit``: per-channel gains of the quantized occlusion, one
  multiply), gamma and the white-balance/exposure gains as one per-channel byte table composed per frame over
  the 256 levels (``tone_lut``: the OpenCV operations' arithmetic), vignetting by a precomputed uint8 gain, and
  sensor noise from a per-episode int16 bank of standard normals (fixed point, 2**-11) read at a random offset per
  frame, scaled by the read + shot noise sigma (int16 fixed point, 2**-8), added with saturation: within 2 grey
  levels of the float arithmetic (tests/sensors/test_render_photometry.py derives the bound) and bit-identical to the
  OpenCV passes it replaced (tests/sensors/test_render_kernel.py keeps them as the reference). A perspective or tilted
  view samples the baked box through its per-pixel maps inside the same pass, the maps made there a band of rows
  at a time and its facades shaded there too (``perspective_kernels.view_finish``, bit for bit the view's maps,
  ``cv2.remap`` and the facade gains). Motion blur and ``pre_sensor`` steps split the pass in two around them.
"""

from __future__ import annotations

import functools
import math
import sys
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import cv2
import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import rng as range_meta
from aerial_loc_env.errors import ConfigError, FootprintError
from aerial_loc_env.sensors.camera import CameraModel, Pose, apply_affine
from aerial_loc_env.sensors.perspective import (
    PerspectiveConfig,
    ReliefView,
    ViewMaps,
    ViewPlan,
    footprint_px,
    sample_grid,
    tilt_homography,
)

FootprintStatus = Literal["valid", "outside", "nodata"]
OcclusionSource = Any  # np.ndarray (map-sized float32) | world.shadows.ShadowGrid | world.shadows.CloudField

#: bumped when the frames change for the same inputs (env/fingerprint.py); 1: an episode's cast shadows are shaded
#: into the map at reset (``CameraRenderer.bake``), before the interpolation instead of after it
GENERATOR_VERSION = 1

_WARP_FLAGS = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
_RGBA_MAX_PX = 32_000_000  # maps up to this many pixels get an RGBA copy (faster warps; the default city: 27 Mpx)
_BAKE_TILE_PX = 128  # BakedShadows fills its box in tiles this size, as footprints first reach them
_BOX_POOL_BUFFERS = 4            # a renderer keeps at most this many freed boxes' buffers ...
_BOX_POOL_MAX_BYTES = 256 << 20  # ... holding at most this many bytes (larger ones are freed as before)
_NOISE_MARGIN_PX = 97  # the noise bank is this much larger than a frame in each direction (random offsets)
_BLOCK_PX = 16  # no-data screening block (map pixels)
_NOISE_BITS = 11  # the int16 noise bank holds round(z * 2**11), |z| <= 16
_SIGMA_BITS = 8   # the int16 sigma LUT holds round(sigma * 2**8); sigma <= 71.1 DN within Photometry's ranges


_LEVELS = np.repeat(np.arange(256, dtype=np.uint8)[None, :, None], 3, axis=2)  # (1, 256, 3): every level per channel
_UNIT_LEVELS = np.arange(256) / 255.0                                           # the levels in [0, 1] (float64)
_UNIT_GAINS = np.ones(3)                                                         # tone_lut's gains when none are drawn
_IDENTITY = np.ascontiguousarray(_LEVELS[0].T)                                   # (3, 256) identity tone table
_IDENTITY_RO = _IDENTITY.copy()
_IDENTITY_RO.flags.writeable = False   # the dummy shading table (shading LUTs are read-only: one kernel signature)
_NO_OCC = np.zeros((1, 1), np.float32)   # dummy arguments where the kernel reads nothing
_NO_VIG = np.zeros((1, 1), np.uint8)
_NO_BANK = np.zeros((1, 1), np.int16)
_BAKED_ALPHA = np.zeros((1, 1), np.float32)   # ``_finish``'s marker: the occlusion is src's (baked) alpha
_FRAME_KERNEL = __name__.rpartition(".")[0] + ".render_kernels"


def _kernels():
    """``sensors.render_kernels``, imported on first use (importing numba is slow: only processes that render pay)."""
    fk = sys.modules.get(_FRAME_KERNEL)
    if fk is None:   # the import statement's lookups cost more than the frame's other Python steps, cold
        from aerial_loc_env.sensors import render_kernels as fk
    return fk


@dataclass(frozen=True)
class Photometry:
    """Sensor and exposure effects that make camera frames differ from the database (all drawn per frame).

    Defaults are a small drone camera in daylight: +-8 % exposure, 2 % white balance, gamma 1 +- 0.05, about
    3 DN of noise at mid grey (read 2 DN, shot variance 0.05 DN per DN), half of the cos^4 vignetting, and a
    1/500 s exposure (motion blur only matters when ``speed * exposure_time`` reaches a pixel).
    """

    gain: float = field(default=1.0, metadata=range_meta(0.0, 10.0, lo_open=True, doc="mean exposure gain"))
    exposure_std: float = field(default=0.08, metadata=range_meta(0.0, 1.0, doc="per-frame log-gain std"))
    white_balance_std: float = field(default=0.02, metadata=range_meta(0.0, 0.5, doc="per-channel log-gain std"))
    gamma: float = field(default=1.0, metadata=range_meta(0.2, 5.0, doc="tone curve exponent vs the map"))
    gamma_std: float = field(default=0.05, metadata=range_meta(0.0, 1.0, doc="per-frame log-gamma std"))
    read_noise_dn: float = field(default=2.0, metadata=range_meta(0.0, 50.0, doc="signal-independent noise std"))
    shot_noise_gain: float = field(default=0.05, metadata=range_meta(0.0, 10.0, doc="shot variance per DN"))
    vignetting: float = field(default=0.5, metadata=range_meta(0.0, 1.0, doc="fraction of the cos^4 fall-off"))
    exposure_time_s: float = field(default=0.002, metadata=range_meta(0.0, 1.0, doc="motion blur exposure"))

    @classmethod
    def ideal(cls) -> Photometry:
        """No jitter, noise, vignetting or blur: frames equal the warped (and shaded) map."""
        return cls(exposure_std=0.0, white_balance_std=0.0, gamma_std=0.0, read_noise_dn=0.0,
                   shot_noise_gain=0.0, vignetting=0.0, exposure_time_s=0.0)

    @property
    def has_noise(self) -> bool:
        return self.read_noise_dn > 0.0 or self.shot_noise_gain > 0.0


@dataclass(frozen=True, eq=False, init=False)
class Frame:
    """One camera frame and its ground truth (the shadow mask is for oracles, reports and tests).

    ``occlusion`` is (H, W) float32 in [0, 1] in the camera frame, None without shadows. Frames from baked
    shadows carry it quantized (``occlusion_q``: the warped alpha, ``round(255 occ)``) and make the float32
    image on first read; frames whose pass warped a shadow grid itself carry how to warp it (``occlusion_of``,
    called on first read); ``shadow_mask`` (bool, True where the occlusion is >= 0.5, i.e. ``occlusion_q`` >= 128)
    is made from them on first read when not given: the env and the estimators never read them, so a frame costs
    no pass for them (``shadow_fraction`` is counted in the renderer's pass).
    """

    image: np.ndarray             # (H, W, 3) uint8
    shadow_fraction: float        # fraction of the frame in shadow
    valid: bool                   # the footprint lies inside the map and touches no no-data
    status: FootprintStatus
    pose: Pose
    pyramid_level: int = 0        # the map pyramid level the frame was warped from

    def __init__(self, image: np.ndarray, shadow_mask: np.ndarray | None, shadow_fraction: float, valid: bool,
                 status: FootprintStatus, pose: Pose, occlusion: np.ndarray | None = None, pyramid_level: int = 0,
                 *, occlusion_q: np.ndarray | None = None,
                 occlusion_of: Callable[[], np.ndarray] | None = None) -> None:
        if sum(o is not None for o in (occlusion, occlusion_q, occlusion_of)) > 1:
            raise ValueError("Frame: give one of occlusion, occlusion_q or occlusion_of")
        for name, value in (("image", image), ("_shadow_mask", shadow_mask), ("shadow_fraction", shadow_fraction),
                            ("valid", valid), ("status", status), ("pose", pose), ("pyramid_level", pyramid_level),
                            ("_occlusion", occlusion), ("occlusion_q", occlusion_q), ("_occlusion_of", occlusion_of)):
            object.__setattr__(self, name, value)

    @property
    def shadow_mask(self) -> np.ndarray:
        """(H, W) bool, True where the occlusion is >= 0.5."""
        if self._shadow_mask is None:
            if self.occlusion_q is not None:
                mask = self.occlusion_q > 127
            elif self.occlusion is not None:
                mask = self.occlusion >= 0.5
            else:
                mask = np.zeros(self.image.shape[:2], dtype=bool)
            object.__setattr__(self, "_shadow_mask", mask)
        return self._shadow_mask

    @property
    def occlusion(self) -> np.ndarray | None:
        if self._occlusion is None and self.occlusion_q is not None:
            object.__setattr__(self, "_occlusion", np.multiply(self.occlusion_q, np.float32(1.0 / 255.0),
                                                               dtype=np.float32))
        elif self._occlusion is None and self._occlusion_of is not None:
            object.__setattr__(self, "_occlusion", self._occlusion_of())
            object.__setattr__(self, "_occlusion_of", None)
        return self._occlusion


class _BoxPool:
    """The memory of an episode's freed boxes (``BakedShadows.rgba``), kept for the renderer's next boxes.

    A box is written once, a tile at a time, as the flight first reaches it: in fresh memory the first write to
    each page faults it in (a 4 KiB page per tile row, or a 2 MiB huge page where the kernel hands them out), which
    on a virtual machine can cost the frame that bakes the tile many times its shading. A box in a freed box's
    memory finds the pages the last flights touched committed. The bytes it held do not matter: a frame reads
    baked tiles only. At most ``_BOX_POOL_BUFFERS`` buffers and ``_BOX_POOL_MAX_BYTES`` bytes are kept; more are
    freed."""

    def __init__(self) -> None:
        self._free: list[np.ndarray] = []

    def take(self, shape: tuple[int, int, int]) -> np.ndarray:
        """A uint8 array of ``shape``: a view of the smallest free buffer that holds it, else new memory."""
        need = shape[0] * shape[1] * shape[2]
        # by identity, over a snapshot: a box collected by the cyclic GC during these lines gives its buffer back
        fits = [buf for buf in tuple(self._free) if buf.size >= need]
        if not fits:
            # the kept buffers go back to the allocator first (fresh memory is theirs, recycled, rather than memory
            # never touched, which a virtual machine's host may not have mapped yet); half again this box's size
            # (address space: pages are committed where written), so that later episodes' boxes fit; its base is
            # the flat buffer given back
            self._free.clear()
            return np.empty(need + need // 2, np.uint8)[:need].reshape(shape)
        buf = min(fits, key=lambda b: b.size)
        self._free[:] = [b for b in self._free if b is not buf]
        return buf[:need].reshape(shape)

    def give(self, array: np.ndarray) -> None:
        """Take back the memory of ``array`` (a box no longer used), keeping the largest buffers within the limits."""
        buf = array if array.base is None else array.base
        if buf.ndim != 1 or buf.nbytes > _BOX_POOL_MAX_BYTES:
            return
        self._free.append(buf)
        self._free.sort(key=lambda b: -b.size)
        while len(self._free) > _BOX_POOL_BUFFERS or sum(b.nbytes for b in self._free) > _BOX_POOL_MAX_BYTES:
            self._free.pop()

    def box(self, baked: BakedShadows) -> BakedShadows:
        """``baked``, its box's memory given back to the pool when it is no longer used."""
        weakref.finalize(baked, self.give, baked.rgba).atexit = False
        return baked


@dataclass(frozen=True, eq=False)
class BakedShadows:
    """An episode's cast shadows shaded into a box of the map (``CameraRenderer.bake``).

    A frame whose footprint lies in the box is ONE warp of ``rgba``: the shaded RGB, with the occlusion quantized
    to uint8 in the alpha channel (the channel the renderer warps anyway), so the per-frame occlusion warp and
    shading disappear. ``rgba`` is filled lazily in tiles of ``_BAKE_TILE_PX``, each the first time a footprint
    needs it: an episode shades the strip it flies over, not its whole bounding box, and its memory is either fresh
    (``np.empty``: tiles never touched are never committed) or a freed box's (``_BoxPool``: pages committed by
    earlier episodes). A tile's bytes do not depend on when it is baked. Perspective and tilted views sample it
    through their maps. Frames warped from a coarser pyramid level L (a flat, untilted view) take the same box at
    that level (``levels[L]``, made on first use: the level's pixels shaded with the grid at their centres), so
    that every level is shaded before it is interpolated. Frames that cannot use it (a footprint or a view's reads
    leaving the box, a perspective or tilted view at level > 0) render from ``grid`` and ``shading_params`` as
    before. The shading is applied before the interpolation instead of after it: the same
    bytes away from shadow edges up to rounding, and within the bound tests/sensors/test_render_bake.py derives at the
    edges; the shadow mask is the warped alpha >= 128.
    """

    grid: Any                         # world.shadows.ShadowGrid: the source
    shading_params: Mapping[str, Any]
    rgba: np.ndarray                  # (h, w, 4) uint8: shaded RGB, alpha = round(255 occlusion), where baked
    origin_px: tuple[int, int]        # (column, row) of rgba[0, 0] in the map's pixels at ``level``
    baked_tiles: np.ndarray           # (rows, columns) bool: the tiles of rgba filled so far
    done_range: list[int] = field(default_factory=lambda: [0, 0, 0, 0])  # (ty0, ty1, tx0, tx1) a frame found baked
    level: int = 0                    # the map pyramid level of ``rgba``'s pixels
    levels: dict[int, BakedShadows] = field(default_factory=dict)   # the same box at coarser levels, by level

    def covers(self, bounds_px: tuple[float, float, float, float]) -> bool:
        """Whether map points within ``bounds_px`` (u0, v0, u1, v1) lie in the box with the bilinear kernel's
        margin."""
        c0, r0 = self.origin_px
        h, w = self.rgba.shape[:2]
        u0, v0, u1, v1 = bounds_px
        return u0 >= c0 + 1.0 and v0 >= r0 + 1.0 and u1 <= c0 + w - 2.0 and v1 <= r0 + h - 2.0


@dataclass(frozen=True, eq=False)
class _BoxWarp:
    """The baked box's warp for a frame, done row by row inside the finishing pass (``render_kernels.warp_finish``:
    bit for bit ``cv2.warpAffine`` INTER_LINEAR | WARP_INVERSE_MAP with a zero border, without a warped frame going
    through memory between the warp and a separate pass). ``box``: the box's RGBA pixels as uint32 (h, w); ``matrix``:
    frame pixel -> box pixel, (2, 3) float64."""

    box: np.ndarray
    matrix: np.ndarray
    height_px: int
    width_px: int

    def finish(self, fk: Any, *args: Any) -> int:
        """``warp_finish`` of this warp with the finishing arguments ``args`` (lut, out, alpha, sensor ...)."""
        return fk.warp_finish(self.box, self.matrix, *args)


@dataclass(frozen=True, eq=False)
class _ViewWarp:
    """The baked box sampled through a planned view inside the finishing pass, the view's maps made a band at a time
    in the same pass (``ReliefView.finish_frame``, ``perspective_kernels.view_finish``: the frame of ``view_maps``
    then ``cv2.remap`` of the box through them, bit for bit, the facades shaded with ``facade_gains``)."""

    box: np.ndarray
    view: ReliefView
    plan: ViewPlan
    sun_deg: tuple[float, float] | None
    gamma: float
    height_px: int
    width_px: int

    def finish(self, fk: Any, *args: Any) -> int:
        """``view_finish`` of this view with the finishing arguments ``args``."""
        return self.view.finish_frame(self.plan, self.box, self.sun_deg, self.gamma, *args)


@dataclass(frozen=True, eq=False)
class _LevelWarp:
    """A map level's warp and the shadow grid's, done row by row inside the finishing pass
    (``render_kernels.level_finish``: bit for bit ``cv2.warpAffine`` of the level (zero border) and of the grid
    (replicated border), then the float occlusion's shading): the frames a bake does not serve. ``box``: the
    level's RGBA pixels as uint32 (h, w); ``matrix``: frame pixel -> level pixel; ``grid`` (float32) and
    ``grid_matrix``: the occlusion and frame pixel -> grid pixel; ``shade``: the shading LUT (``_shading_lut``)."""

    box: np.ndarray
    matrix: np.ndarray
    grid: np.ndarray
    grid_matrix: np.ndarray
    shade: np.ndarray
    height_px: int
    width_px: int

    def finish(self, fk: Any, lut: np.ndarray, out: np.ndarray, alpha: np.ndarray, *args: Any) -> int:
        """``level_finish`` of this warp with the finishing arguments (``alpha`` unused: the occlusion is float)."""
        return fk.level_finish(self.box, self.matrix, self.grid, self.grid_matrix, self.shade, self.height_px,
                               self.width_px, lut, out, *args)


@dataclass(frozen=True, eq=False)
class _SensorParams:
    """The renderer's fixed sensor arguments of ``render_kernels.finish``: the vignetting gains (uint8 over 255,
    (H, 3 W); all 255 when only noise is on) and how the noise sigma is computed. ``sigma_lut`` is the int16 sigma
    LUT ``rint(256 sqrt(r**2 + g v))`` (float64): the kernel computes it in float32 where that gives all 256
    values (checked here with the kernel's own arithmetic), else in float64, the LUT's own arithmetic."""

    active: bool               # vignetting or noise
    vig: np.ndarray
    sigma_mode: int
    a32: np.float32
    b32: np.float32
    a64: float
    b64: float
    sigma_lut: np.ndarray

    @classmethod
    def build(cls, camera: CameraModel, p: Photometry) -> _SensorParams:
        fk = _kernels()
        r2, g = p.read_noise_dn ** 2, p.shot_noise_gain
        sigma_lut = np.rint(np.sqrt(r2 + g * np.arange(256, dtype=np.float64)) * (1 << _SIGMA_BITS)).astype(np.int16)
        a32, b32 = np.float32(r2 * (1 << 2 * _SIGMA_BITS)), np.float32(g * (1 << 2 * _SIGMA_BITS))
        mode = fk.NOISE_OFF
        if p.has_noise:
            for mode in (fk.SIGMA_F32, fk.SIGMA_F64):
                if np.array_equal(fk.sigma_levels(mode, a32, b32, r2, g), sigma_lut):
                    break
            else:  # pragma: no cover - float64 is the LUT's own arithmetic
                raise AssertionError(f"render_kernels: no sigma arithmetic reproduces the sigma LUT of {p}")
        vignette = CameraRenderer._vignetting_map(camera, p.vignetting)
        if vignette is not None:
            vig = np.rint(vignette * 255.0).astype(np.uint8).reshape(camera.height_px, -1)
            half = (camera.height_px + 1) // 2
            if np.array_equal(vig, vig[::-1]):   # symmetric about the middle row: its top half (less to read)
                vig = np.ascontiguousarray(vig[:half])
        else:
            vig = np.full((camera.height_px, 3 * camera.width_px), 255, np.uint8) if p.has_noise else _NO_VIG
        return cls(vignette is not None or p.has_noise, vig, mode, a32, b32, float(r2), float(g), sigma_lut)


class CameraRenderer:
    """Renders camera frames (and shadow-free database patches) of an orthomap for given poses.

    ``orthomap`` needs ``rgb`` (H, W, 3) uint8, ``gsd_x_m``, ``gsd_y_m``, ``height_px``, ``width_px`` and
    optionally ``nodata`` (H, W) bool (the ``Orthomap`` contract). The map pyramid is built lazily, once per
    level. ``noise_seed`` seeds the first noise bank; call ``reset(rng)`` at each episode to redraw it.
    ``rgba``: keep a private RGBA copy of the map for faster warps (default: maps up to 32 Mpx).
    ``frame`` and ``origin_px``: ``orthomap`` is the window of a larger map read by window (``frame``, its geometry:
    gsd, size) whose pixel (0, 0) lies at ``origin_px`` of ``frame``; poses are in ``frame``'s world, and every
    affine is shifted by the origin (an integer translation) before it reaches the window's pixels.
    Not thread-safe (reused scratch buffers, lazily built pyramid): one renderer per thread or process.
    """

    def __init__(self, orthomap: Any, camera: CameraModel | None = None, photometry: Photometry | None = None,
                 *, strict: bool = True, noise_seed: int | np.random.Generator = 0,
                 rgba: bool | None = None, perspective: PerspectiveConfig | None = None, frame: Any = None,
                 origin_px: tuple[int, int] = (0, 0)) -> None:
        rgb = orthomap.rgb
        if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
            raise ConfigError(f"CameraRenderer: map '{getattr(orthomap, 'name', 'map')}' rgb must be (H, W, 3) "
                              f"uint8, got shape {rgb.shape} dtype {rgb.dtype}")
        self.orthomap = orthomap
        self.frame = orthomap if frame is None else frame
        self._origin = (int(origin_px[0]), int(origin_px[1])) if any(origin_px) else None
        self.camera = camera or CameraModel()
        self.photometry = photometry or Photometry()
        self.strict = strict
        # perspective view of the height model (sensors/perspective.py) when configured and the map has one;
        # a flat view serves tilted (gimbal jitter) frames of maps without one
        dsm = getattr(orthomap, "dsm_m", None)
        relief = perspective is not None and perspective.enabled and dsm is not None
        self._view = ReliefView(dsm if relief else None, perspective)
        # OpenCV's bilinear warp is about twice as fast on 4-channel pixels (same bytes per channel), so maps
        # up to _RGBA_MAX_PX get a private RGBA copy (4 bytes/px, not shared between processes like a
        # memory-mapped map); larger ones are warped as they are. Both give the same bytes.
        self._rgba = rgb.shape[0] * rgb.shape[1] <= _RGBA_MAX_PX if rgba is None else bool(rgba)
        self._levels: list[np.ndarray] = [cv2.cvtColor(rgb, cv2.COLOR_RGB2RGBA) if self._rgba else rgb]
        nodata = getattr(orthomap, "nodata", None)
        self._nodata_levels: list[np.ndarray] | None = None
        self._nodata_blocks: np.ndarray | None = None
        if nodata is not None and np.any(nodata):
            nd = np.where(np.asarray(nodata), np.uint8(255), np.uint8(0))
            self._nodata_levels = [nd]
            # integral image of "block has no-data" on a coarse grid: most footprints skip the mask warp
            padded = np.pad(nd, ((0, (-nd.shape[0]) % _BLOCK_PX), (0, (-nd.shape[1]) % _BLOCK_PX)))
            blocks = padded.reshape(padded.shape[0] // _BLOCK_PX, _BLOCK_PX, padded.shape[1] // _BLOCK_PX,
                                    _BLOCK_PX).max(axis=(1, 3))
            self._nodata_blocks = cv2.integral((blocks > 0).astype(np.uint8))
        self._noise_bank: np.ndarray | None = None
        self._boxes = _BoxPool()     # freed boxes' memory for the next episodes' (``bake``)
        self._affine_terms_of: tuple[Any, Any, float, tuple[float, ...]] = (None, None, math.nan, ())
        self._sensor = _SensorParams.build(self.camera, self.photometry)
        self.reset(noise_seed if isinstance(noise_seed, np.random.Generator) else np.random.default_rng(noise_seed))

    # ------------------------------------------------------------------ per-episode state
    def reset(self, rng: np.random.Generator) -> None:
        """Redraw the noise bank (once per episode) from ``rng``."""
        if self.photometry.has_noise:
            self._noise_bank = noise_bank(rng, self.camera)

    def bake(self, grid: Any, shading_params: Mapping[str, Any] | None,
             box_px: tuple[int, int, int, int]) -> BakedShadows | None:
        """Shade the cast shadows ``grid`` (a ``world.shadows.ShadowGrid``) into the map over ``box_px`` (column0,
        row0, column1, row1; level 0 map pixels, the region an episode's footprints stay in), once per episode
        (lazily: each tile when a frame first needs it).

        Returns None where baking does not apply: maps warped as RGB (no alpha channel to carry the occlusion).
        Perspective and tilted views sample the box through their per-pixel maps (the shadows lie in map
        coordinates, on the surfaces the view sees). Memory: at most one RGBA copy of the box (the tiles flown
        over), held by the returned object only; once it is freed, the renderer keeps that memory for its next
        boxes (``_BoxPool``: its pages stay committed, so later episodes' tiles fault none in)."""
        from aerial_loc_env.world.shadows import ShadowGrid

        if not self._rgba or not isinstance(grid, ShadowGrid):
            return None
        h, w = self.orthomap.rgb.shape[:2]
        c0, r0 = max(0, int(box_px[0]) - 2), max(0, int(box_px[1]) - 2)
        c1, r1 = min(w, int(box_px[2]) + 2), min(h, int(box_px[3]) + 2)
        if c1 <= c0 or r1 <= r0:
            raise ConfigError(f"CameraRenderer.bake: box_px = {box_px!r} holds no map pixel of the {w}x{h} map")
        self._grid(grid)                         # checks the grid against the map
        return self._new_box(grid, dict(shading_params or {}), (r1 - r0, c1 - c0), (c0, r0))

    def _new_box(self, grid: Any, shading_params: Mapping[str, Any], size_px: tuple[int, int],
                 origin_px: tuple[int, int], level: int = 0) -> BakedShadows:
        """A box of ``size_px`` (rows, columns) at ``origin_px`` of pyramid level ``level``, no tile shaded yet, in a
        freed box's memory where the renderer kept one (``_BoxPool``)."""
        h, w = size_px
        tiles = (-(-h // _BAKE_TILE_PX), -(-w // _BAKE_TILE_PX))
        return self._boxes.box(BakedShadows(grid, shading_params, self._boxes.take((h, w, 4)), origin_px,
                                            np.zeros(tiles, dtype=bool), level=level))

    def _baked_level(self, baked: BakedShadows, level: int) -> BakedShadows:
        """The level-0 box ``baked`` at pyramid level ``level`` > 0: the level's pixels over the level-0 box, with
        the bilinear kernel's margin, made on first use (no tile shaded yet)."""
        got = baked.levels.get(level)
        if got is None:
            s = 1 << level
            c0, r0 = baked.origin_px
            h, w = baked.rgba.shape[:2]
            lh, lw = self.map_level(level).shape[:2]
            lc0, lr0 = max(0, c0 // s - 2), max(0, r0 // s - 2)
            lc1, lr1 = min(lw, -(-(c0 + w) // s) + 2), min(lh, -(-(r0 + h) // s) + 2)
            got = self._new_box(baked.grid, baked.shading_params, (lr1 - lr0, lc1 - lc0), (lc0, lr0), level)
            baked.levels[level] = got
        return got

    def _bake_tiles(self, baked: BakedShadows, bounds_px: tuple[float, float, float, float]) -> None:
        """Shade the tiles of ``baked`` that the bilinear warp over map points within ``bounds_px`` (u0, v0, u1, v1;
        pixels of ``baked``'s level) reads, if not yet."""
        c0, r0 = baked.origin_px
        u0, v0, u1, v1 = bounds_px
        tx0 = max((math.floor(u0) - c0 - 1) // _BAKE_TILE_PX, 0)
        ty0 = max((math.floor(v0) - r0 - 1) // _BAKE_TILE_PX, 0)
        tx1 = (math.floor(u1) - c0 + 2) // _BAKE_TILE_PX + 1
        ty1 = (math.floor(v1) - r0 + 2) // _BAKE_TILE_PX + 1
        last = baked.done_range
        if last[0] <= ty0 and ty1 <= last[1] and last[2] <= tx0 and tx1 <= last[3]:
            return   # inside the range a frame found baked (tiles stay baked): no numpy call
        done = baked.baked_tiles[ty0:ty1, tx0:tx1]
        if done.all():
            baked.done_range[:] = (ty0, ty1, tx0, tx1)
            return
        from aerial_loc_env.world.shadows import shade

        data, f = self._grid(baked.grid)
        lut = _shading_lut(baked.shading_params)
        level_map = self.map_level(baked.level)
        h, w = baked.rgba.shape[:2]
        for ty, tx in zip(*np.nonzero(~done), strict=True):
            ty, tx = int(ty) + ty0, int(tx) + tx0
            y0, x0 = ty * _BAKE_TILE_PX, tx * _BAKE_TILE_PX
            y1, x1 = min(h, y0 + _BAKE_TILE_PX), min(w, x0 + _BAKE_TILE_PX)
            u0, v0 = c0 + x0, r0 + y0
            occ = _upsample_tile(data, f, u0, v0, x1 - x0, y1 - y0, 1 << baked.level)
            # the RGBA map tile (alpha 255) shaded as 4 channels: shaded RGB, alpha = occ_q, in one pass written
            # straight into the box
            shade(level_map[v0:v0 + y1 - y0, u0:u0 + x1 - x0], occ, lut, out=baked.rgba[y0:y1, x0:x1])
            baked.baked_tiles[ty, tx] = True

    # ------------------------------------------------------------------ geometry
    def camera_to_map(self, pose: Pose, camera: CameraModel | None = None) -> np.ndarray:
        """The (2, 3) affine camera pixel -> map pixel (level 0) for ``pose`` (the camera's ``affine_terms`` kept
        for the last altitude: a flight's altitude rarely changes, and they cost a frame a few NumPy calls)."""
        camera = camera or self.camera
        pose = _pose_tuple(pose)
        held_camera, held_map, held_alt, terms = self._affine_terms_of
        if held_camera is not camera or held_map is not self.frame or held_alt != pose[3]:
            terms = camera.affine_terms(self.frame, pose[3])
            self._affine_terms_of = (camera, self.frame, pose[3], terms)
        affine = camera.project_pose(self.frame, pose, terms)
        return affine if self._origin is None else self._to_window(affine)

    def _to_window(self, affine: np.ndarray) -> np.ndarray:
        """An affine to ``frame``'s pixels made one to the window's (its origin subtracted)."""
        affine[0, 2] -= self._origin[0]
        affine[1, 2] -= self._origin[1]
        return affine

    def pyramid_level(self, affine: np.ndarray) -> int:
        """The pyramid level whose pixels are closest to one camera pixel (log2 of the sampling step, rounded)."""
        (a00, a01, _), (a10, a11, _) = affine.tolist()
        step = max(math.hypot(a00, a10), math.hypot(a01, a11))
        return max(0, int(math.floor(math.log2(max(step, 1e-12)) + 0.5)))

    def footprint_status(self, pose: Pose, camera: CameraModel | None = None) -> FootprintStatus:
        """``"valid"``, ``"outside"`` (a footprint corner leaves the map) or ``"nodata"`` (touches no-data)."""
        camera = camera or self.camera
        affine = self.camera_to_map(pose, camera)
        return self._status(affine, self.pyramid_level(affine), camera)

    def _status(self, affine: np.ndarray, level: int, camera: CameraModel,
                corners_px: np.ndarray | None = None, map_corners: np.ndarray | None = None) -> FootprintStatus:
        """The footprint's status; ``map_corners``: the corners already in map pixels (else from ``corners_px``,
        by default the camera's)."""
        corners = apply_affine(affine, camera.corners_px() if corners_px is None else corners_px) \
            if map_corners is None else map_corners
        h, w = self.orthomap.rgb.shape[:2]
        tol = 1e-6
        us, vs = corners[:, 0].tolist(), corners[:, 1].tolist()      # 4 points: plain Python beats numpy here
        if min(us) < -0.5 - tol or min(vs) < -0.5 - tol or max(us) > w - 0.5 + tol or max(vs) > h - 0.5 + tol:
            return "outside"
        if self._nodata_levels is not None and self._blocks_touched(corners, level):
            nd = self._nodata_level(level)
            touched = cv2.warpAffine(nd, affine / (1 << level), (camera.width_px, camera.height_px),
                                     flags=_WARP_FLAGS, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            if cv2.countNonZero(touched):
                return "nodata"
        return "valid"

    def _blocks_touched(self, corners: np.ndarray, level: int) -> bool:
        """Whether the footprint's bounding box (grown by the pyramid kernel) meets a block with no-data."""
        assert self._nodata_blocks is not None
        grow = 3.0 * (1 << level)
        lo = np.floor((corners.min(axis=0) - grow) / _BLOCK_PX).astype(int)
        hi = np.floor((corners.max(axis=0) + grow) / _BLOCK_PX).astype(int) + 1
        nb_v, nb_u = self._nodata_blocks.shape[0] - 1, self._nodata_blocks.shape[1] - 1
        u0, v0 = max(lo[0], 0), max(lo[1], 0)
        u1, v1 = min(hi[0], nb_u), min(hi[1], nb_v)
        if u1 <= u0 or v1 <= v0:
            return False
        ii = self._nodata_blocks
        return bool(ii[v1, u1] - ii[v0, u1] - ii[v1, u0] + ii[v0, u0] > 0)

    def _check(self, pose: Pose, status: FootprintStatus, strict: bool, camera: CameraModel) -> None:
        if status == "valid" or not strict:
            return
        corners = camera.footprint_corners_m(*_pose_tuple(pose))
        om = self.orthomap
        width_m, height_m = om.rgb.shape[1] * om.gsd_x_m, om.rgb.shape[0] * om.gsd_y_m
        what = "leaves the map" if status == "outside" else "touches no-data pixels of the map"
        bounds = f"map bounds x in [0, {width_m:.1f}] m, y in [0, {height_m:.1f}] m"
        if self._origin is not None:   # a window of a map read by window
            om = self.frame
            x0 = self._origin[0] * om.gsd_x_m
            y0 = (om.height_px - self._origin[1]) * om.gsd_y_m - height_m
            what = what.replace("the map", "the window read of the map")
            bounds = f"window bounds x in [{x0:.1f}, {x0 + width_m:.1f}] m, y in [{y0:.1f}, {y0 + height_m:.1f}] m"
        radius = 0.5 * math.hypot(*camera.footprint_m(pose[3]))
        raise FootprintError(
            f"camera footprint {what} '{getattr(om, 'name', 'map')}': pose x_m={pose[0]:.2f}, y_m={pose[1]:.2f}, "
            f"yaw_rad={pose[2]:.4f}, altitude_m={pose[3]:.2f}; footprint x in [{corners[:, 0].min():.1f}, "
            f"{corners[:, 0].max():.1f}] m, y in [{corners[:, 1].min():.1f}, {corners[:, 1].max():.1f}] m; "
            f"{bounds}. Keep poses at least "
            f"{radius:.1f} m (half the footprint diagonal) inside valid map data, lower the altitude, or render "
            "with strict=False to get a frame flagged invalid")

    # ------------------------------------------------------------------ pyramids
    def map_level(self, level: int) -> np.ndarray:
        """Level ``level`` of the map's Gaussian pyramid (pixel ``u_L = u_0 / 2**L``), built on first use.

        RGBA (alpha unused) for maps up to 32 Mpx unless the constructor says otherwise, else RGB."""
        while len(self._levels) <= level:
            self._levels.append(cv2.pyrDown(np.ascontiguousarray(self._levels[-1])))
        return self._levels[level]

    def _nodata_level(self, level: int) -> np.ndarray:
        """Conservative no-data pyramid: a level pixel is no-data if any map pixel under pyrDown's 5x5 kernel is."""
        assert self._nodata_levels is not None
        kernel = np.ones((5, 5), np.uint8)
        while len(self._nodata_levels) <= level:
            self._nodata_levels.append(cv2.dilate(self._nodata_levels[-1], kernel)[::2, ::2].copy())
        return self._nodata_levels[level]

    # ------------------------------------------------------------------ rendering
    def database_patch(self, pose: Pose, size: tuple[int, int] | None = None, *, strict: bool = False) -> np.ndarray:
        """The reconstructed camera image from the database: no shadows, no sensor effects (uint8 (h, w, 3)).

        ``size=(width_px, height_px)`` renders the same footprint at another resolution. Outside the map the
        patch is black; ``strict=True`` raises ``FootprintError`` instead (see ``footprint_status``).
        """
        camera = self.camera if size is None else self.camera.resized(int(size[0]), int(size[1]))
        affine = self.camera_to_map(pose, camera)
        level = self.pyramid_level(affine)
        if strict:
            self._check(pose, self._status(affine, level, camera), True, camera)
        return self._warp(affine, level, camera)

    def warp_map(self, image_to_map: np.ndarray, size: tuple[int, int]) -> np.ndarray:
        """Any view of the map: ``image_to_map`` (2, 3) maps output pixels to map pixels (level 0, of ``frame``);
        the pyramid level is chosen as for camera frames (no aliasing). Returns RGB uint8 ``(size[1], size[0], 3)``,
        black outside the map or the window (no footprint checks: for overviews and debugging views)."""
        affine = np.asarray(image_to_map, dtype=np.float64)
        if affine.shape != (2, 3) or not np.isfinite(affine).all():
            raise ConfigError(f"warp_map: image_to_map must be a finite 2x3 affine, got shape {affine.shape}")
        w, h = int(size[0]), int(size[1])
        if self._origin is not None:
            affine = self._to_window(affine.copy())
        return self._warp_level(affine, self.pyramid_level(affine), w, h)

    def _warp(self, affine: np.ndarray, level: int, camera: CameraModel) -> np.ndarray:
        return self._warp_level(affine, level, camera.width_px, camera.height_px)

    def _warp_level(self, affine: np.ndarray, level: int, w: int, h: int) -> np.ndarray:
        out = self._warp_raw(affine, level, w, h)
        return cv2.cvtColor(out, cv2.COLOR_RGBA2RGB) if self._rgba else out

    def _warp_raw(self, affine: np.ndarray, level: int, w: int, h: int) -> np.ndarray:
        """The warp of pyramid level ``level`` as the map is held: RGBA (alpha 255) or RGB."""
        return cv2.warpAffine(self.map_level(level), affine / (1 << level), (w, h),
                              flags=_WARP_FLAGS, borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))

    def occlusion_in_camera(self, occlusion: OcclusionSource | Sequence[OcclusionSource], pose: Pose, *,
                            t_s: float = 0.0, camera: CameraModel | None = None) -> np.ndarray:
        """The occlusion (float32 (h, w) in [0, 1], 1 = no direct sun) the camera sees at ``pose``.

        Sources: a map-sized (H, W) float32 array, a ``world.shadows.ShadowGrid`` (coarse grid, pixel ``c``
        covers map pixels ``[c f, (c + 1) f)``), a ``world.shadows.CloudField`` (sampled at ``t_s``), or a
        sequence of them (independent occluders: visible fractions multiply). Each is one ``warpAffine``.
        """
        camera = camera or self.camera
        return self._occlusion(occlusion, self.camera_to_map(pose, camera), pose, t_s, camera)

    def _occlusion(self, occlusion: Any, affine: np.ndarray, pose: Pose, t_s: float,
                   camera: CameraModel, view: ViewMaps | None = None) -> np.ndarray:
        from aerial_loc_env.world import shadows  # layer 1, imported late: the geometry works without it

        size = (camera.width_px, camera.height_px)
        if isinstance(occlusion, (list, tuple)) and not isinstance(occlusion, shadows.ShadowGrid):
            if not occlusion:
                raise ConfigError("render: the occlusion sequence is empty; pass None for no shadows")
            fields = [self._occlusion(o, affine, pose, t_s, camera, view) for o in occlusion]
            return fields[0] if len(fields) == 1 else shadows.combine_occlusion(*fields)
        if isinstance(occlusion, shadows.CloudField):
            to_world = camera.camera_to_world(*_pose_tuple(pose))
            return occlusion.occlusion_image(t_s, to_world, (camera.height_px, camera.width_px))
        data, factor = self._grid(occlusion)
        if view is not None:  # shadows lie on the surfaces the perspective view sees
            return sample_grid(view, data, factor)
        return cv2.warpAffine(data, _to_grid(affine, factor), size, flags=_WARP_FLAGS,
                              borderMode=cv2.BORDER_REPLICATE)

    def _grid(self, occlusion: Any) -> tuple[np.ndarray, int]:
        """The (data, map px per cell) of a ShadowGrid or map-sized array, checked against the map."""
        from aerial_loc_env.world import shadows

        if isinstance(occlusion, shadows.ShadowGrid):
            data, factor = occlusion.data, int(occlusion.factor)
        elif isinstance(occlusion, np.ndarray):
            data, factor = occlusion, 1
        else:
            raise ConfigError(f"render: occlusion must be a map-sized float32 array, a ShadowGrid, a CloudField, "
                              f"a BakedShadows or a sequence of them, got {type(occlusion).__name__}")
        h, w = self.orthomap.rgb.shape[:2]
        expected = (-(-h // factor), -(-w // factor))
        if data.shape != expected or data.dtype != np.float32:
            raise ConfigError(f"render: occlusion grid must be float32 of shape {expected} (the map {h}x{w} "
                              f"px at {factor} map px per cell), got {data.dtype} {data.shape}")
        return data, factor

    def render(self, pose: Pose, rng: np.random.Generator,
               occlusion: OcclusionSource | Sequence[OcclusionSource] | None = None,
               shading_params: Mapping[str, Any] | None = None, *, t_s: float = 0.0, speed_mps: float = 0.0,
               strict: bool | None = None, tilt_rad: tuple[float, float] = (0.0, 0.0),
               pre_sensor: Callable[[np.ndarray], np.ndarray] | None = None,
               sun_deg: tuple[float, float] | None = None) -> Frame:
        """Render the camera frame at ``pose``: map warp, shadows (if ``occlusion``), then photometry.

        ``occlusion``: see ``occlusion_in_camera`` (``t_s`` is the time for cloud fields), or a ``BakedShadows``
        from ``bake`` (which brings its own shading parameters; ``shading_params`` is ignored). ``shading_params``
        are the keyword arguments of ``world.shadows.apply_shading`` (``strength`` defaults to 1), e.g.
        ``{"strength": cfg.draw_strength(rng), **cfg.shading_kwargs()}`` for a ``ShadowConfig``.
        ``speed_mps`` sets the motion blur length (``speed * exposure_time`` along the heading).
        ``tilt_rad``: the gimbal's (roll, pitch) error; with it, or with a perspective view of the height model,
        the frame is one ``remap`` through per-pixel maps (``sensors.perspective``) instead of the affine warp.
        ``pre_sensor``: scene-side effects (haze, exposure control) on the shaded image before the photometry
        (which then works in place on the uint8 image it returns). ``sun_deg`` (azimuth, elevation): the sun
        that lights the facades of a perspective view (without it they are a fixed fraction of the roof).
        """
        pose = Pose(*_pose_tuple(pose))
        strict = self.strict if strict is None else strict
        camera = self.camera
        affine = self.camera_to_map(pose, camera)
        level = self.pyramid_level(affine)
        tilt = tilt_homography(camera, *tilt_rad) if any(tilt_rad) else None
        # the footprint's corners, once a frame (the status, the box's cover and the view's window use them)
        footprint = footprint_px(affine, camera, tilt)
        status = self._status(affine, level, camera, map_corners=footprint)
        self._check(pose, status, strict, camera)
        # a flat, untilted view needs no per-pixel maps (the affine warp is exact): skip their two float passes
        flat = tilt is None and self._view.dsm is None
        baked = occlusion if isinstance(occlusion, BakedShadows) else None
        if baked is not None:
            occlusion, shading_params = baked.grid, baked.shading_params
            reads = self._view.reads_bounds_px(footprint)     # the bounds of the map points the frame reads
            if level > 0 and not flat:
                baked = None        # views' maps are made at level 0
            elif level != baked.level:  # a flat view warps the box baked at its level
                baked = self._baked_level(baked, level) if baked.level == 0 else None
            if baked is not None:
                reads = tuple(r / (1 << level) for r in reads) if level else reads
                baked = baked if baked.covers(reads) else None
        # a view's maps come in the baked box's pixels when it serves the frame (no shift of the maps to sample it)
        plan = None if flat else self._view.plan(
            affine, pose.altitude_m, camera, tilt, (0, 0) if baked is None else baked.origin_px, footprint)
        if baked is not None:
            self._bake_tiles(baked, reads)
            return self._render_baked(baked, affine, pose, rng, speed_mps, status, pre_sensor, plan, sun_deg)
        view = None if plan is None else self._view.view_of(plan)
        if view is None:
            warp = self._level_warp(occlusion, shading_params, affine, level, camera)
            if warp is not None:
                image, _, count = self._finish(warp, None, shading_params, rng, speed_mps, pose,
                                               [] if pre_sensor is None else [pre_sensor])
                grid = occlusion     # the float occlusion, warped as the per-frame path warps it, if a caller reads it
                return Frame(image=image, shadow_mask=None, shadow_fraction=count / (warp.width_px * warp.height_px),
                             valid=status == "valid", status=status, pose=pose, pyramid_level=level,
                             occlusion_of=functools.partial(_contiguous_occlusion, self, grid, affine, pose, t_s,
                                                            camera))
            image = self._warp_raw(affine, level, camera.width_px, camera.height_px)
        else:
            image = view.sample(self.map_level(level), level)
            image = cv2.cvtColor(image, cv2.COLOR_RGBA2RGB) if self._rgba else image
            self._view.shade_facades(image, view, sun_deg, float((shading_params or {}).get("gamma", 2.2)))
        occ_cam = None
        if occlusion is not None:
            occ_cam = np.ascontiguousarray(self._occlusion(occlusion, affine, pose, t_s, camera, view))
        image, _, count = self._finish(image, occ_cam, shading_params, rng, speed_mps, pose,
                                       [] if pre_sensor is None else [pre_sensor])
        return Frame(image=image, shadow_mask=None, shadow_fraction=count / (camera.width_px * camera.height_px),
                     valid=status == "valid", status=status, pose=pose, occlusion=occ_cam, pyramid_level=level)

    def _level_warp(self, occlusion: Any, shading_params: Mapping[str, Any] | None, affine: np.ndarray, level: int,
                    camera: CameraModel) -> _LevelWarp | None:
        """The frame's warp of map level ``level`` and of the shadow grid ``occlusion`` for the finishing pass, or
        None where the pass does not take it (an RGB-held map, no occlusion, a cloud field or several occluders):
        the same matrices as ``_warp_raw`` and ``_occlusion``."""
        from aerial_loc_env.world.shadows import ShadowGrid  # layer 1, imported late (as in ``_occlusion``)

        if not self._rgba or not isinstance(occlusion, (ShadowGrid, np.ndarray)):
            return None
        data, factor = self._grid(occlusion)
        rgba = self.map_level(level)
        if rgba.shape[0] * rgba.shape[1] >= 1 << 32:    # (the pass indexes the level with uint32)
            return None
        box = rgba.view(np.uint32).reshape(rgba.shape[:2])
        return _LevelWarp(box, affine / (1 << level), np.ascontiguousarray(data), _to_grid(affine, factor),
                          _shading_lut(shading_params), camera.height_px, camera.width_px)

    def _render_baked(self, baked: BakedShadows, affine: np.ndarray, pose: Pose, rng: np.random.Generator,
                      speed_mps: float, status: FootprintStatus,
                      pre_sensor: Callable[[np.ndarray], np.ndarray] | None, plan: ViewPlan | None = None,
                      sun_deg: tuple[float, float] | None = None) -> Frame:
        """One warp of the pre-shaded box: RGB and the occlusion (alpha) together, inside the finishing pass
        (``_BoxWarp``). ``plan``: a perspective or tilted view, planned in the box's pixels, samples the box through
        its maps instead, the maps made and its facades shaded in the same pass (``_ViewWarp``). The passes index the
        box with uint32: a box is part of a map with an RGBA copy (``_RGBA_MAX_PX`` unless forced), far below 2**32
        pixels."""
        camera = self.camera
        h, w = baked.rgba.shape[:2]
        box = baked.rgba.view(np.uint32).reshape(h, w)
        out: _BoxWarp | _ViewWarp
        if plan is None:
            a = affine / (1 << baked.level)     # frame pixel -> the level's pixel (exact: a power of two)
            a[0, 2] -= baked.origin_px[0]
            a[1, 2] -= baked.origin_px[1]
            out = _BoxWarp(box, a, camera.height_px, camera.width_px)
        else:
            out = _ViewWarp(box, self._view, plan, sun_deg, float(baked.shading_params.get("gamma", 2.2)),
                            camera.height_px, camera.width_px)
        mid = [] if pre_sensor is None else [pre_sensor]
        image, alpha, count = self._finish(out, _BAKED_ALPHA, None, rng, speed_mps, pose, mid)
        return Frame(image=image, shadow_mask=None, shadow_fraction=count / alpha.size, valid=status == "valid",
                     status=status, pose=pose, pyramid_level=baked.level, occlusion_q=alpha)

    # ------------------------------------------------------------------ photometry
    def _finish(self, src: np.ndarray | _BoxWarp | _ViewWarp | _LevelWarp, occ: np.ndarray | None,
                shading_params: Mapping[str, Any] | None, rng: np.random.Generator, speed_mps: float, pose: Pose,
                mid: list[Callable[[np.ndarray], np.ndarray]]) -> tuple[np.ndarray, np.ndarray, int]:
        """The frame from the warped map ``src`` (a fresh (H, W, 3 or 4) uint8 array, which becomes the frame's
        memory), or the baked box's warp to do in the first pass (``_BoxWarp``, ``_ViewWarp``, with ``_BAKED_ALPHA``):
        shadows, motion blur, gamma, gains, vignetting, noise (``render_kernels.finish``, ``warp_finish``,
        ``view_finish``); returns (image,
        the alpha (H, W) with ``_BAKED_ALPHA`` else a dummy, the shadowed pixel count).

        ``occ``: the float occlusion to shade with ``shading_params``, or ``_BAKED_ALPHA`` (src's alpha, already
        shaded), or None. ``mid``: scene-side steps on the shaded RGB image before the sensor (facades, exposure):
        with them or with motion blur, the pass is split in two around them. The random draws and their order:
        ``photometry_draws``, then the noise bank offsets."""
        fk = _kernels()
        p = self.photometry
        warp = src if isinstance(src, (_BoxWarp, _ViewWarp, _LevelWarp)) else None
        if warp is not None:   # the warp is done in the first pass, into the frame's memory
            h, w, cn = warp.height_px, warp.width_px, 4
            src = np.empty((h, w, 3), np.uint8)
        else:
            h, w, cn = src.shape
        alpha = _NO_VIG
        if occ is None:
            occ_mode, occ_f, shade = fk.OCC_NONE, _NO_OCC, _IDENTITY_RO
        elif occ is _BAKED_ALPHA:
            occ_mode, occ_f, shade, alpha = fk.OCC_ALPHA, _NO_OCC, _IDENTITY_RO, np.empty((h, w), np.uint8)
        else:
            occ_mode, occ_f, shade = fk.OCC_FLOAT, occ, _shading_lut(shading_params)
        camera = self.camera
        blur_px = speed_mps * p.exposure_time_s / (camera.gsd_m(pose.altitude_m) * camera.pixel_aspect)
        sp = self._sensor
        count = 0
        if mid or blur_px >= 1.0:   # the scene stage alone, the steps between, then the rest in place
            if warp is not None:
                count = warp.finish(fk, _IDENTITY, src.reshape(-1), alpha, False, _NO_VIG, _NO_BANK, 0, 0,
                                    fk.NOISE_OFF, sp.a32, sp.b32, sp.a64, sp.b64)
                warp = None
            else:
                count = fk.finish(src.reshape(h, w * cn), cn, occ_mode, occ_f, shade, _IDENTITY, src.reshape(-1),
                                  alpha, False, _NO_VIG, _NO_BANK, 0, 0, fk.NOISE_OFF, sp.a32, sp.b32, sp.a64, sp.b64)
            src = src.reshape(-1)[:h * w * 3].reshape(h, w, 3)
            for step in mid:
                src = np.ascontiguousarray(step(src))
                if src.dtype != np.uint8 or src.shape != (h, w, 3):   # the kernel indexes tables by its bytes
                    raise ConfigError(f"render: pre_sensor must return the ({h}, {w}, 3) uint8 image, got "
                                      f"{src.shape} {src.dtype}")
            if blur_px >= 1.0:
                src = cv2.filter2D(src, -1, _motion_kernel(blur_px), borderType=cv2.BORDER_REPLICATE)
            cn, occ_mode = 3, fk.OCC_NONE
        lut = tone_lut(*photometry_draws(p, rng))
        bank, dy, dx = _NO_BANK, 0, 0
        if p.has_noise:
            assert self._noise_bank is not None
            dy, dx = rng.integers(0, _NOISE_MARGIN_PX + 1, size=2).tolist()
            bank = self._noise_bank.reshape(self._noise_bank.shape[0], -1)
        flat = src.reshape(-1)
        if warp is not None:
            count += warp.finish(fk, lut, flat, alpha, sp.active, sp.vig, bank, dy, 3 * dx, sp.sigma_mode, sp.a32,
                                 sp.b32, sp.a64, sp.b64)
        else:
            count += fk.finish(src.reshape(h, w * cn), cn, occ_mode, occ_f, shade, lut, flat, alpha, sp.active,
                               sp.vig, bank, dy, 3 * dx, sp.sigma_mode, sp.a32, sp.b32, sp.a64, sp.b64)
        return flat[:h * w * 3].reshape(h, w, 3), alpha, count

    @staticmethod
    def _vignetting_map(camera: CameraModel, strength: float) -> np.ndarray | None:
        """Per-pixel gain ``1 - strength * (1 - cos^4 theta)``, theta the off-axis angle of the pixel."""
        if strength <= 0.0:
            return None
        f_px = (camera.width_px / 2.0) / math.tan(math.radians(camera.hfov_deg) / 2.0)
        cu, cv = camera.center_px
        u = (np.arange(camera.width_px, dtype=np.float32) - cu)[None, :]
        v = (np.arange(camera.height_px, dtype=np.float32) - cv)[:, None] * camera.pixel_aspect
        cos2 = f_px ** 2 / (f_px ** 2 + u ** 2 + v ** 2)
        gain = (1.0 - strength * (1.0 - cos2 ** 2)).astype(np.float32)
        return cv2.merge([gain, gain, gain])


def _to_grid(affine: np.ndarray, factor: int) -> np.ndarray:
    """Frame pixel -> shadow-grid pixel from the frame -> map ``affine``: map pixel u -> grid pixel
    (u + 0.5) / factor - 0.5."""
    a = affine / factor
    a[:, 2] += 0.5 / factor - 0.5
    return a


def _contiguous_occlusion(renderer: CameraRenderer, *args: Any) -> np.ndarray:
    """A frame's float occlusion computed on first read (a module-level function, so that a frame, and an env
    holding it, pickles)."""
    return np.ascontiguousarray(renderer._occlusion(*args))


def _shading_lut(shading_params: Mapping[str, Any] | None) -> np.ndarray:
    """``world.shadows.shading_lut`` of render's ``shading_params`` (``strength`` defaults to 1)."""
    from aerial_loc_env.world.shadows import shading_lut

    kwargs = dict(shading_params or {})
    strength = float(kwargs.pop("strength", 1.0))
    if "sky_tint_rgb" in kwargs:
        kwargs["sky_tint_rgb"] = tuple(float(t) for t in kwargs["sky_tint_rgb"])
    return shading_lut(strength, **kwargs)


def _upsample_tile(data: np.ndarray, f: int, u0: int, v0: int, w: int, h: int, scale: int = 1) -> np.ndarray:
    """The occlusion grid ``data`` (``f`` map px per cell) bilinearly at the pixels [u0, u0 + w) x [v0, v0 + h) of a
    map level ``scale`` level-0 pixels apart (its pixel x at level-0 pixel ``scale x``, as ``pyrDown`` and the
    warps place it; level-0 pixel u -> grid pixel (u + 0.5) / f - 0.5, as in the per-frame warp; the grid's edges
    replicated).

    For level 0 and f a power of two up to 32 the warp's 1/32 px coordinate quantization is exact and so is
    resize's (u + 0.5) / f - 0.5: a ``cv2.resize`` of the grid block under the tile gives the same floats as the
    warp, and is faster (tests/sensors/test_render_bake.py checks them bit for bit); the rest take the warp."""
    if f & (f - 1) or f > 32 or scale != 1:
        a = np.array([[scale / f, 0.0, (scale * u0 + 0.5) / f - 0.5], [0.0, scale / f, (scale * v0 + 0.5) / f - 0.5]])
        return cv2.warpAffine(data, a, (w, h), flags=_WARP_FLAGS, borderMode=cv2.BORDER_REPLICATE)
    gh, gw = data.shape
    # the grid cells the tile's bilinear taps read, one more on each side (resize replicates the block's edges,
    # which must be the grid's own edges or lie outside the taps)
    i0, j0 = max(v0 // f - 1, 0), max(u0 // f - 1, 0)
    i1, j1 = min((v0 + h - 1) // f + 2, gh), min((u0 + w - 1) // f + 2, gw)
    block = cv2.resize(data[i0:i1, j0:j1], ((j1 - j0) * f, (i1 - i0) * f), interpolation=cv2.INTER_LINEAR)
    return block[v0 - i0 * f:v0 - i0 * f + h, u0 - j0 * f:u0 - j0 * f + w]


def _motion_kernel(length_px: float) -> np.ndarray:
    """Vertical box kernel of fractional length (image rows = along the heading), normalized to 1."""
    half = length_px / 2.0
    n = 2 * int(math.ceil(half - 0.5)) + 1
    centres = np.arange(n) - n // 2
    weights = np.clip(np.minimum(centres + 0.5, half) - np.maximum(centres - 0.5, -half), 0.0, None)
    return (weights / weights.sum()).astype(np.float32).reshape(n, 1)


def _pose_tuple(pose: Any) -> tuple[float, float, float, float]:
    try:
        x, y, yaw, alt = (float(v) for v in pose)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"render: pose must be (x_m, y_m, yaw_rad, altitude_m), got {pose!r}") from exc
    if not all(math.isfinite(v) for v in (x, y, yaw, alt)):
        raise ConfigError(f"render: pose values must be finite, got {pose!r}")
    return x, y, yaw, alt


def photometry_draws(p: Photometry, rng: np.random.Generator) -> tuple[float | None, np.ndarray | None]:
    """The frame's gamma and per-channel gains (None where the photometry has no such effect), drawn in this order
    from ``rng``; the noise bank offsets are drawn after them."""
    gamma = gains = None
    if p.gamma != 1.0 or p.gamma_std > 0.0:
        gamma = p.gamma * math.exp(p.gamma_std * rng.standard_normal())
    if p.gain != 1.0 or p.exposure_std > 0.0 or p.white_balance_std > 0.0:
        # gain exp(e + s w_c) per channel in Python floats: NumPy's float64 operations and libm's exp (``portable``)
        exposure = p.exposure_std * rng.standard_normal()
        gains = np.array([p.gain * math.exp(exposure + p.white_balance_std * w)
                          for w in rng.standard_normal(3).tolist()])
    return gamma, gains


def gamma_lut(gamma: float) -> np.ndarray:
    """uint8 tone curve ``round(255 (v / 255) ** gamma)``."""
    return np.rint(255.0 * portable.power(_UNIT_LEVELS, gamma)).astype(np.uint8)


def tone_lut(gamma: float | None, gains: np.ndarray | None) -> np.ndarray:
    """The frame's tone curve then per-channel gains as one (3, 256) uint8 table (row c: channel c's output at
    each input level): what ``cv2.LUT`` of ``gamma_lut`` then a diagonal float32 ``cv2.transform`` (saturating) do
    to the 256 levels, the curve and the gains computed in one compiled call (``render_kernels.tone_table``: that
    arithmetic instead of five OpenCV/NumPy calls; tests/sensors/test_render_geometry.py compares it with the OpenCV
    operations)."""
    if gamma is None and gains is None:
        return _IDENTITY
    out = np.empty((3, 256), np.uint8)
    _kernels().tone_table(_UNIT_LEVELS, math.nan if gamma is None else float(gamma),
                          _UNIT_GAINS if gains is None else np.asarray(gains, dtype=np.float64), out)
    return out


def noise_bank(rng: np.random.Generator, camera: CameraModel) -> np.ndarray:
    """A frame-plus-margin of standard normals (one ``standard_normal`` float32 draw) in int16 fixed point,
    ``round(z * 2**_NOISE_BITS)`` (resolution 0.0005 sigma; |z| > 16, p < 1e-57, would clip)."""
    h, w = camera.height_px + _NOISE_MARGIN_PX, camera.width_px + _NOISE_MARGIN_PX
    z = rng.standard_normal((h, w, 3), dtype=np.float32)
    np.multiply(z, np.float32(1 << _NOISE_BITS), out=z)
    np.rint(z, out=z)
    np.clip(z, -32767, 32767, out=z)
    return z.astype(np.int16)
