"""Two-epoch real image pairs: two co-registered images of the same ground at two dates, put on one grid.

A real pair is what a map database (epoch A, the earlier image) and a drone's camera (epoch B, the later one)
differ by in reality. The two images come with their own georeferences (GeoTIFF tags, a world file + CRS, or a
stated ground sampling for images without one: those are aligned by their centres), which may differ by a
fraction of a pixel, have non-square pixels or different ground samplings. ``load_pair`` honours them:

1. **One grid** (``pair_grid``): square pixels at the finer of the two samplings over B's extent. When B already
   has square pixels at that sampling, the grid is B's own (B is then not resampled); otherwise it is a local
   tangent plane centred on B (``LocalTangentGeoref``), so that grid metres are ground metres.
2. **Resampling** (``resample_onto``): each image goes through its own georeference to lat/lon and onto the grid
   (bilinear; an image finer than the grid is area-averaged first, never aliased). The mapping is evaluated
   on a lattice and interpolated between its knots (exact for the affine mappings of two north-up grids).
   The grid is cropped to where A covers it.
3. **Residual misregistration** (``measure_shift``): what the georeferences leave, measured by phase
   correlation of the luma gradients (robust to the colour and illumination changes between epochs) in several
   windows across the overlap; the median over windows is the shift, the median deviation its spread. Beyond
   ``max_shift_m`` the pair is refused with an error naming the shift; ``correct_shift`` removes a small
   constant shift (resampling A once more with it), when the windows agree on it.

Sign convention: ``(dx_px, dy_px)`` is how far B's content sits from A's on the grid, columns right and rows
down: B(u, v) = A(u - dx, v - dy). In metres east and north: ``(dx * gsd, -dy * gsd)``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps.geo import Georeference, LocalTangentGeoref
from aerial_loc_env.world.maps.orthomap import Orthomap

#: the default bound on the residual misregistration (metres on the ground): beyond it a benchmark's truth (B's
#: georeference) would differ from the map's (A's) by a good part of the errors being measured
DEFAULT_MAX_SHIFT_M = 1.5
#: ``correct_shift`` removes a constant shift only when the windows agree on it within this many grid pixels
#: (median absolute deviation); beyond, the images differ by more than a shift (rotation, scale, relief)
MAX_CORRECTED_SPREAD_PX = 3.0
#: the side of a registration window, grid pixels (smaller on smaller overlaps, never below MIN_WINDOW_PX)
WINDOW_PX = 512
MIN_WINDOW_PX = 32
#: registration windows along each axis (at most)
WINDOWS_PER_AXIS = 3
#: phase correlation refined to 1/UPSAMPLE px; a window's own shift (for the spread) is looked for within NEAR_PX
#: of the shift all windows agree on
UPSAMPLE = 32
NEAR_PX = 4.0
#: spacing of the lattice on which a georeference mapping is evaluated, grid pixels
LATTICE_PX = 32
#: relative difference of the two ground pixel sides below which pixels count as square
SQUARE_TOL = 1e-3


@dataclass(frozen=True)
class Registration:
    """The residual misregistration of a pair on its grid (see the module doc for the sign convention)."""

    dx_px: float
    dy_px: float
    gsd_m: float
    windows: int              # windows the median is over
    spread_px: float          # median absolute deviation of the windows' shifts from the median (hypot)
    window_px: int
    corrected: tuple[float, float] | None = None   # the shift removed from A (px), when corrected

    @property
    def east_m(self) -> float:
        return self.dx_px * self.gsd_m

    @property
    def north_m(self) -> float:
        return -self.dy_px * self.gsd_m

    @property
    def shift_m(self) -> float:
        return math.hypot(self.east_m, self.north_m)

    def describe(self) -> str:
        """One line: the shift in pixels and metres, over how many windows, how consistent."""
        text = (f"misregistration {self.dx_px:+.2f}, {self.dy_px:+.2f} px ({self.east_m:+.2f} m east, "
                f"{self.north_m:+.2f} m north; {self.shift_m:.2f} m) over {self.windows} window(s) of "
                f"{self.window_px} px, spread {self.spread_px:.2f} px")
        if self.corrected is not None:
            text += (f", after removing a constant shift of {self.corrected[0]:+.2f}, {self.corrected[1]:+.2f} px "
                     "from epoch A")
        return text


@dataclass(frozen=True)
class PairGrid:
    """The common grid: square pixels of ``gsd_m`` metres, ``width_px`` x ``height_px``, and its georeference."""

    georef: Georeference
    width_px: int
    height_px: int
    gsd_m: float
    own: bool                 # True: B's own pixel grid (B is not resampled)

    def describe(self) -> str:
        how = "B's own pixel grid" if self.own else "a local tangent plane centred on B"
        return f"{self.width_px} x {self.height_px} px at {self.gsd_m:.4g} m ({how})"


@dataclass(frozen=True, eq=False)
class Pair:
    """A loaded pair: ``surveyed`` (epoch A, the map database) and ``ground`` (epoch B, what the camera sees)
    on one grid (same size, pixels and georeference), and the residual misregistration measured on it."""

    surveyed: Orthomap
    ground: Orthomap
    grid: PairGrid
    registration: Registration


# ------------------------------------------------------------------------------------------ loading
def load_pair(path_a: str | os.PathLike, path_b: str | os.PathLike, *, gsd_m: float | None = None,
              gsd_b_m: float | None = None, crs: str | int | None = None,
              max_shift_m: float | None = DEFAULT_MAX_SHIFT_M, correct_shift: bool = False,
              name: str | None = None, where: str = "pair") -> Pair:
    """Load a two-epoch pair onto one grid and check its co-registration (see the module doc).

    gsd_m: ground metres per pixel of images without a georeference (``gsd_b_m``: of B, when it differs).
    crs: the CRS of world files that have no .prj / .aux.xml beside them.
    max_shift_m: refuse a residual misregistration beyond this (None: never refuse, only measure).
    correct_shift: remove a constant misregistration from A (checked against ``max_shift_m`` afterwards).
    """
    pa, pb = Path(path_a).expanduser(), Path(path_b).expanduser()
    for label, p in (("A (the map database's epoch)", pa), ("B (the camera's epoch)", pb)):
        if not p.is_file():
            raise MapError(f"{where}: image {label} '{p}' does not exist or is not a file (resolved to "
                           f"{p.resolve()}); give two co-registered image files of the same ground")
    if max_shift_m is not None and not (math.isfinite(max_shift_m) and max_shift_m > 0):
        raise MapError(f"{where}: max_shift_m = {max_shift_m!r} must be a positive number of metres (or None)")

    a, b = read_image(pa, gsd_m, crs), read_image(pb, gsd_b_m if gsd_b_m is not None else gsd_m, crs)
    georeferenced = [not _nominal(m) for m in (a, b)]
    if georeferenced[0] != georeferenced[1]:
        which, other = (pa, pb) if georeferenced[0] else (pb, pa)
        raise MapError(f"{where}: {which.name} has a georeference but {other.name} has none (it was given a "
                       "ground sampling only); the two cannot be placed on one grid. Give both a georeference "
                       "(a world file + .prj, or GeoTIFF tags) or neither (gsd_m: they are then aligned by "
                       "their centres)")
    grid = pair_grid(a, b)
    b_grid, b_bad = resample_onto(b, grid)
    a_grid, a_bad = resample_onto(a, grid)
    box = _overlap_box(a_bad, b_bad, grid, pa, pb, where)
    registration = measure_shift(a_grid[box], b_grid[box], a_bad[box] | b_bad[box], grid.gsd_m, where=where)
    if correct_shift:
        spread = registration.spread_px
        if spread > MAX_CORRECTED_SPREAD_PX:
            raise MapError(f"{where}: map.correct_shift removes a constant shift, but the windows disagree by "
                           f"{spread:.2f} px (median deviation; at most {MAX_CORRECTED_SPREAD_PX:g} px): "
                           f"{registration.describe()}. The images differ by more than a shift (rotation, scale "
                           "or relief): co-register them first (e.g. gdalwarp with ground control points)")
        shift = (registration.dx_px, registration.dy_px)
        a_grid, a_bad = resample_onto(a, grid, shift_px=shift)
        residual = measure_shift(a_grid[box], b_grid[box], a_bad[box] | b_bad[box], grid.gsd_m, where=where)
        registration = Registration(residual.dx_px, residual.dy_px, residual.gsd_m, residual.windows,
                                    residual.spread_px, residual.window_px, corrected=shift)
    if max_shift_m is not None and registration.shift_m > max_shift_m:
        fix = ("co-register the images (e.g. gdalwarp with ground control points)" if correct_shift else
               "co-register them (e.g. gdalwarp), or remove a small constant shift with map.correct_shift = "
               "true (correct_shift=True)")
        raise MapError(f"{where}: {pa.name} (A) and {pb.name} (B) are misregistered by {registration.shift_m:.2f} m "
                       f"on the ground, beyond map.max_shift_m = {max_shift_m:g} m: {registration.describe()}. "
                       f"A benchmark's truth is B's georeference, so every estimate would carry that offset; {fix}, "
                       "or raise map.max_shift_m to accept it")
    label = name or f"{pa.stem}"
    note = f"resampled onto {grid.describe()}; {registration.describe()}"
    u0, v0 = box[1].start, box[0].start
    gref = grid.georef.shifted(u0, v0)
    surveyed = Orthomap(np.ascontiguousarray(a_grid[box]), grid.gsd_m, grid.gsd_m, gref,
                        nodata=_mask(a_bad[box]), name=f"{label}_A", source=f"{pa} [pair epoch A; {note}]")
    ground = Orthomap(np.ascontiguousarray(b_grid[box]), grid.gsd_m, grid.gsd_m, gref,
                      nodata=_mask(a_bad[box] | b_bad[box]), name=f"{label}_B",
                      source=f"{pb} [pair epoch B; {note}]")
    return Pair(surveyed, ground, grid, registration)


def read_image(path: Path, gsd_m: float | None = None, crs: str | int | None = None) -> Orthomap:
    """One real image, whole, through its georeference; ``gsd_m`` (ground metres per pixel) only where the file
    has none (else that file's own error is raised)."""
    from aerial_loc_env.world.maps.io import load_orthomap

    kw = {"crs": crs} if crs is not None else {}
    try:
        return load_orthomap(path, mmap=False, **kw)
    except MapError as exc:
        if gsd_m is None or "no georeference" not in str(exc):
            raise
    return load_orthomap(path, gsd_m=gsd_m, mmap=False, **kw)


def _nominal(m: Orthomap) -> bool:
    """Whether a map was loaded without a georeference (a stated sampling and a nominal origin)."""
    return isinstance(m.georef, LocalTangentGeoref) and "no georeference" in (m.source or "")


def _mask(bad: np.ndarray) -> np.ndarray | None:
    return np.ascontiguousarray(bad) if bad.any() else None


def _overlap_box(a_bad: np.ndarray, b_bad: np.ndarray, grid: PairGrid, pa: Path, pb: Path,
                 where: str) -> tuple[slice, slice]:
    """The grid's rows and columns where A has data somewhere (the bounding box of A's valid pixels)."""
    ok = ~a_bad & ~b_bad
    rows, cols = np.flatnonzero(ok.any(axis=1)), np.flatnonzero(ok.any(axis=0))
    if rows.size < MIN_WINDOW_PX or cols.size < MIN_WINDOW_PX:
        w_m, h_m = cols.size * grid.gsd_m, rows.size * grid.gsd_m
        raise MapError(f"{where}: {pa.name} (A) and {pb.name} (B) overlap on only {w_m:.1f} x {h_m:.1f} m "
                       f"({cols.size} x {rows.size} px at {grid.gsd_m:.3g} m) of valid data; a pair shows the same "
                       "ground twice: check that the two files (and their georeferences) belong together")
    return slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1)


