"""A pinhole camera's view of the height model: relief displacement, facades and occlusion.

Why: one affine warp of the orthomap shows every roof on its own ground footprint. A real camera at height ``H``
sees a point at height ``h`` and ground distance ``r`` from nadir at ``r H / (H - h)``, i.e. displaced outward by
``r h / (H - h)``; it sees the facades that face the nadir point, and not the ground behind tall buildings. Real
maps without a height model keep the affine warp (``render.py``).

How (inverse mapping, vectorized with OpenCV): the ray of camera pixel ``q`` meets the ground at ``g0(q)`` and
crosses height ``z`` at ``m(z) = g0 + (c - g0) z / H`` (``c`` the nadir point): it moves towards nadir as it
rises, so every point the camera can see lies inside the ground footprint. The visible point is the ray's first
intersection from above, the largest ``z`` with ``h(m(z)) >= z``.

1. March: for ``N`` heights ``z_i`` from the footprint's tallest point down, the points ``m(z_i)`` of all rays
   form the (nadir) camera grid scaled by ``1 - z_i / H`` about the principal point, so each step is one small
   ``warpAffine`` of the height model sampled on a half-resolution camera grid, thresholded at ``z_i`` and
   max-combined: the first hit from the top, to within one step (dilated by a pixel so that no roof edge is
   lost to the half resolution; the next step verifies).
2. Refine at full resolution on the map's own height model: ``z1 = h(m(z_hit))`` is the exact height of the
   surface the ray entered (a flat roof: its height, the ground: 0). Where the next fixed-point step
   ``h(m(z_k))`` agrees with ``z_k`` (two steps are allowed) the ray sees that surface at ``m(z_k)``; where the
   steps keep jumping between the street and the roof the ray entered through a wall: a facade pixel, coloured
   from the building where the ray meets the ground (inside its footprint) and darkened by ``facade_gain``.

The result is a pair of per-pixel map coordinates for one ``cv2.remap`` of the map (and of the cast-shadow
field, which lives in map coordinates on the ground and roofs, so shadows stay on the surfaces they fall on).
Heights are clipped below ``0.95 H`` (a camera below the roofs has no downward view). Features thinner than one
march step (about ``H_max / N`` of height, ``r H_max / (N H)`` on the ground) may be missed at the frame edge.

Gimbal attitude errors (roll, pitch) rotate the camera about its centre: an image homography ``K R K^-1``
independent of the scene, composed into the same maps (or, for flat ground, into one ``warpPerspective``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..config import rng
from .camera import CameraModel, apply_affine

_NEAREST = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
_MAX_HEIGHT_FRACTION = 0.95
_SURFACE_TOL_M = 0.3    # h(m(z1)) within this of z1: the ray sees the surface (ridged roofs vary by less per px)


@dataclass(frozen=True)
class PerspectiveConfig:
    """The [perspective] section: render the height model in perspective (off by default: the affine warp).

    Applies only to maps with a height model (``map.use_dsm`` and a DSM); others keep the affine warp.
    """

    enabled: bool = False
    march_steps: int = field(default=12, metadata=rng(2, 64, doc="heights probed per ray (first-hit search)"))
    facade_gain: float = field(default=0.55, metadata=rng(0.0, 1.0, lo_open=True,
                                                           doc="facade brightness relative to its roof"))


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
    """Per-pixel level-0 map coordinates of one frame (``x``, ``y`` float32 (h, w)) and its facade pixels
    (bool (h, w), or None when there are none)."""

    x: np.ndarray
    y: np.ndarray
    facade: np.ndarray | None
    bbox: tuple[float, float, float, float]   # (x0, y0, x1, y1) level-0 map pixels holding every sample

    def sample(self, image: np.ndarray, level: int = 0, *, border: int = cv2.BORDER_CONSTANT,
               scale: float = 1.0, offset: float = 0.0) -> np.ndarray:
        """``image`` sampled (bilinear) at the maps: pyramid level ``level`` (``u_L = u_0 / 2**L``), or any grid
        with ``u_g = u_0 * scale + offset`` (e.g. a coarse shadow field). Only the window under the footprint
        is handed to ``cv2.remap`` (its sources must stay below 32767 px a side)."""
        f = scale / (1 << level)
        return remap_window(image, self.x, self.y, self.bbox, f, offset, cv2.INTER_LINEAR, border)


def remap_window(image: np.ndarray, x: np.ndarray, y: np.ndarray, bbox: tuple[float, float, float, float],
                 scale: float, offset: float, interpolation: int, border: int) -> np.ndarray:
    """``image`` at ``(x, y) * scale + offset``, remapped from the window of ``image`` under ``bbox`` (level-0
    map pixels, before the scaling): a view, so large maps cost nothing and stay within remap's limits."""
    h, w = image.shape[:2]
    c0 = max(0, int(math.floor(bbox[0] * scale + offset)) - 2)
    r0 = max(0, int(math.floor(bbox[1] * scale + offset)) - 2)
    c1 = min(w, int(math.ceil(bbox[2] * scale + offset)) + 3)
    r1 = min(h, int(math.ceil(bbox[3] * scale + offset)) + 3)
    if c1 <= c0 or r1 <= r0:
        return np.zeros(x.shape + image.shape[2:], image.dtype)
    if scale != 1.0 or offset != 0.0 or c0 or r0:
        x = x * np.float32(scale) + np.float32(offset - c0)
        y = y * np.float32(scale) + np.float32(offset - r0)
    return cv2.remap(image[r0:r1, c0:c1], x, y, interpolation, borderMode=border, borderValue=0)


