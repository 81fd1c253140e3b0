"""A pinhole camera's view of the height model: relief displacement, facades and occlusion.

Why: one affine warp of the orthomap shows every roof on its own ground footprint. A real camera at height ``H``
sees a point at height ``h`` and ground distance ``r`` from nadir at ``r H / (H - h)``, i.e. displaced outward by
``r h / (H - h)``; it sees the facades that face the nadir point, and not the ground behind tall buildings. Real
maps without a height model keep the affine warp (``render.py``).

How (inverse mapping, vectorized with OpenCV): the ray of camera pixel ``q`` meets the ground at ``g0(q)`` and
crosses height ``z`` at ``m(z) = g0 + (c - g0) z / H`` (``c`` the nadir point): it moves towards nadir as it
rises, so every point the camera can see lies inside the ground footprint. The visible point is the ray's first
intersection from above, the largest ``z`` with ``h(m(z)) >= z``.

1. March: one ray per 4 x 4 block of camera pixels (its centre's). For ``N`` heights ``z_i`` from the
   footprint's tallest point down, the points ``m(z_i)`` of these rays are the blocks' ground points scaled by
   ``1 - z_i / H`` about nadir: an affine image of the block grid (projective for a tilted camera), so each step
   is one small warp (``warpAffine`` / ``warpPerspective``) of the height model's 4 x 4 block maximum (a
   contiguous copy of the window under the footprint) onto the block grid, thresholded at ``z_i`` and
   max-combined: the highest ``z_i`` at which the ray is at or below the surface, i.e. the first hit from the
   top to within one step (dilated by a block so that no roof edge is lost to the coarse grid; the next step
   verifies). Each block's pixels start from its z0: a relief block's pixels are listed block by block.
2. Refine at full resolution on the map's own height model with fixed-point steps ``z_{k+1} = h(m(z_k))``:
   ``z1 = h(m(z0))`` is the height of the surface the ray is in; where the next step leaves it unchanged the ray
   sees that surface at ``m(z1)`` (flat roofs and open ground: most pixels). The rest (walls, roof edges, trees,
   low objects such as cars) get one more step on that subset; where ``z`` keeps jumping between the street and
   the roof the ray entered through a wall: a facade pixel, coloured from the building where the ray meets the
   ground (inside its footprint) and darkened by ``facade_gain``. Only pixels of march cells with relief (a hit,
   or a non-zero block maximum within the cell's reach on the ground) are refined, as 1-D arrays: on flat
   ground the steps would leave the affine point unchanged (a quarter of the pixels in the perf scene remain).

The result is a pair of per-pixel map coordinate planes (x, y) for one ``cv2.remap`` of the map (and of the cast-shadow
field, which lives in map coordinates on the ground and roofs, so shadows stay on the surfaces they fall on). With
the shadows baked into a box of the map (``render.CameraRenderer.bake``) the frame is one remap of that box, RGB and
occlusion together: the maps are then made in the box's pixels (``origin_px``) so that no pass shifts them.
Heights are clipped below ``0.95 H`` (a camera below the roofs has no downward view). Features thinner than one
march step (about ``H_max / N`` of height, ``r H_max / (N H)`` on the ground) may be missed at the frame edge.

Gimbal attitude errors (roll, pitch) rotate the camera about its centre: an image homography ``K R K^-1``
independent of the scene, composed into the same maps (flat ground: the homography's maps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from ..config import rng
from .camera import CameraModel, apply_affine

_NEAREST = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
_MAX_HEIGHT_FRACTION = 0.95
GENERATOR_VERSION = 5  # bump whenever the frames change for the same inputs (env/fingerprint.py)
_MARCH_FACTOR = 4      # the march runs on a 1/4-resolution camera grid over the 4 x 4 block maximum of the heights
_REMAP_MAX_PX = 32767  # cv2.remap's limit on the source's sides
_ROW_PX = 1024         # 1-D sample points go to remap as rows of this many (remap wants fewer than 32767 rows)
_SURFACE_TOL_M = 0.3    # h(m(z1)) within this of z1: the ray sees the surface (ridged roofs vary by less per px)


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
    fu = (camera.width_px / 2.0) / math.tan(math.radians(camera.hfov_deg) / 2.0)
    fv = fu / camera.pixel_aspect
    cu, cv = camera.center_px
    k = np.array([[fu, 0.0, cu], [0.0, fv, cv], [0.0, 0.0, 1.0]])
    cr, sr, cp, sp = math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    r_roll = np.array([[cr, 0.0, sr], [0.0, 1.0, 0.0], [-sr, 0.0, cr]])
    r_pitch = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    return k @ r_roll @ r_pitch @ np.linalg.inv(k)


def tilted_corners(camera: CameraModel, tilt: np.ndarray | None) -> np.ndarray:
    """The image corners (4, 2) in nadir-camera pixels (for footprint checks)."""
    corners = camera.corners_px()
    if tilt is None:
        return corners
    return cv2.perspectiveTransform(corners.reshape(1, 4, 2), tilt).reshape(4, 2)


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

    def _centred_grid(self, camera: CameraModel) -> np.ndarray:
        """(h, w, 2) float32 pixel offsets from the principal point."""
        key = (camera.width_px, camera.height_px)
        if key not in self._grids:
            cu, cv = camera.center_px
            u, v = np.meshgrid(np.arange(key[0], dtype=np.float32) - np.float32(cu),
                               np.arange(key[1], dtype=np.float32) - np.float32(cv))
            self._grids[key] = np.dstack([u, v])
        return self._grids[key]

    def _centred_planes(self, camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
        """The centred grid as two contiguous (h, w) float32 planes (u, v), once per camera size."""
        key = ("planes", camera.width_px, camera.height_px)
        if key not in self._grids:
            self._grids[key] = tuple(cv2.split(self._centred_grid(camera)))
        return self._grids[key]

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
            from ..world.shadows import max_pool  # layer 1

            self._pooled = max_pool(self.dsm, _MARCH_FACTOR)
        return self._pooled

    def reads_px(self, affine: np.ndarray, camera: CameraModel, tilt: np.ndarray | None = None) -> np.ndarray:
        """Level-0 map points (n, 2) whose bounding box holds every point a frame's maps can sample: the footprint
        (every ray's visible point lies between its ground point and nadir), one map pixel wider with a height
        model (facades sample one pixel beyond their ground point)."""
        corners = apply_affine(np.asarray(affine, dtype=np.float64), tilted_corners(camera, tilt))
        if self.dsm is None:
            return corners
        return np.concatenate([corners - 1.0, corners + 1.0])

    def maps(self, affine: np.ndarray, altitude_m: float, camera: CameraModel,
             tilt: np.ndarray | None = None, origin_px: tuple[int, int] = (0, 0)) -> ViewMaps | None:
        """The maps of the frame whose nadir camera->map affine (level 0) is ``affine`` at ``altitude_m``, with
        the tilt homography ``tilt`` (``tilt_homography``), in map pixels minus ``origin_px`` (``ViewMaps``);
        None when the footprint is flat and the camera untilted (the affine warp is exact then)."""
        w, h = camera.width_px, camera.height_px
        a = np.asarray(affine, dtype=np.float64)
        cu, cv = camera.center_px
        nadir_x, nadir_y = a[:, :2] @ np.array([cu, cv]) + a[:, 2]     # the map pixel below the camera
        corners = apply_affine(a, tilted_corners(camera, tilt))
        bbox = (*corners.min(axis=0), *corners.max(axis=0))
        ru, rv = self._centred_planes(camera)
        if tilt is not None:
            ru, rv = _tilted_rays(ru, rv, camera, tilt)
        origin = (int(origin_px[0]), int(origin_px[1]))
        ox, oy = float(nadir_x) - origin[0], float(nadir_y) - origin[1]    # nadir in the maps' frame

        def ground_points() -> tuple[np.ndarray, np.ndarray]:
            """The ground point each ray meets (x, y), map px - origin: one pass each."""
            return cv2.addWeighted(ru, a[0, 0], rv, a[0, 1], ox), cv2.addWeighted(ru, a[1, 0], rv, a[1, 1], oy)

        def flat_view() -> ViewMaps | None:
            """Flat ground under the footprint: the affine warp (None), or the tilted camera's ground points."""
            return None if tilt is None else ViewMaps(*ground_points(), None, bbox, origin_px=origin)

        if self.dsm is None:
            return flat_view()
        big_h = float(altitude_m)
        # the march grid: one cell per F x F camera block, probed along the ray of the block's centre pixel
        # (q = F q_c + (F - 1) / 2, through the tilt to the nadir camera, then to the map), on the F x F block
        # maximum of the heights (map px u -> pooled px (u + 0.5) / F - 0.5)
        f = _MARCH_FACTOR
        wc, hc = -(-w // f), -(-h // f)
        grid_to_cam = np.array([[f, 0.0, (f - 1) / 2.0], [0.0, f, (f - 1) / 2.0], [0.0, 0.0, 1.0]])
        to_map = np.vstack([a, [0.0, 0.0, 1.0]]) @ (np.eye(3) if tilt is None else tilt) @ grid_to_cam
        map_to_pool = np.array([[1.0 / f, 0.0, 0.5 / f - 0.5], [0.0, 1.0 / f, 0.5 / f - 0.5], [0, 0, 1]])

        def at_height(src: np.ndarray, k: float, dst: np.ndarray | None = None) -> np.ndarray:
            """``src`` (pooled grid) at the cells' points m(z) = nadir + k (g - nadir), k = 1 - z / H: one warp."""
            scaled = np.array([[k, 0.0, nadir_x * (1.0 - k)], [0.0, k, nadir_y * (1.0 - k)], [0.0, 0.0, 1.0]])
            m = map_to_pool @ scaled @ to_map
            if tilt is None:
                return cv2.warpAffine(src, m[:2], (wc, hc), dst=dst, flags=_NEAREST, borderMode=cv2.BORDER_CONSTANT)
            return cv2.warpPerspective(src, m, (wc, hc), dst=dst, flags=_NEAREST, borderMode=cv2.BORDER_CONSTANT)

        # every m(z) lies in the footprint: the march reads a contiguous copy of the pooled heights under it
        # (cache-resident for the 11 warps); pooled px (u + 0.5) / F - 0.5 of the window's map px u
        pooled = self._march_heights()
        c0, r0, c1, r1 = _window(bbox, 1.0 / f, (0.5 / f - 0.5,) * 2, pooled.shape[1], pooled.shape[0])
        pooled = np.ascontiguousarray(pooled[r0:r1, c0:c1])
        map_to_pool[:2, 2] -= (c0, r0)
        heights = at_height(pooled, 1.0)
        z_raw = float(cv2.minMaxLoc(heights)[1])
        z_top = min(z_raw, _MAX_HEIGHT_FRACTION * big_h)
        if z_top <= 0.0:
            return flat_view()
        z_hit = np.zeros_like(heights)
        probe = np.empty_like(heights)
        steps = self.config.march_steps
        for i in range(steps):
            z = z_top * (steps - i) / steps
            at_height(pooled, 1.0 - z / big_h, probe)
            cv2.threshold(probe, z - 1e-4, z, cv2.THRESH_BINARY, dst=probe)   # hit: the ray is at/below the surface
            cv2.max(z_hit, probe, dst=z_hit)
        z_hit = cv2.dilate(z_hit, np.ones((3, 3), np.uint8))
        # Flat ground: a cell whose rays hit nothing in the march (z0 = 0) and whose pixels all look at ground of
        # height 0 (the block maximum dilated by the cell's reach, sampled like the march) sees the ground at its
        # affine point g: the fixed-point steps below would leave it there (z1 = z2 = 0). Only the other cells'
        # pixels (marked by z0 >= 0; flat ones get -1) are refined, as 1-D arrays.
        reach = 2.0 * max(abs(a[0, 0]) + abs(a[0, 1]), abs(a[1, 0]) + abs(a[1, 1]))   # map px per axis, in a cell
        ground = at_height(self._ground_heights(int(math.ceil((reach + 1.0) / f)))[r0:r1, c0:c1], 1.0)
        relief = cv2.bitwise_or(cv2.compare(z_hit, 0.0, cv2.CMP_GT), cv2.compare(ground, 0.0, cv2.CMP_GT))
        if cv2.countNonZero(relief) == 0:
            return flat_view()
        cap = np.float32(_MAX_HEIGHT_FRACTION * big_h) if z_raw > _MAX_HEIGHT_FRACTION * big_h else None
        # the relief cells' pixels, block by block (flat indices), each with its cell's z0
        cells = np.flatnonzero(relief)
        rows, cols = np.divmod(cells, wc)
        within = (np.arange(f)[:, None] * w + np.arange(f)[None, :]).ravel()
        idx = ((rows * (f * w) + cols * f)[:, None] + within[None, :]).ravel()
        z0s = np.repeat(z_hit.ravel()[cells], f * f)
        if w % f or h % f:   # partial blocks at the right and bottom edges: their pixels inside the frame
            keep = ((rows[:, None] * f + within[None, :] // w < h)
                    & (cols[:, None] * f + within[None, :] % w < w)).ravel()
            idx, z0s = idx[keep], z0s[keep]
        nx, ny = np.float32(nadir_x), np.float32(nadir_y)
        rus, rvs = ru.ravel()[idx], rv.ravel()[idx]
        m = a[:, :2].astype(np.float32)
        du, dv = m[0, 0] * rus + m[0, 1] * rvs, m[1, 0] * rus + m[1, 1] * rvs     # ground point - nadir, map px
        bx, by = self._row_buffers(idx.size)
        big_h32 = np.float32(big_h)

        def height(k: np.ndarray, part: np.ndarray | None = None) -> np.ndarray:
            """h(m(z)) for the subset's rays (or its ``part``) scaled by k = 1 - z / H about nadir."""
            n = k.size
            if n == 0:
                return k.copy()
            rows = -(-n // _ROW_PX)
            sx, sy = bx[:rows], by[:rows]          # sample points written in place (the tail: stale, unread)
            fx, fy = sx.ravel()[:n], sy.ravel()[:n]
            np.multiply(du if part is None else du[part], k, out=fx)
            np.multiply(dv if part is None else dv[part], k, out=fy)
            fx += nx
            fy += ny
            if max(self.dsm.shape) < _REMAP_MAX_PX:
                hz = cv2.remap(self.dsm, sx, sy, cv2.INTER_NEAREST)
            else:
                c0, r0, c1, r1 = _window(bbox, 1.0, (0.0, 0.0), self.dsm.shape[1], self.dsm.shape[0])
                hz = cv2.remap(self.dsm[r0:r1, c0:c1], sx - np.float32(c0), sy - np.float32(r0), cv2.INTER_NEAREST,
                               borderMode=cv2.BORDER_REPLICATE)
            hz = hz.ravel()[:n]
            return hz if cap is None else np.minimum(hz, cap, out=hz)

        # Fixed-point steps z_{k+1} = h(m(z_k)) from the march's z0 (just below the first hit): z1 is the height
        # of the surface the ray is in there; where the next step leaves it unchanged the ray sees that surface
        # (a flat roof, the ground: most pixels). The others (walls, roof edges, trees, low objects) get one
        # more step; where z keeps jumping between the street and the roof the ray crosses a wall.
        tol = np.float32(_SURFACE_TOL_M)
        z1 = height(1.0 - z0s / big_h32)
        scale = 1.0 - z1 / big_h32
        z2 = height(scale)
        moved = np.flatnonzero(np.abs(z2 - z1) > tol)      # not settled on a surface after one step
        z2 = z2[moved]
        scale[moved] = k2 = 1.0 - z2 / big_h32
        wall = moved[np.abs(height(k2, moved) - z2) > tol]
        facade = facing = None
        if wall.size:
            # the ray entered the building through a wall and runs inside down to the ground (unless the
            # building is thinner than its horizontal travel): the facade takes the building's colour where the
            # ray meets the ground, one map pixel further from the wall so that bilinear sampling skips the street
            wu, wv = du[wall], dv[wall]
            dist = np.maximum(np.hypot(wu, wv), np.float32(1e-3))
            scale[wall] = 1.0 + 1.0 / dist
            facade = idx[wall]
            # a wall the camera sees faces it: towards nadir (map u east, v south)
            facing = np.empty((wall.size, 2), np.float32)
            np.divide(wu, dist, out=facing[:, 0])
            np.negative(facing[:, 0], out=facing[:, 0])
            np.divide(wv, dist, out=facing[:, 1])
        # the visible point: the ground point scaled about nadir, in the maps' frame
        gx, gy = ground_points()
        gx.ravel()[idx] = du * scale + np.float32(ox)
        gy.ravel()[idx] = dv * scale + np.float32(oy)
        return ViewMaps(gx, gy, facade, bbox, facing, origin)

    def _row_buffers(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Two (rows, _ROW_PX) float32 buffers holding n sample points, reused from frame to frame."""
        rows = max(1, -(-n // _ROW_PX))
        bufs = self._grids.get("rows")
        if bufs is None or bufs[0].shape[0] < rows:
            bufs = self._grids["rows"] = (np.zeros((rows, _ROW_PX), np.float32),
                                          np.zeros((rows, _ROW_PX), np.float32))
        return bufs

    def shade_facades(self, image: np.ndarray, view: ViewMaps, sun_deg: tuple[float, float] | None = None,
                      gamma: float = 2.2) -> np.ndarray:
        """Shade facade pixels in place (uint8 (h, w, 3)); returns ``image``.

        Without a sun: ``facade_gain`` times the roof colour. With ``sun_deg = (azimuth, elevation)`` (towards
        the sun, compass degrees) a facade is lit like a vertical wall: in linear light, relative to a sunlit
        roof (``ambient + direct = 1``, ``direct = (1 - ambient)`` at the sun's elevation), a wall gets half the
        sky (``ambient / 2``) plus ``direct cos(el) / sin(el) max(0, n . sun)``: walls facing away from the sun
        are dark, walls facing it at a low sun bright; then ``facade_gain`` (its albedo against the roof's) and
        the tone curve ``gamma``.
        """
        if view.facade is None:
            return image
        gain: np.ndarray | float = self.config.facade_gain
        if sun_deg is not None and view.facing is not None:
            az, el = (math.radians(a) for a in sun_deg)
            amb = self.config.ambient
            towards = view.facing @ np.array([math.sin(az), math.cos(az)], dtype=np.float32)
            direct = (1.0 - amb) * math.cos(el) / max(math.sin(el), 0.05) * np.maximum(towards, 0.0)
            gain = gain * np.minimum(0.5 * amb + direct, 1.5) ** (1.0 / gamma)
            gain = np.asarray(gain, np.float32).repeat(image.shape[-1])
        # the facade pixels' bytes as one 1-D gather/scatter (several times faster than rows of 3 bytes)
        c = image.shape[-1]
        at = (view.facade * c).repeat(c)
        for i in range(1, c):
            at[i::c] += i
        raw = image.reshape(-1)
        vals = raw[at] * gain
        raw[at] = np.clip(np.rint(vals, out=vals), 0, 255, out=vals)
        return image


def _tilted_rays(u: np.ndarray, v: np.ndarray, camera: CameraModel,
                 tilt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The nadir-camera offsets from the principal point (two (h, w) float32 planes) of the tilted camera's
    pixels at centred offsets ``u``, ``v``: the homography conjugated by the centring, per plane."""
    cu, cv = camera.center_px
    shift = np.array([[1.0, 0.0, cu], [0.0, 1.0, cv], [0.0, 0.0, 1.0]])
    c = np.linalg.inv(shift) @ tilt @ shift
    den = cv2.addWeighted(u, c[2, 0], v, c[2, 1], c[2, 2])
    return (cv2.divide(cv2.addWeighted(u, c[0, 0], v, c[0, 1], c[0, 2]), den),
            cv2.divide(cv2.addWeighted(u, c[1, 0], v, c[1, 1], c[1, 2]), den))


def sample_grid(view: ViewMaps, data: np.ndarray, factor: int) -> np.ndarray:
    """A coarse map-aligned field (cell ``c`` covers map pixels ``[c f, (c + 1) f)``) at the view's pixels."""
    return view.sample(data, border=cv2.BORDER_REPLICATE, scale=1.0 / factor, offset=0.5 / factor - 0.5)


__all__ = ["PerspectiveConfig", "ReliefView", "ViewMaps", "sample_grid", "tilt_homography", "tilted_corners"]