# ------------------------------------------------------------------------------------------ the grid
def pair_grid(a: Orthomap, b: Orthomap) -> PairGrid:
    """The common grid of a pair: square pixels at the finer of the two samplings over B's extent (B's own
    grid when its pixels are square at that sampling)."""
    g = min(a.gsd_x_m, a.gsd_y_m, b.gsd_x_m, b.gsd_y_m)
    square = abs(b.gsd_x_m / b.gsd_y_m - 1.0) <= SQUARE_TOL
    if square and min(b.gsd_x_m, b.gsd_y_m) <= g * (1.0 + SQUARE_TOL):
        return PairGrid(b.georef, b.width_px, b.height_px, math.sqrt(b.gsd_x_m * b.gsd_y_m), own=True)
    w, h = max(2, int(math.floor(b.width_m / g + 1e-6))), max(2, int(math.floor(b.height_m / g + 1e-6)))
    lat, lon = b.georef.pixel_to_latlon((b.width_px - 1) / 2.0, (b.height_px - 1) / 2.0)
    georef = LocalTangentGeoref(float(np.ravel(lat)[0]), float(np.ravel(lon)[0]), g, g, (w - 1) / 2.0, (h - 1) / 2.0)
    return PairGrid(georef, w, h, g, own=False)


def source_coords(grid: PairGrid, src: Orthomap, shift_px: tuple[float, float] = (0.0, 0.0)
                  ) -> tuple[np.ndarray, np.ndarray]:
    """For every grid pixel (u, v), the pixel of ``src`` that shows the same ground point as grid pixel
    (u - dx, v - dy) (``shift_px`` = (dx, dy)), as two (H, W) float64 arrays; through lat/lon, evaluated on a
    lattice of ``LATTICE_PX`` and interpolated bilinearly between its knots."""
    w, h = grid.width_px, grid.height_px
    us = np.unique(np.r_[np.arange(0, w, LATTICE_PX), w - 1]).astype(np.float64)
    vs = np.unique(np.r_[np.arange(0, h, LATTICE_PX), h - 1]).astype(np.float64)
    uu, vv = np.meshgrid(us, vs)
    if src.georef is grid.georef:
        su, sv = uu - shift_px[0], vv - shift_px[1]
    else:
        lat, lon = grid.georef.pixel_to_latlon(uu - shift_px[0], vv - shift_px[1])
        su, sv = src.georef.latlon_to_pixel(lat, lon)
    return _interpolate(su, us, vs, w, h), _interpolate(sv, us, vs, w, h)