class ReliefView:
    """Per-pixel maps of camera frames over one orthomap: its height model ``dsm_m`` ((H, W) metres above
    ground, level 0) in perspective, and/or a tilted camera. ``dsm_m=None``: flat ground (tilt only).

    Not thread-safe (cached grids); one per renderer.
    """

    def __init__(self, dsm_m: np.ndarray | None, config: PerspectiveConfig | None = None) -> None:
        self.dsm = None if dsm_m is None else np.ascontiguousarray(dsm_m, dtype=np.float32)
        self.config = config or PerspectiveConfig(enabled=True)
        self._grids: dict[tuple[int, int], np.ndarray] = {}

    def _grid(self, w: int, h: int) -> np.ndarray:
        key = (w, h)
        if key not in self._grids:
            u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
            self._grids[key] = np.dstack([u, v])
        return self._grids[key]

    def maps(self, affine: np.ndarray, altitude_m: float, camera: CameraModel,
             tilt: np.ndarray | None = None) -> ViewMaps | None:
        """The maps of the frame whose nadir camera->map affine (level 0) is ``affine`` at ``altitude_m``, with
        the tilt homography ``tilt`` (``tilt_homography``); None when the footprint is flat and the camera
        untilted (the affine warp is exact then)."""
        w, h = camera.width_px, camera.height_px
        a = np.asarray(affine, dtype=np.float64)
        if self.dsm is None:
            return None if tilt is None else self._flat(a, camera, tilt)
        big_h = float(altitude_m)
        margin = 0
        if tilt is not None:
            shift = np.abs(tilted_corners(camera, tilt) - camera.corners_px()).max()
            margin = int(math.ceil(shift)) + 2
        # the nadir camera grid (with a margin for tilted rays) at half resolution: q_full = 2 q_half + 0.5 - m
        wh, hh = (w + 2 * margin + 1) // 2, (h + 2 * margin + 1) // 2
        half = a.copy()
        half[:, :2] = a[:, :2] * 2.0
        half[:, 2] = a[:, 2] + (0.5 - margin) * (a[:, 0] + a[:, 1])
        heights = cv2.warpAffine(self.dsm, half, (wh, hh), flags=_NEAREST, borderMode=cv2.BORDER_CONSTANT)
        z_raw = float(cv2.minMaxLoc(heights)[1])
        z_top = min(z_raw, _MAX_HEIGHT_FRACTION * big_h)
        if z_top <= 0.0:
            return None if tilt is None else self._flat(a, camera, tilt)
        cu, cv = camera.center_px
        chu, chv = (cu + margin - 0.5) / 2.0, (cv + margin - 0.5) / 2.0
        z_hit = np.zeros_like(heights)
        probe = np.empty_like(heights)
        steps = self.config.march_steps
        for i in range(steps):
            z = z_top * (steps - i) / steps
            s = 1.0 - z / big_h
            m = np.float64([[s, 0.0, chu * (1.0 - s)], [0.0, s, chv * (1.0 - s)]])
            cv2.warpAffine(heights, m, (wh, hh), dst=probe, flags=_NEAREST, borderMode=cv2.BORDER_REPLICATE)
            cv2.threshold(probe, z - 1e-4, z, cv2.THRESH_BINARY, dst=probe)
            cv2.max(z_hit, probe, dst=z_hit)
        z_hit = cv2.dilate(z_hit, np.ones((3, 3), np.uint8))
        # full resolution: nadir pixel of every camera pixel, its ray's ground point g0 and direction to nadir
        grid = self._grid(w, h)
        if tilt is None:
            nadir = grid
            z0 = cv2.resize(z_hit, (w, h), interpolation=cv2.INTER_NEAREST) if margin == 0 else None
        else:
            nadir = cv2.perspectiveTransform(grid.reshape(1, -1, 2), tilt).reshape(h, w, 2)
            z0 = None
        if z0 is None:   # nadir pixel -> half-grid pixel: (q + m - 0.5) / 2
            z0 = cv2.remap(z_hit, (nadir + np.float32(margin - 0.5)) * np.float32(0.5), None, cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_REPLICATE)
        c_map = a[:, :2] @ np.array([cu, cv]) + a[:, 2]
        if tilt is None:   # separable: a row plus a column
            u, v = grid[0, :, 0] - np.float32(cu), grid[:, 0, 1] - np.float32(cv)
            dx = (np.float32(a[0, 0]) * u)[None, :] + (np.float32(a[0, 1]) * v)[:, None]
            dy = (np.float32(a[1, 0]) * u)[None, :] + (np.float32(a[1, 1]) * v)[:, None]
        else:
            nu, nv = nadir[..., 0] - np.float32(cu), nadir[..., 1] - np.float32(cv)
            dx = nu * np.float32(a[0, 0]) + nv * np.float32(a[0, 1])
            dy = nu * np.float32(a[1, 0]) + nv * np.float32(a[1, 1])
        # the ray of a pixel: m(z) = c + (g0 - c) (1 - z / H) = g0 + k z, with g0 - c = (dx, dy), k = -(dx, dy) / H
        gx, gy = dx + np.float32(c_map[0]), dy + np.float32(c_map[1])
        kx, ky = dx * np.float32(-1.0 / big_h), dy * np.float32(-1.0 / big_h)
        cap = _MAX_HEIGHT_FRACTION * big_h if z_raw > _MAX_HEIGHT_FRACTION * big_h else None

        def along(z: np.ndarray, sel: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
            if sel is None:
                return gx + kx * z, gy + ky * z
            return gx.ravel()[sel] + kx.ravel()[sel] * z, gy.ravel()[sel] + ky.ravel()[sel] * z

        corners = apply_affine(a, tilted_corners(camera, tilt))
        bbox = (*corners.min(axis=0), *corners.max(axis=0))

        def height(mx: np.ndarray, my: np.ndarray) -> np.ndarray:
            hz = remap_window(self.dsm, mx, my, bbox, 1.0, 0.0, cv2.INTER_NEAREST, cv2.BORDER_REPLICATE)
            return hz if cap is None else np.minimum(hz, np.float32(cap), out=hz)

        # fixed-point steps z_{k+1} = h(m(z_k)) from the march's z0: where two agree (within the tolerance) the
        # ray sees that surface; where they keep moving it crosses a wall, coloured from a sample inside it
        tol = _SURFACE_TOL_M
        z1 = height(*along(z0))
        mx, my = along(z1)
        z2 = height(mx, my)
        moving = cv2.absdiff(z2, z1) > tol
        if not moving.any():
            return ViewMaps(x=mx, y=my, facade=None, bbox=bbox)
        sel = np.flatnonzero(moving)
        z2s = z2.ravel()[sel]
        z3s = height(*(_rows(c) for c in along(z2s, sel))).ravel()[:sel.size]
        seen = np.abs(z3s - z2s) <= tol
        xs, ys = along(z2s, sel)
        mx.ravel()[sel[seen]], my.ravel()[sel[seen]] = xs[seen], ys[seen]
        if seen.all():
            return ViewMaps(x=mx, y=my, facade=None, bbox=bbox)
        # a wall: the ray entered the building through it and runs inside down to the ground (unless the building
        # is thinner than its horizontal travel). The facade takes the colour of the building where the ray meets
        # the ground, one pixel further from the wall so that bilinear sampling does not mix in the street.
        wall = sel[~seen]
        dxw, dyw = dx.ravel()[wall], dy.ravel()[wall]
        push = 1.0 / np.maximum(np.hypot(dxw, dyw), np.float32(1e-3))
        mx.ravel()[wall] = gx.ravel()[wall] + dxw * push
        my.ravel()[wall] = gy.ravel()[wall] + dyw * push
        facade = np.zeros(moving.shape, bool)
        facade.ravel()[wall] = True
        return ViewMaps(x=mx, y=my, facade=facade, bbox=bbox)

    def _flat(self, a: np.ndarray, camera: CameraModel, tilt: np.ndarray) -> ViewMaps:
        """Flat ground seen by a tilted camera: map pixel = affine(tilt(q)), a homography."""
        grid = self._grid(camera.width_px, camera.height_px)
        hom = np.vstack([a, [0.0, 0.0, 1.0]]) @ tilt
        x, y = cv2.split(cv2.perspectiveTransform(grid.reshape(1, -1, 2), hom).reshape(grid.shape))
        corners = apply_affine(a, tilted_corners(camera, tilt))
        return ViewMaps(x=x, y=y, facade=None, bbox=(*corners.min(axis=0), *corners.max(axis=0)))

    def shade_facades(self, image: np.ndarray, view: ViewMaps) -> np.ndarray:
        """Darken facade pixels in place (uint8 (h, w, 3)) by ``facade_gain``; returns ``image``."""
        if view.facade is not None:
            gain = np.where(view.facade, np.float32(self.config.facade_gain), np.float32(1.0))
            cv2.multiply(image, cv2.merge([gain, gain, gain]), dst=image, dtype=cv2.CV_8U)
        return image


def _rows(a: np.ndarray, width: int = 1024) -> np.ndarray:
    """A 1-D float32 array as a (rows, width) image, zero-padded (remap wants fewer than 32767 rows)."""
    out = np.zeros(-(-a.size // width) * width, np.float32)
    out[:a.size] = a
    return out.reshape(-1, width)


def sample_grid(view: ViewMaps, data: np.ndarray, factor: int) -> np.ndarray:
    """A coarse map-aligned field (cell ``c`` covers map pixels ``[c f, (c + 1) f)``) at the view's pixels."""
    return view.sample(data, border=cv2.BORDER_REPLICATE, scale=1.0 / factor, offset=0.5 / factor - 0.5)


__all__ = ["PerspectiveConfig", "ReliefView", "ViewMaps", "sample_grid", "tilt_homography", "tilted_corners"]
