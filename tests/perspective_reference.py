"""The OpenCV/NumPy implementation of the perspective maps and facade shading (perspective v5) that
``sensors.perspective_kernels`` replaced: the reference its compiled kernels are checked against, bit for bit."""

from __future__ import annotations

import math

import cv2
import numpy as np

from aerial_loc_env.sensors.camera import CameraModel, apply_affine
from aerial_loc_env.sensors.perspective import (
    _MARCH_FACTOR,
    _MAX_HEIGHT_FRACTION,
    _REMAP_MAX_PX,
    _SURFACE_TOL_M,
    ReliefView,
    ViewMaps,
    _window,
)

_ROW_PX = 1024
_NEAREST = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP   # OpenCV's nearest warp, its matrix the inverse map


def reference_tilt(camera: CameraModel, roll_rad: float, pitch_rad: float) -> np.ndarray:
    """``tilt_homography``'s matrix as NumPy products: ``K R_roll R_pitch K^-1``."""
    fu = (camera.width_px / 2.0) / math.tan(math.radians(camera.hfov_deg) / 2.0)
    cu, cv = camera.center_px
    k = np.array([[fu, 0.0, cu], [0.0, fu / camera.pixel_aspect, cv], [0.0, 0.0, 1.0]])
    cr, sr, cp, sp = math.cos(roll_rad), math.sin(roll_rad), math.cos(pitch_rad), math.sin(pitch_rad)
    r_roll = np.array([[cr, 0.0, sr], [0.0, 1.0, 0.0], [-sr, 0.0, cr]])
    r_pitch = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])
    return k @ r_roll @ r_pitch @ np.linalg.inv(k)


def reference_tilted_corners(camera: CameraModel, tilt: np.ndarray | None) -> np.ndarray:
    """``tilted_corners`` by ``cv2.perspectiveTransform``."""
    corners = camera.corners_px()
    if tilt is None:
        return corners
    return cv2.perspectiveTransform(corners.reshape(1, 4, 2), tilt).reshape(4, 2)


def _centred_planes(camera: CameraModel) -> tuple[np.ndarray, np.ndarray]:
    """(h, w) float32 pixel offsets from the principal point (u, v)."""
    cu, cv = camera.center_px
    u, v = np.meshgrid(np.arange(camera.width_px, dtype=np.float32) - np.float32(cu),
                       np.arange(camera.height_px, dtype=np.float32) - np.float32(cv))
    return np.ascontiguousarray(u), np.ascontiguousarray(v)


def reference_maps(self: ReliefView, affine: np.ndarray, altitude_m: float, camera: CameraModel,
                   tilt: np.ndarray | None = None, origin_px: tuple[int, int] = (0, 0)) -> ViewMaps | None:
    """Perspective v5's ``ReliefView.maps``: OpenCV warps of the march grid, 1-D remaps of the relief pixels."""
    a = np.asarray(affine, dtype=np.float64)
    (w, h), (cu, cv) = (camera.width_px, camera.height_px), camera.center_px
    nadir_x, nadir_y = a[:, :2] @ np.array([cu, cv]) + a[:, 2]     # the map pixel below the camera
    corners = apply_affine(a, reference_tilted_corners(camera, tilt))
    bbox = (*corners.min(axis=0), *corners.max(axis=0))
    ru, rv = _centred_planes(camera)
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
    bx, by = _row_buffers(self, idx.size)
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


def _row_buffers(self: ReliefView, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Two (rows, _ROW_PX) float32 buffers holding n sample points, reused from frame to frame."""
    rows = max(1, -(-n // _ROW_PX))
    bufs = self._grids.get("rows")
    if bufs is None or bufs[0].shape[0] < rows:
        bufs = self._grids["rows"] = (np.zeros((rows, _ROW_PX), np.float32),
                                      np.zeros((rows, _ROW_PX), np.float32))
    return bufs


def facade_gains_numpy(self: ReliefView, view: ViewMaps, sun_deg: tuple[float, float] | None = None,
                       gamma: float = 2.2) -> np.ndarray:
    """``ReliefView.facade_gains`` as NumPy computed it before its kernel: a float64 constant without a sun, else
    NumPy's float32 arithmetic on the facings (the sun's direction added in index order, libm's ``powf``)."""
    if sun_deg is None or view.facing is None:
        return np.full(0 if view.facade is None else view.facade.size, self.config.facade_gain)
    az, el = (math.radians(a) for a in sun_deg)
    amb = self.config.ambient
    sun = np.array([math.sin(az), math.cos(az)], dtype=np.float32)
    towards = (np.float32(0.0) + view.facing[:, 0] * sun[0]) + view.facing[:, 1] * sun[1]
    direct = (1.0 - amb) * math.cos(el) / max(math.sin(el), 0.05) * np.maximum(towards, 0.0)
    lit = np.minimum(0.5 * amb + direct, 1.5)
    p = np.float32(1.0 / gamma)
    return np.asarray(self.config.facade_gain * np.array([v ** p for v in lit], np.float32), np.float32)


def reference_shade_facades(self: ReliefView, image: np.ndarray, view: ViewMaps,
                            sun_deg: tuple[float, float] | None = None, gamma: float = 2.2) -> np.ndarray:
    """Perspective v5's ``ReliefView.shade_facades``: the facade pixels' bytes as one 1-D NumPy gather/scatter
    (the gains, unchanged, from the library)."""
    if view.facade is None:
        return image
    c = image.shape[-1]
    gain = facade_gains_numpy(self, view, sun_deg, gamma).repeat(c)
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