def _interpolate(values: np.ndarray, us: np.ndarray, vs: np.ndarray, w: int, h: int) -> np.ndarray:
    """Bilinear interpolation of a lattice (len(vs), len(us)) at knots ``us``/``vs`` to every pixel (h, w)."""
    def weights(knots: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        x = np.arange(n, dtype=np.float64)
        if knots.size == 1:
            return np.zeros(n, np.int64), np.zeros(n)
        i = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, knots.size - 2)
        return i, (x - knots[i]) / (knots[i + 1] - knots[i])

    iu, tu = weights(us, w)
    iv, tv = weights(vs, h)
    j1 = np.minimum(iu + 1, us.size - 1)
    rows = values[:, iu] * (1.0 - tu) + values[:, j1] * tu                     # (len(vs), w)
    i1 = np.minimum(iv + 1, vs.size - 1)
    return rows[iv] * (1.0 - tv)[:, None] + rows[i1] * tv[:, None]


def resample_onto(src: Orthomap, grid: PairGrid, *, shift_px: tuple[float, float] = (0.0, 0.0)
                  ) -> tuple[np.ndarray, np.ndarray]:
    """``src`` on ``grid`` (see ``source_coords``): (H, W, 3) uint8 and the (H, W) mask of grid pixels without
    data (outside ``src`` or on its no-data). A source finer than the grid is area-averaged to about the grid's
    sampling first; an exact integer-offset mapping is a copy (no interpolation)."""
    su, sv = source_coords(grid, src, shift_px)
    rgb = np.asarray(src.rgb)
    bad = None if src.nodata is None else np.asarray(src.nodata)
    fu, fv = src.gsd_x_m / grid.gsd_m, src.gsd_y_m / grid.gsd_m        # source pixels per grid pixel, < 1: finer
    du, dv = np.rint(su[0, 0]), np.rint(sv[0, 0])
    uu, vv = np.meshgrid(np.arange(grid.width_px), np.arange(grid.height_px))
    if abs(fu - 1.0) <= SQUARE_TOL and abs(fv - 1.0) <= SQUARE_TOL and \
            np.abs(su - uu - du).max() < 1e-6 and np.abs(sv - vv - dv).max() < 1e-6:
        return _copy(rgb, bad, int(du), int(dv), grid)
    if fu < 1.0 / 1.25 or fv < 1.0 / 1.25:   # area-average the source down to the grid's sampling first
        h, w = rgb.shape[:2]
        size = (max(2, round(w * fu)), max(2, round(h * fv)))
        sx, sy = size[0] / w, size[1] / h
        rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)
        if bad is not None:
            bad = cv2.resize(bad.astype(np.float32), size, interpolation=cv2.INTER_AREA) > 0
        su, sv = (su + 0.5) * sx - 0.5, (sv + 0.5) * sy - 0.5
    mx, my = su.astype(np.float32), sv.astype(np.float32)
    out = cv2.remap(np.ascontiguousarray(rgb), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                    borderValue=(0, 0, 0))
    valid = np.ones(rgb.shape[:2], np.float32) if bad is None else (~bad).astype(np.float32)
    cover = cv2.remap(valid, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
    return out, cover < 1.0 - 1e-3


def _copy(rgb: np.ndarray, bad: np.ndarray | None, du: int, dv: int, grid: PairGrid
          ) -> tuple[np.ndarray, np.ndarray]:
    """The grid's window of ``rgb`` starting at source pixel (du, dv), no-data outside the source."""
    h, w = rgb.shape[:2]
    out = np.zeros((grid.height_px, grid.width_px, 3), np.uint8)
    mask = np.ones((grid.height_px, grid.width_px), bool)
    u0, v0 = max(0, -du), max(0, -dv)
    u1, v1 = min(grid.width_px, w - du), min(grid.height_px, h - dv)
    if u1 > u0 and v1 > v0:
        out[v0:v1, u0:u1] = rgb[v0 + dv:v1 + dv, u0 + du:u1 + du]
        mask[v0:v1, u0:u1] = False if bad is None else bad[v0 + dv:v1 + dv, u0 + du:u1 + du]
    return out, mask


# ------------------------------------------------------------------------------------------ registration
def _gradient(gray: np.ndarray) -> np.ndarray:
    gx = cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)
    return cv2.magnitude(gx, gy)


