"""A pinhole camera's view of the height model: relief displacement, facades and occlusion.

Why: one affine warp of the orthomap shows every roof on its own ground footprint. A real camera at height ``H``
sees a point at height ``h`` and ground distance ``r`` from nadir at ``r H / (H - h)``, i.e. displaced outward by
``r h / (H - h)``; it sees the facades that face the nadir point, and not the ground behind tall buildings. Real
maps without a height model keep the affine warp (``render.py``).

How (inverse mapping; compiled kernels in ``perspective_kernels.py``): the ray of camera pixel ``q`` meets the
ground at ``g0(q)`` and crosses height ``z`` at ``m(z) = g0 + (c - g0) z / H`` (``c`` the nadir point): it moves
towards nadir as it rises, so every point the camera can see lies inside the ground footprint. The visible point
is the ray's first intersection from above, the largest ``z`` with ``h(m(z)) >= z``.

1. March: one ray per 4 x 4 block of camera pixels (its centre's). For ``N`` heights ``z_i`` from the
   footprint's tallest point down, the points ``m(z_i)`` of these rays are the blocks' ground points scaled by
   ``1 - z_i / H`` about nadir: an affine image of the block grid (projective for a tilted camera), read
   (nearest) on the height model's 4 x 4 block maximum (a contiguous copy of the window under the footprint).
   Each cell stops at its first hit from the top, the highest ``z_i`` at which its ray is at or below the
   surface (to within one step); z0 is the hits' maximum over the cell and its 8 neighbours (no roof edge is
   lost to the coarse grid; the next step verifies). Each block's pixels start from its z0.
2. Refine at full resolution on the map's own height model with fixed-point steps ``z_{k+1} = h(m(z_k))``:
   ``z1 = h(m(z0))`` is the height of the surface the ray is in; where the next step leaves it unchanged the ray
   sees that surface at ``m(z1)`` (flat roofs and open ground: most pixels). The rest (walls, roof edges, trees,
   low objects such as cars) get one more step on that subset; where ``z`` keeps jumping between the street and
   the roof the ray entered through a wall: a facade pixel, coloured from the building where the ray meets the
   ground (inside its footprint) and darkened by ``facade_gain``. Only pixels of march cells with relief (a hit,
   or a non-zero block maximum within the cell's reach on the ground) are refined, a band of cells at a time,
   step by step over the band's list: on flat ground the steps would leave the affine point unchanged (a
   fifth of the pixels in the perf scene remain). The kernels reproduce the arithmetic of the OpenCV warps and
   NumPy passes they replaced (perspective v5) bit for bit (see ``perspective_kernels``).

The result is a pair of per-pixel map coordinate planes (x, y) for one ``cv2.remap`` of the map (and of the cast-shadow
field, which lives in map coordinates on the ground and roofs, so shadows stay on the surfaces they fall on). With
the shadows baked into a box of the map (``render.CameraRenderer.bake``) the frame is one remap of that box, RGB and
occlusion together, done inside the frame's finishing pass (``perspective_kernels.view_finish``, the facades shaded
there): the maps are then made in the box's pixels (``origin_px``) so that no pass shifts them.
Heights are clipped below ``0.95 H`` (a camera below the roofs has no downward view). Features thinner than one
march step (about ``H_max / N`` of height, ``r H_max / (N H)`` on the ground) may be missed at the frame edge.

Gimbal attitude errors (roll, pitch) rotate the camera about its centre: an image homography ``K R K^-1``
independent of the scene, composed into the same maps (flat ground: the homography's maps).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import cv2
import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.sensors import perspective_kernels as kernels
from aerial_loc_env.sensors.camera import CameraModel

_MAX_HEIGHT_FRACTION = 0.95
GENERATOR_VERSION = 6  # bump whenever the frames change for the same inputs (env/fingerprint.py)
_MARCH_FACTOR = kernels.MARCH_FACTOR   # the march's 1/4-resolution camera grid over the heights' 4 x 4 block maximum
_REMAP_MAX_PX = 32767  # cv2.remap's limit on the source's sides
_FACADE_REACH_PX = 1.0  # how far beyond the footprint a frame samples with a height model (facades: one map px)
_SURFACE_TOL_M = 0.3    # h(m(z1)) within this of z1: the ray sees the surface (ridged roofs vary by less per px)
_NO_DSM = np.zeros((1, 1), np.float32)   # the kernel's height model argument for flat views (never read)
_NO_TILT = np.zeros((3, 3), np.float32)  # its tilt argument for untilted views (never read)
_NO_SUN = np.full(6, np.nan, np.float32)  # view_finish's sun argument without a sun (facades at facade_gain)
_EYE = np.eye(3)       # plan_view's and map_corners' tilt argument for untilted views (never written)
_IDENTITY_AFFINE = np.eye(2, 3)   # tilted_corners' affine (never written)


@dataclass(frozen=True)
class PerspectiveConfig:
    """The [perspective] section: render the height model in perspective (off by default: the affine warp).

    Applies only to maps with a height model (``map.use_dsm`` and a DSM); others keep the affine warp.
    """

    enabled: bool = False
    march_steps: int = field(default=10, metadata=rng(2, 64, doc="heights probed per ray (first-hit search)"))
    facade_gain: float = field(default=0.55, metadata=rng(0.0, 1.0, lo_open=True,
                                                           doc="facade brightness relative to its roof"))
    # with the sun known (the env passes it), facades are lit by it: see ReliefView.shade_facades
    ambient: float = field(default=0.15, metadata=rng(0.0, 1.0, lo_open=True,
                                                      doc="sky light on a roof, share of sun + sky (linear)"))


def tilt_homography(camera: CameraModel, roll_rad: float, pitch_rad: float) -> np.ndarray | None:
    """(3, 3) homography: pixel of the tilted camera -> pixel of the nadir camera at the same centre, or None.

    Camera axes: x right (``u``), y towards the tail (``v``), z down the optical axis. Positive roll tilts the
    optical axis to the vehicle's right, positive pitch forward (the frame then shows ground further ahead).
    """
    if roll_rad == 0.0 and pitch_rad == 0.0:
        return None
    k, k_inv = _intrinsics(camera)
    out = np.empty((3, 3))
    # K R_roll R_pitch K^-1, NumPy's products in one compiled call (a frame's NumPy calls run cold after its kernels)
    kernels.tilt_matrix(k, k_inv, math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad),
                        out)
    return out


@lru_cache(maxsize=16)
def _intrinsics(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """The camera matrix K and its inverse (read-only; once per camera: ``np.linalg.inv`` costs more than the rest
    of a frame's tilt, and gives the same floats each time)."""
    fu = (camera.width_px / 2.0) / math.tan(math.radians(camera.hfov_deg) / 2.0)
    fv = fu / camera.pixel_aspect
    cu, cv = camera.center_px
    k = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    k_inv = np.linalg.inv(k)
    k.flags.writeable = k_inv.flags.writeable = False
    return k, k_inv


@lru_cache(maxsize=16)
def _centre_shift(cu: float, cv: float) -> tuple[np.ndarray, np.ndarray]:
    """The translation by the principal point (cu, cv) and its inverse (read-only, as ``_intrinsics``)."""
    shift = np.array([[1.0, 0.0, cu], [0.0, 1.0, cv], [0.0, 0.0, 1.0]])
    inv = np.linalg.inv(shift)
    shift.flags.writeable = inv.flags.writeable = False
    return shift, inv


def tilted_corners(camera: CameraModel, tilt: np.ndarray | None) -> np.ndarray:
    """The image corners (4, 2) in nadir-camera pixels (for footprint checks)."""
    return footprint_px(_IDENTITY_AFFINE, camera, tilt)


def footprint_px(affine: np.ndarray, camera: CameraModel, tilt: np.ndarray | None = None) -> np.ndarray:
    """The frame's corners (4, 2) in level-0 map pixels: the camera->map ``affine`` of the (tilted) image corners
    (``cv2.perspectiveTransform`` then ``camera.apply_affine``'s floats, in one compiled call:
    ``perspective_kernels.map_corners``)."""
    out = np.empty((4, 2))
    kernels.map_corners(np.ascontiguousarray(affine, dtype=np.float64),
                        _EYE if tilt is None else np.ascontiguousarray(tilt, dtype=np.float64), _corners(camera),
                        tilt is not None, out)
    return out


@lru_cache(maxsize=16)
def _corners(camera: CameraModel) -> np.ndarray:
    """``camera.corners_px()`` (read-only; once per camera)."""
    corners = camera.corners_px()
    corners.flags.writeable = False
    return corners


@dataclass(frozen=True, eq=False)
class ViewMaps:
    """Where each pixel of one frame looks on the map.

    ``x``, ``y`` (h, w) float32: the level-0 map pixel each camera pixel sees, minus ``origin_px`` (separate
    planes: OpenCV's per-plane arithmetic and ``remap(src, x, y)`` are several times faster than on an
    interleaved (h, w, 2) array; the origin lets a box cut from the map be sampled without shifting them);
    ``facade``: flat indices of facade pixels, or None; ``facing`` (n, 2) float32 unit (east, north): where each
    facade pixel faces.
    """

    x: np.ndarray
    y: np.ndarray
    facade: np.ndarray | None
    bbox: tuple[float, float, float, float]   # (x0, y0, x1, y1) level-0 map pixels holding every sample
    facing: np.ndarray | None = None
    origin_px: tuple[int, int] = (0, 0)       # (column, row): the map pixel at x = y = 0

    @property
    def xy(self) -> np.ndarray:
        """(h, w, 2) float32 map pixels (for inspection; sampling uses the planes)."""
        xy = cv2.merge([self.x, self.y])
        return xy if self.origin_px == (0, 0) else xy + np.float32(self.origin_px)

    def sample(self, image: np.ndarray, level: int = 0, *, border: int = cv2.BORDER_CONSTANT,
               scale: float = 1.0, offset: float = 0.0, origin_px: tuple[int, int] = (0, 0)) -> np.ndarray:
        """``image`` sampled (bilinear) at the maps: pyramid level ``level`` (``u_L = u_0 / 2**L``), or any grid
        with ``u_g = u_0 * scale + offset`` (e.g. a coarse shadow field), whose pixel (0, 0) is the grid's pixel
        ``origin_px`` (column, row) (e.g. a box cut from the map). Sources beyond remap's 32767 px limit are cut
        to the window under the footprint (a view)."""
        f = scale / (1 << level)
        h, w = image.shape[:2]
        ox, oy = offset - origin_px[0], offset - origin_px[1]    # grid px = map px * f + (ox, oy)
        sx, sy = self.origin_px[0] * f + ox, self.origin_px[1] * f + oy   # ... = (x, y) * f + (sx, sy)
        if f == 1.0 and sx == 0.0 and sy == 0.0 and max(h, w) < _REMAP_MAX_PX:
            return cv2.remap(image, self.x, self.y, cv2.INTER_LINEAR, borderMode=border, borderValue=0)
        c0, r0, c1, r1 = _window(self.bbox, f, (ox, oy), w, h)
        if c1 <= c0 or r1 <= r0:
            return np.zeros(self.x.shape + image.shape[2:], image.dtype)
        gx = cv2.addWeighted(self.x, f, self.x, 0.0, sx - c0)
        gy = cv2.addWeighted(self.y, f, self.y, 0.0, sy - r0)
        return cv2.remap(image[r0:r1, c0:c1], gx, gy, cv2.INTER_LINEAR, borderMode=border, borderValue=0)


@dataclass(frozen=True, eq=False)
class ViewPlan:
    """A frame's view up to its per-pixel maps: the march's result and the maps kernel's arguments
    (``ReliefView.plan``), for ``ReliefView.view_of`` (the maps) or ``ReliefView.finish_frame`` (the frame sampled
    through them, the maps never stored whole)."""

    shape: tuple[int, int]                    # (h, w) camera pixels
    bbox: tuple[float, float, float, float]   # as ``ViewMaps.bbox``
    origin_px: tuple[int, int]                # as ``ViewMaps.origin_px``
    key: tuple[bool, bool]                    # the kernels' (tilted, replicated border)
    args: tuple[Any, ...]                     # (z0, relief, factor, centre, tilt, flat, lin, consts, dsm, window)


def _plan_buffers(hc: int, wc: int, steps: int) -> tuple[np.ndarray, ...]:
    """``perspective_kernels.plan_view``'s outputs and scratch for a (hc, wc) march grid of ``steps`` heights: z0,
    relief, centre, conj, flat, lin, consts, the march window, the probes' warps, the levels."""
    f32 = np.float32
    return (np.empty((hc, wc), f32), np.empty((hc, wc), np.uint8), np.empty(2, f32), np.empty((3, 3), f32),
            np.empty((2, 3), f32), np.empty((2, 2), f32), np.empty(7, f32), np.empty(4, np.int64),
            np.empty((steps + 1, 9), f32), np.empty((2, steps), f32))


def _window(bbox: tuple[float, float, float, float], scale: float, offset: tuple[float, float], w: int,
            h: int) -> tuple[int, int, int, int]:
    """The pixel window (c0, r0, c1, r1) of a grid ``u_g = u_0 * scale + offset`` (per axis) holding ``bbox``
    (+2 px)."""
    lo = [int(math.floor(b * scale + o)) - 2 for b, o in zip(bbox[:2], offset, strict=True)]
    hi = [int(math.ceil(b * scale + o)) + 3 for b, o in zip(bbox[2:], offset, strict=True)]
    return max(0, lo[0]), max(0, lo[1]), min(w, hi[0]), min(h, hi[1])


class ReliefView:
    """Per-pixel maps of camera frames over one orthomap: its height model ``dsm_m`` ((H, W) metres above
    ground, level 0) in perspective, and/or a tilted camera. ``dsm_m=None``: flat ground (tilt only).

    Not thread-safe (cached grids); one per renderer.
    """

    def __init__(self, dsm_m: np.ndarray | None, config: PerspectiveConfig | None = None) -> None:
        self.dsm = None if dsm_m is None else np.ascontiguousarray(dsm_m, dtype=np.float32)
        self.config = config or PerspectiveConfig(enabled=True)
        self._grids: dict[tuple, Any] = {}
        self._pooled: np.ndarray | None = None

    def _ground_heights(self, radius: int) -> np.ndarray:
        """The block maximum dilated by ``radius`` blocks (once per radius): zero where a whole neighbourhood is
        flat ground."""
        key = ("ground", radius)
        if key not in self._grids:
            self._grids[key] = cv2.dilate(self._march_heights(), np.ones((2 * radius + 1,) * 2, np.uint8))
        return self._grids[key]

    def _march_heights(self) -> np.ndarray:
        """The height model's block maximum over ``_MARCH_FACTOR`` px (once): the coarse march misses nothing."""
        if self._pooled is None:
            from aerial_loc_env.world.shadows import max_pool  # layer 1

            self._pooled = max_pool(self.dsm, _MARCH_FACTOR)
        return self._pooled

    def reads_px(self, affine: np.ndarray, camera: CameraModel, tilt: np.ndarray | None = None,
                 corners: np.ndarray | None = None) -> np.ndarray:
        """Level-0 map points (n, 2) whose bounding box holds every point a frame's maps can sample: the footprint
        (every ray's visible point lies between its ground point and nadir), one map pixel wider with a height
        model (facades sample one pixel beyond their ground point). ``corners``: the footprint's corners in map
        pixels if the caller has them (``footprint_px``)."""
        corners = footprint_px(affine, camera, tilt) if corners is None else corners
        if self.dsm is None:
            return corners
        return np.concatenate([corners - _FACADE_REACH_PX, corners + _FACADE_REACH_PX])

    def reads_bounds_px(self, corners: np.ndarray) -> tuple[float, float, float, float]:
        """The bounds (u0, v0, u1, v1) of ``reads_px`` for a frame whose footprint's corners (``footprint_px``) are
        ``corners``: the same floats, in plain Python (4 points; a frame's NumPy calls run cold after its
        kernels)."""
        m = 0.0 if self.dsm is None else _FACADE_REACH_PX
        us, vs = corners[:, 0].tolist(), corners[:, 1].tolist()
        return min(us) - m, min(vs) - m, max(us) + m, max(vs) + m

    def maps(self, affine: np.ndarray, altitude_m: float, camera: CameraModel,
             tilt: np.ndarray | None = None, origin_px: tuple[int, int] = (0, 0),
             corners: np.ndarray | None = None) -> ViewMaps | None:
        """The maps of the frame whose nadir camera->map affine (level 0) is ``affine`` at ``altitude_m``, with
        the tilt homography ``tilt`` (``tilt_homography``), in map pixels minus ``origin_px`` (``ViewMaps``);
        None when the footprint is flat and the camera untilted (the affine warp is exact then). ``corners``: the
        footprint's corners (``footprint_px``) if the caller has them."""
        plan = self.plan(affine, altitude_m, camera, tilt, origin_px, corners)
        return None if plan is None else self.view_of(plan)

    def view_of(self, plan: ViewPlan) -> ViewMaps:
        """The per-pixel maps of a planned frame (``perspective_kernels.view_maps``)."""
        h, w = plan.shape
        gx, gy = self._map_buffers(h, w)
        facade, facing = self._facade_buffers(h * w)
        n = kernels.view_maps[plan.key](gx, gy, facade, facing, *plan.args)
        if n == 0:
            return ViewMaps(gx, gy, None, plan.bbox, None, plan.origin_px)
        return ViewMaps(gx, gy, facade[:n], plan.bbox, facing[:n], plan.origin_px)

    def finish_frame(self, plan: ViewPlan, box: np.ndarray, sun_deg: tuple[float, float] | None, gamma: float,
                     *args: Any) -> int:
        """A planned frame sampled from ``box`` (a baked box's uint32 RGBA pixels, in whose pixels the plan was
        made) and finished, its facades shaded (``facade_gains``), without its maps going through memory
        (``perspective_kernels.view_finish``; ``args``: ``render_kernels.warp_finish``'s after its matrix)."""
        h, w = plan.shape
        facade, facing = self._facade_buffers(h * w)
        sun = self._sun_params(sun_deg, gamma)
        key, dtype = ("gains f64", np.float64) if sun is None else ("gains f32", np.float32)  # (``facade_gains``)
        (gains,) = self._reused(key, lambda: (np.empty(h * w, dtype),), lambda bufs: bufs[0].size >= h * w)
        return kernels.view_finish[plan.key](box, facade, facing, gains, _NO_SUN if sun is None else sun,
                                             self.config.facade_gain, *plan.args, *args)

    def plan(self, affine: np.ndarray, altitude_m: float, camera: CameraModel,
             tilt: np.ndarray | None = None, origin_px: tuple[int, int] = (0, 0),
             corners: np.ndarray | None = None) -> ViewPlan | None:
        """``maps``' frame up to its per-pixel maps: the march done, the maps kernel's arguments (``ViewPlan``), or
        None where ``maps`` gives None."""
        w, h = camera.width_px, camera.height_px
        a = np.ascontiguousarray(affine, dtype=np.float64)
        cu, cv = camera.center_px
        corners = footprint_px(a, camera, tilt) if corners is None else corners
        us, vs = corners.T.tolist()        # 4 points: plain Python beats NumPy's reductions (the same values)
        bbox = (min(us), min(vs), max(us), max(vs))
        origin = (int(origin_px[0]), int(origin_px[1]))
        f = _MARCH_FACTOR
        wc, hc = -(-w // f), -(-h // f)
        if tilt is None and self.dsm is None:
            return None     # flat ground, untilted: the affine warp is exact
        steps = self.config.march_steps
        bufs = self._reused("march", lambda: _plan_buffers(hc, wc, steps),
                            lambda bufs: bufs[0].shape == (hc, wc) and bufs[8].shape[0] == steps + 1)
        z0, relief, centre, conj, flat, lin, consts, march_window, warps, levels = bufs
        shift, unshift = _centre_shift(cu, cv)
        tilt_arg = _EYE if tilt is None else np.ascontiguousarray(tilt, dtype=np.float64)

        def planned(window: tuple[int, ...]) -> ViewPlan:
            """The maps kernel's arguments (``window``: the height model's, and whether its border is replicated)."""
            return ViewPlan((h, w), bbox, origin, (tilt is not None, bool(window[4])), (
                z0, relief, f, centre, _NO_TILT if tilt is None else conj, flat, lin, consts,
                _NO_DSM if self.dsm is None else self.dsm, np.array(window[:4], np.int64)))

        if self.dsm is None:    # a tilted camera over flat ground: its ground points
            kernels.view_args(a, tilt_arg, shift, unshift, float(cu), float(cv), *origin, True, centre, conj, flat,
                              lin)
            z0[:], relief[:], consts[:] = 0.0, 0, 0.0
            return planned((0,) * 5)
        # the march and the maps' arguments in one compiled call (``perspective_kernels.plan_view``: the nadir
        # point, the cells' probes m(z) = nadir + k (g - nadir), k = 1 - z / H, the top height, the march): every
        # m(z) lies in the footprint, so the march reads the pooled heights in the window under it (pooled px
        # (u + 0.5) / F - 0.5 of map px u). A cell's hit is the first height z_i from the footprint's top at which
        # its ray is at or below the block maximum (pooled > z_i - 1e-4), 0 without one; z0 is the hits' 3 x 3
        # maximum (no roof edge is lost to the coarse grid; the next steps verify). Flat ground: a cell whose rays
        # hit nothing (z0 = 0) and whose pixels all look at ground of height 0 (the block maximum dilated by the
        # cell's reach, sampled like the march) sees the ground at its affine point g: the fixed-point steps would
        # leave it there (z1 = z2 = 0).
        pooled = self._march_heights()
        c0, r0, c1, r1 = _window(bbox, 1.0 / f, (0.5 / f - 0.5,) * 2, pooled.shape[1], pooled.shape[0])
        (a00, a01, _), (a10, a11, _) = a.tolist()
        reach = 2.0 * max(abs(a00) + abs(a01), abs(a10) + abs(a11))   # map px per axis, in a cell
        march_window[:] = (r0, c0, r1 - r0, c1 - c0)
        count = kernels.plan_view[tilt is not None](
            a, tilt_arg, shift, unshift, float(cu), float(cv), float(altitude_m), _MAX_HEIGHT_FRACTION,
            _SURFACE_TOL_M, *origin, march_window, pooled, self._ground_heights(int(math.ceil((reach + 1.0) / f))),
            warps, levels, z0, relief, centre, conj, flat, lin, consts)
        if count <= 0:   # flat ground under the footprint: the affine warp (None), or the tilted ground points
            return None if tilt is None else planned((0,) * 5)
        if max(self.dsm.shape) < _REMAP_MAX_PX:
            return planned((0, 0, self.dsm.shape[1], self.dsm.shape[0], 0))
        # as remap would read it: a window under the footprint, its border replicated
        return planned((*_window(bbox, 1.0, (0.0, 0.0), self.dsm.shape[1], self.dsm.shape[0]), 1))

    def _map_buffers(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """Two (h, w) float32 planes for a frame's maps: the last frame's when nothing else holds them any more
        (the renderer drops its view after sampling), else new ones. Fresh planes cost more than the copy: the
        kernel's first touch faults their pages in (zeroed) every frame."""
        return self._reused("maps", lambda: (np.empty((h, w), np.float32), np.empty((h, w), np.float32)),
                            lambda bufs: bufs[0].shape == (h, w))

    def _facade_buffers(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Facade index and facing buffers for up to n pixels (a view returns their first rows: no copy), the last
        frame's when nothing else holds them or a view of them any more, else new ones (as ``_map_buffers``)."""
        return self._reused("facades", lambda: (np.empty(n, np.int64), np.empty((n, 2), np.float32)),
                            lambda bufs: bufs[0].size >= n)

    def _reused(self, key: str, new: Callable[[], tuple[np.ndarray, ...]],
                fits: Callable[[tuple[np.ndarray, ...]], bool]) -> tuple[np.ndarray, ...]:
        """The buffers under ``key`` if they ``fit`` and nothing else holds them (or a view of them), else ``new()``
        ones (kept for the next frame)."""
        last = self._grids.get(key)
        # references: the dict's tuple, ``last`` and getrefcount's argument; a live ViewMaps (or view) adds its own
        if last is not None and fits(last) and all(sys.getrefcount(b) <= 3 for b in last):
            return last
        bufs = self._grids[key] = new()
        return bufs

    def shade_facades(self, image: np.ndarray, view: ViewMaps, sun_deg: tuple[float, float] | None = None,
                      gamma: float = 2.2) -> np.ndarray:
        """Shade facade pixels in place (uint8 (h, w, 3)) by ``facade_gains``; returns ``image``."""
        if view.facade is not None:
            # the kernel writes through a flat view of the frame at the facade indices, unchecked
            if image.dtype != np.uint8 or image.ndim != 3 or image.shape[:2] != view.x.shape \
                    or not image.flags.c_contiguous:
                raise ConfigError(f"shade_facades: expected a C-contiguous uint8 (h, w, c) frame with (h, w) = "
                                  f"{view.x.shape}, got {image.dtype} {image.shape}")
            kernels.shade_pixels(image.reshape(-1, image.shape[-1]), view.facade,
                                 self.facade_gains(view, sun_deg, gamma))
        return image

    def facade_gains(self, view: ViewMaps, sun_deg: tuple[float, float] | None = None,
                     gamma: float = 2.2) -> np.ndarray:
        """The gain of each facade pixel of ``view`` on its roof's colour.

        Without a sun: ``facade_gain`` (float64: a byte times a Python float is float64 in NumPy, which the shading
        reproduces). With ``sun_deg = (azimuth, elevation)`` (towards the sun, compass degrees) a facade is lit
        like a vertical wall: in linear light, relative to a sunlit roof (``ambient + direct = 1``, ``direct =
        (1 - ambient)`` at the sun's elevation), a wall gets half the sky (``ambient / 2``) plus ``direct cos(el) /
        sin(el) max(0, n . sun)``: walls facing away from the sun are dark, walls facing it at a low sun bright;
        then ``facade_gain`` (its albedo against the roof's) and the tone curve ``gamma`` (float32).
        """
        sun = self._sun_params(sun_deg, gamma)
        if sun is None or view.facing is None:
            return np.full(0 if view.facade is None else view.facade.size, self.config.facade_gain)
        gains = np.empty(view.facing.shape[0], np.float32)
        kernels.facade_gains(view.facing, sun, gains)
        return gains

    def _sun_params(self, sun_deg: tuple[float, float] | None, gamma: float) -> np.ndarray | None:
        """``facade_gains``' constants as its kernel takes them (float32: sin and cos of the azimuth, the direct
        light's coefficient ``(1 - ambient) cos(el) / max(sin(el), 0.05)``, half the ambient, 1 / gamma,
        ``facade_gain``: each rounded once from its float64 value, as NumPy's float32 arithmetic takes a Python
        number), or None without a sun."""
        if sun_deg is None:
            return None
        az, el = (math.radians(a) for a in sun_deg)
        amb = self.config.ambient
        return np.array([math.sin(az), math.cos(az), (1.0 - amb) * math.cos(el) / max(math.sin(el), 0.05),
                         0.5 * amb, 1.0 / gamma, self.config.facade_gain], np.float32)


def sample_grid(view: ViewMaps, data: np.ndarray, factor: int) -> np.ndarray:
    """A coarse map-aligned field (cell ``c`` covers map pixels ``[c f, (c + 1) f)``) at the view's pixels."""
    return view.sample(data, border=cv2.BORDER_REPLICATE, scale=1.0 / factor, offset=0.5 / factor - 0.5)


__all__ = ["PerspectiveConfig", "ReliefView", "ViewMaps", "ViewPlan", "footprint_px", "sample_grid", "tilt_homography",
           "tilted_corners"]