def _luma(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY).astype(np.float32)


def measure_shift(a_rgb: np.ndarray, b_rgb: np.ndarray, bad: np.ndarray | None, gsd_m: float, *,
                  where: str = "pair") -> Registration:
    """The residual misregistration of two images on one grid (see the module doc): phase correlation of the
    luma gradient magnitudes over up to ``WINDOWS_PER_AXIS`` x ``WINDOWS_PER_AXIS`` (overlapping) windows of
    ``WINDOW_PX`` (smaller on small images) that hold no no-data. The windows' whitened cross-power spectra are
    summed (one correlation surface over all of them: the shift they agree on, robust to a window whose ground
    changed), its peak refined to 1/``UPSAMPLE`` px; each window's own peak near it gives the spread."""
    if bad is not None and bad.any():        # peel no-data strips off the edges (a shifted grid's border)
        rows, cols = _valid_core(bad)
        a_rgb, b_rgb, bad = a_rgb[rows, cols], b_rgb[rows, cols], bad[rows, cols]
    ga, gb = _gradient(_luma(a_rgb)), _gradient(_luma(b_rgb))
    h, w = ga.shape
    side = WINDOW_PX
    while side > min(h, w) and side > MIN_WINDOW_PX:
        side //= 2
    if side > min(h, w):
        raise MapError(f"{where}: the overlap ({w} x {h} px) is smaller than one {MIN_WINDOW_PX} px registration "
                       "window")
    hann = cv2.createHanningWindow((side, side), cv2.CV_32F)

    def starts(n: int) -> list[int]:
        k = max(1, min(WINDOWS_PER_AXIS, math.ceil(n / side) + 1))
        return sorted({int(round(x)) for x in np.linspace(0, n - side, k)})

    spectra = []
    for y in starts(h):
        for x in starts(w):
            if bad is not None and bad[y:y + side, x:x + side].any():
                continue
            wa, wb = ga[y:y + side, x:x + side], gb[y:y + side, x:x + side]
            if float(wa.std()) < 1e-3 or float(wb.std()) < 1e-3:
                continue
            spectra.append(cross_power(wa, wb, hann))
    if not spectra:
        raise MapError(f"{where}: no {side} px window of the overlap is free of no-data and textured in both "
                       "images; the misregistration cannot be measured")
    dx, dy, _ = correlation_peak(sum(spectra) / len(spectra))
    each = np.asarray([correlation_peak(s, near=(dx, dy))[:2] for s in spectra])
    spread = float(np.median(np.hypot(each[:, 0] - dx, each[:, 1] - dy)))
    return Registration(dx, dy, float(gsd_m), len(spectra), spread, side)


def _valid_core(bad: np.ndarray) -> tuple[slice, slice]:
    """Rows and columns left after peeling, one border line at a time (the one with most no-data first), the
    border lines that hold no-data; stops at ``MIN_WINDOW_PX``."""
    top, left, bottom, right = 0, 0, bad.shape[0], bad.shape[1]
    while bottom - top > MIN_WINDOW_PX and right - left > MIN_WINDOW_PX:
        counts = (int(bad[top, left:right].sum()), int(bad[bottom - 1, left:right].sum()),
                  int(bad[top:bottom, left].sum()), int(bad[top:bottom, right - 1].sum()))
        side = int(np.argmax(counts))
        if counts[side] == 0:
            break
        if side == 0:
            top += 1
        elif side == 1:
            bottom -= 1
        elif side == 2:
            left += 1
        else:
            right -= 1
    return slice(top, bottom), slice(left, right)


def cross_power(a: np.ndarray, b: np.ndarray, window: np.ndarray) -> np.ndarray:
    """The whitened cross-power spectrum of two equal windows (its inverse DFT peaks at their shift)."""
    prod = np.fft.fft2((a - a.mean()) * window) * np.fft.fft2((b - b.mean()) * window).conj()
    mag = np.abs(prod)
    return prod / (mag + 1e-12 * max(float(mag.max()), 1e-30)) / prod.size


def correlation_peak(spectrum: np.ndarray, near: tuple[float, float] | None = None, upsample: int = UPSAMPLE
                     ) -> tuple[float, float, float]:
    """The shift (dx, dy) with b(u, v) = a(u - dx, v - dy) from a ``cross_power`` spectrum of (a, b): the peak
    of its inverse DFT (or, with ``near``, the highest point within ``NEAR_PX`` of that shift), refined to
    1/``upsample`` px by a matrix-multiply DFT around it (Guizar-Sicairos et al., Opt. Lett. 33(2), 2008); and
    the peak's height (1: identical up to the shift, near 0: unrelated)."""
    if near is None:
        cc = np.abs(np.fft.ifft2(spectrum))
        shape = np.asarray(cc.shape)
        peak = np.asarray(np.unravel_index(int(np.argmax(cc)), cc.shape), dtype=np.float64)
        peak[peak > shape // 2] -= shape[peak > shape // 2]
        reach = 1.5
    else:
        peak, reach = -np.asarray(near[::-1], dtype=np.float64), 2.0 * NEAR_PX
    peak = np.round(peak * upsample) / upsample
    size = int(math.ceil(upsample * reach))
    centre = float(size // 2)
    fine = np.abs(_upsampled_dft(spectrum.conj(), size, upsample, centre - peak * upsample))
    best = np.asarray(np.unravel_index(int(np.argmax(fine)), fine.shape), dtype=np.float64) - centre
    row, col = peak + best / upsample          # the shift that brings b onto a
    return -float(col), -float(row), float(fine.max())


def _upsampled_dft(data: np.ndarray, size: int, factor: int, offsets: np.ndarray) -> np.ndarray:
    """The inverse DFT of ``data`` (M, N) on a ``size`` x ``size`` patch of a grid ``factor`` times finer,
    starting at ``offsets`` (rows, columns, in fine-grid samples)."""
    for n, off in zip(data.shape[::-1], offsets[::-1], strict=True):
        kernel = np.exp(-2j * np.pi * (np.arange(size) - off)[:, None] * np.fft.fftfreq(n, factor))
        data = np.tensordot(kernel, data, axes=(1, -1))
    return data


# ------------------------------------------------------------------------------------------ folders of pairs
def pairs_in(folder: str | os.PathLike) -> list[tuple[Path, Path]]:
    """The pairs of a folder laid out as ``A/<name>`` (earlier epoch) and ``B/<name>`` (later epoch), sorted by
    name (the LEVIR-CD layout; other folders such as ``label/`` are ignored, and so are world files and .prj
    files beside the images)."""
    root = Path(folder).expanduser()
    a, b = root / "A", root / "B"
    if not a.is_dir() or not b.is_dir():
        raise MapError(f"{root}: a folder of pairs holds A/ (the earlier epoch, the map) and B/ (the later "
                       "epoch, the camera) with images of the same names; "
                       f"{'A/' if not a.is_dir() else 'B/'} is missing")
    sidecar = (".prj", ".pgw", ".jgw", ".tfw", ".wld", ".xml", ".txt", ".md", ".json")
    out = [(p, b / p.name) for p in sorted(a.iterdir())
           if p.is_file() and not p.name.startswith(".") and not p.name.lower().endswith(sidecar)
           and not p.suffix.lower().endswith("w") and (b / p.name).is_file()]
    if not out:
        raise MapError(f"{root}: no image in A/ has a namesake in B/")
    return out
