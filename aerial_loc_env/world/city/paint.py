"""Drawing surface of the procedural city: materials, vector drawing into all layers, final texturing.

The city is drawn with OpenCV primitives into four full-resolution layers at once (base colour, a brightness
"shade" layer, height above ground, and a material code). Texture is added once at the end, per material,
from noise generated at several scales (fine grain at full resolution, 1 m and 6 m noise upsampled, and a
~60 m brightness field), so that no two places look alike and nothing is tiled.

Geometry is given in metres in the *image-aligned* frame (x to the right, y down, origin at the top-left
outer corner of the map); ``Canvas.px`` turns it into OpenCV's fixed-point pixel coordinates.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import IntEnum

import cv2
import numpy as np

from aerial_loc_env.world.maps.landcover import LandCover

_SHIFT = 2                 # fixed-point bits for sub-pixel vertices in cv2 drawing calls
_SCALE = 1 << _SHIFT
NEUTRAL_SHADE = 128        # shade layer value meaning "base colour as drawn"


class Material(IntEnum):
    """What a pixel is made of: decides its land-cover class and how much texture it gets."""

    GRASS = 0
    SOIL = 1
    ASPHALT = 2
    MARKING = 3
    SIDEWALK = 4
    ROOF_FLAT = 5
    ROOF_TILE = 6
    ROOF_METAL = 7
    ROOF_GREEN = 8
    ROOF_UNIT = 9
    TREE = 10
    PARKING = 11
    CAR = 12
    WATER = 13
    PLAZA = 14
    SHRUB = 15
    FIELD = 16
    TRACK = 17
    WALL = 18
    POOL = 19
    GRAVEL = 20


# material -> (land-cover class, fine-grain amplitude, 1 m noise amplitude, 6 m noise amplitude), amplitudes
# in shade units (128 = unit brightness), peak to peak.
_MATERIAL_TABLE: dict[Material, tuple[LandCover, int, int, int]] = {
    Material.GRASS: (LandCover.LAWN, 26, 30, 26),
    Material.SOIL: (LandCover.BARE_SOIL, 30, 26, 30),
    Material.ASPHALT: (LandCover.ROAD, 22, 10, 12),
    Material.MARKING: (LandCover.LANE_MARKING, 10, 6, 8),
    Material.SIDEWALK: (LandCover.SIDEWALK, 22, 14, 10),
    Material.ROOF_FLAT: (LandCover.BUILDING, 22, 16, 24),
    Material.ROOF_TILE: (LandCover.BUILDING, 20, 10, 8),
    Material.ROOF_METAL: (LandCover.BUILDING, 10, 6, 8),
    Material.ROOF_GREEN: (LandCover.BUILDING, 30, 36, 20),
    Material.ROOF_UNIT: (LandCover.ROOF_EQUIPMENT, 14, 8, 4),
    Material.TREE: (LandCover.TREE, 16, 20, 14),
    Material.PARKING: (LandCover.PARKING, 20, 10, 12),
    Material.CAR: (LandCover.CAR, 8, 4, 2),
    Material.WATER: (LandCover.WATER, 8, 14, 16),
    Material.PLAZA: (LandCover.PLAZA, 22, 14, 12),
    Material.SHRUB: (LandCover.SHRUB, 36, 40, 14),
    Material.FIELD: (LandCover.FIELD, 24, 20, 24),
    Material.TRACK: (LandCover.OTHER, 14, 8, 8),
    Material.WALL: (LandCover.WALL, 14, 8, 4),
    Material.POOL: (LandCover.POOL, 6, 10, 4),
    Material.GRAVEL: (LandCover.BARE_SOIL, 40, 20, 14),
}


# material -> darkening (shade units) of stains: oil drips, tyre marks, wet patches, tar on paving; weeds, clover
# and moist hollows on grass and fields; sparse blobs at two scales. Markings get wear instead: the paint thins
# to the asphalt under it in places.
_STAIN_AMPLITUDE: dict[Material, int] = {
    Material.ASPHALT: 36, Material.PARKING: 40, Material.PLAZA: 28, Material.SIDEWALK: 24,
    Material.ROOF_FLAT: 26, Material.GRAVEL: 22, Material.SOIL: 20, Material.TRACK: 16,
    Material.GRASS: 30, Material.FIELD: 30, Material.SHRUB: 30,
}
_MARKING_WEAR = 70

#: How much of its colour a pixel keeps about its own grey (1 keeps the palette, 0 is grey): the palette names
#: the materials' colours; calibrated so that the camera frames' Lab chroma lies within the real two-epoch
#: pairs' later epochs (../shared/data/pairs), which are far less saturated than a painted palette.
WORLD_SATURATION = 0.72


def _lut(column: int) -> np.ndarray:
    lut = np.zeros(256, np.uint8)
    for mat, row in _MATERIAL_TABLE.items():
        lut[int(mat)] = int(row[column])
    return lut


MATERIAL_TO_CLASS = _lut(0)


class Canvas:
    """Four aligned layers drawn together: rgb (uint8), shade (uint8), dsm_m (float32), material (uint8)."""

    def __init__(self, ground_rgb: np.ndarray, gsd_m: float) -> None:
        h, w = ground_rgb.shape[:2]
        self.gsd_m = float(gsd_m)
        self.height_px, self.width_px = h, w
        self.rgb = np.ascontiguousarray(ground_rgb, dtype=np.uint8)
        self.shade = np.full((h, w), NEUTRAL_SHADE, np.uint8)
        self.dsm_m = np.zeros((h, w), np.float32)
        self.material = np.full((h, w), int(Material.GRASS), np.uint8)

    # -- geometry ---------------------------------------------------------------------------------------
    def px(self, pts_m: np.ndarray) -> np.ndarray:
        """Metres (x right, y down) -> int32 fixed-point pixel coordinates for cv2 (pixel centres at k)."""
        return np.rint((np.asarray(pts_m, np.float64) / self.gsd_m - 0.5) * _SCALE).astype(np.int32)

    def _polys(self, polys_m: Sequence[np.ndarray]) -> list[np.ndarray]:
        return [self.px(p).reshape(-1, 1, 2) for p in polys_m]

    def thickness_px(self, width_m: float) -> int:
        return max(1, int(round(width_m / self.gsd_m)))

    # -- drawing into all layers ------------------------------------------------------------------------
    def fill(self, polys_m: Sequence[np.ndarray], colour: Sequence[int], material: Material,
             height_m: float = 0.0, shade: int = NEUTRAL_SHADE) -> None:
        """Fill polygons (each (K, 2) metres) with one colour/material/height; overwrites what is below."""
        if len(polys_m) == 0:
            return
        pts = self._polys(polys_m)
        cv2.fillPoly(self.rgb, pts, tuple(int(c) for c in colour), cv2.LINE_8, _SHIFT)
        cv2.fillPoly(self.material, pts, int(material), cv2.LINE_8, _SHIFT)
        cv2.fillPoly(self.dsm_m, pts, float(height_m), cv2.LINE_8, _SHIFT)
        cv2.fillPoly(self.shade, pts, int(shade), cv2.LINE_8, _SHIFT)

    def lines(self, polylines_m: Sequence[np.ndarray], colour: Sequence[int], material: Material,
              width_m: float, height_m: float = 0.0, closed: bool = False) -> None:
        """Draw polylines ``width_m`` wide (at least one pixel) into all layers."""
        if len(polylines_m) == 0:
            return
        pts = self._polys(polylines_m)
        t = self.thickness_px(width_m)
        cv2.polylines(self.rgb, pts, closed, tuple(int(c) for c in colour), t, cv2.LINE_8, _SHIFT)
        cv2.polylines(self.material, pts, closed, int(material), t, cv2.LINE_8, _SHIFT)
        cv2.polylines(self.dsm_m, pts, closed, float(height_m), t, cv2.LINE_8, _SHIFT)
        cv2.polylines(self.shade, pts, closed, NEUTRAL_SHADE, t, cv2.LINE_8, _SHIFT)

    def px_radius(self, radius_m: np.ndarray) -> np.ndarray:
        """Metres -> fixed-point pixel radii (at least one pixel)."""
        return np.maximum(_SCALE, np.rint(np.asarray(radius_m) / self.gsd_m * _SCALE)).astype(np.int64)

    @staticmethod
    def circle_px(layer: np.ndarray, centre_px: tuple[int, int], radius_px: int, value: float) -> None:
        """Filled disc in one layer, centre and radius already in fixed-point pixels (see px, px_radius)."""
        cv2.circle(layer, centre_px, radius_px, value, -1, cv2.LINE_8, _SHIFT)

    def disc_px(self, centre_px: tuple[int, int], radius_px: int, colour: Sequence[int], material: Material,
                height_m: float = 0.0, shade: int = NEUTRAL_SHADE) -> None:
        """Filled disc in all layers, fixed-point centre and radius."""
        cv2.circle(self.rgb, centre_px, radius_px, tuple(int(v) for v in colour), -1, cv2.LINE_8, _SHIFT)
        cv2.circle(self.material, centre_px, radius_px, int(material), -1, cv2.LINE_8, _SHIFT)
        cv2.circle(self.dsm_m, centre_px, radius_px, float(height_m), -1, cv2.LINE_8, _SHIFT)
        cv2.circle(self.shade, centre_px, radius_px, int(shade), -1, cv2.LINE_8, _SHIFT)

    # -- drawing into one layer -------------------------------------------------------------------------
    def shade_fill(self, polys_m: Sequence[np.ndarray], shade: int) -> None:
        if len(polys_m):
            cv2.fillPoly(self.shade, self._polys(polys_m), int(shade), cv2.LINE_8, _SHIFT)

    def shade_lines(self, polylines_m: Sequence[np.ndarray], shade: int, width_m: float = 0.0) -> None:
        if len(polylines_m):
            cv2.polylines(self.shade, self._polys(polylines_m), False, int(shade), self.thickness_px(width_m),
                          cv2.LINE_8, _SHIFT)

    def dsm_fill(self, polys_m: Sequence[np.ndarray], height_m: float) -> None:
        if len(polys_m):
            cv2.fillPoly(self.dsm_m, self._polys(polys_m), float(height_m), cv2.LINE_8, _SHIFT)

    def paint_lines(self, polylines_m: Sequence[np.ndarray], colour: Sequence[int], material: Material,
                    width_m: float) -> None:
        """Paint on the surface (markings): colour and material only, height and shade unchanged."""
        if len(polylines_m) == 0:
            return
        pts = self._polys(polylines_m)
        t = self.thickness_px(width_m)
        cv2.polylines(self.rgb, pts, False, tuple(int(c) for c in colour), t, cv2.LINE_8, _SHIFT)
        cv2.polylines(self.material, pts, False, int(material), t, cv2.LINE_8, _SHIFT)

    def paint_fill(self, polys_m: Sequence[np.ndarray], colour: Sequence[int], material: Material) -> None:
        if len(polys_m) == 0:
            return
        pts = self._polys(polys_m)
        cv2.fillPoly(self.rgb, pts, tuple(int(c) for c in colour), cv2.LINE_8, _SHIFT)
        cv2.fillPoly(self.material, pts, int(material), cv2.LINE_8, _SHIFT)

    # -- finishing --------------------------------------------------------------------------------------
    def classes(self) -> np.ndarray:
        return cv2.LUT(self.material, MATERIAL_TO_CLASS)

    def textured_rgb(self, rng: np.random.Generator) -> np.ndarray:
        """Final image: base colour x (shade + per-material multi-scale noise) x large-scale light, blurred.

        All full-resolution work is saturating uint8 arithmetic in OpenCV; noise above 0.25 m scale is drawn
        at coarse resolution and upsampled, so the cost is a few passes over the image. The passes write into a
        few scratch planes reused from pass to pass (OpenCV's ``dst``, in place where a pass reads its own
        output): a fresh plane per pass costs more than the pass, every page of it faulted in and zeroed by the
        kernel on first touch. The same bytes as fresh outputs.
        """
        h, w = self.height_px, self.width_px
        mat = self.material
        amps = [_lut(1), _lut(2), _lut(3)]
        offset = (amps[0].astype(np.int32) + amps[1] + amps[2]) // 2
        table, term = np.empty((h, w), np.uint8), np.empty((h, w), np.uint8)   # a pass's looked-up and new term
        scratch = _Scratch()                                                   # the upsampled noise fields
        mod = cv2.subtract(self.shade, cv2.LUT(mat, offset.astype(np.uint8), dst=table))
        scales_m = (None, 1.0, 6.0)
        for amp, scale_m in zip(amps, scales_m, strict=True):
            if scale_m is None:
                noise = rng.integers(0, 256, (h, w), dtype=np.uint8)
            else:
                noise = _upsampled_noise(rng, h, w, max(1, int(round(scale_m / self.gsd_m))), scratch=scratch)
            mod = cv2.add(mod, cv2.multiply(noise, cv2.LUT(mat, amp, dst=table), dst=term, scale=1.0 / 255.0),
                          dst=mod)
        # stains: the top few percent of smooth noise at 1.5 m and at 5 m, darkening paved ground and roofs
        stain_amp = np.zeros(256, np.uint8)
        for m_, a_ in _STAIN_AMPLITUDE.items():
            stain_amp[int(m_)] = a_
        stain_amp[int(Material.MARKING)] = _MARKING_WEAR
        amp = cv2.LUT(mat, stain_amp, dst=table)
        for cell_m, cut in ((1.5, 196), (5.0, 186)):
            blot = _upsampled_noise(rng, h, w, max(1, int(round(cell_m / self.gsd_m))), scratch=scratch)
            blot = cv2.multiply(cv2.subtract(blot, cut, dst=term), 255.0 / (255 - cut), dst=term)
            mod = cv2.subtract(mod, cv2.multiply(blot, amp, dst=term, scale=1.0 / 255.0), dst=mod)
        # large-scale illumination / weathering field (about 60 m blobs, +-10 %)
        light = _upsampled_noise(rng, h, w, max(1, int(round(60.0 / self.gsd_m))), lo=110, hi=146, scratch=scratch)
        mod = cv2.multiply(mod, light, dst=mod, scale=1.0 / 128.0)
        spread = cv2.cvtColor(mod, cv2.COLOR_GRAY2RGB)
        out = cv2.multiply(self.rgb, spread, scale=1.0 / NEUTRAL_SHADE)
        grey = cv2.cvtColor(cv2.cvtColor(out, cv2.COLOR_RGB2GRAY, dst=term), cv2.COLOR_GRAY2RGB, dst=spread)
        mixed = cv2.addWeighted(out, WORLD_SATURATION, grey, 1.0 - WORLD_SATURATION, 0.0, dst=spread)
        sigma_px = 0.12 / self.gsd_m          # optics blur: about 0.12 m, i.e. half a pixel at 0.25 m
        if sigma_px > 0.3:
            return cv2.GaussianBlur(mixed, (3, 3), sigma_px, dst=out)
        return mixed


class _Scratch:
    """A flat uint8 buffer lent out as planes of any shape (the largest asked for so far): one allocation for the
    upsampled noise fields of ``textured_rgb``, each used before the next is drawn."""

    def __init__(self) -> None:
        self._flat = np.empty(0, np.uint8)

    def plane(self, h: int, w: int) -> np.ndarray:
        if self._flat.size < h * w:
            self._flat = np.empty(h * w, np.uint8)
        return self._flat[:h * w].reshape(h, w)


def _upsampled_noise(rng: np.random.Generator, h: int, w: int, cell_px: int, lo: int = 0,
                     hi: int = 255, *, scratch: _Scratch) -> np.ndarray:
    """Smooth uint8 noise in [lo, hi] with features about ``cell_px`` pixels across (bicubic upsampling), in a
    plane of ``scratch`` (valid until its next use)."""
    ch, cw = h // cell_px + 3, w // cell_px + 3
    coarse = rng.integers(lo, hi + 1, (ch, cw), dtype=np.uint8)
    size = ((cw - 1) * cell_px, (ch - 1) * cell_px)
    big = cv2.resize(coarse, size, dst=scratch.plane(size[1], size[0]), interpolation=cv2.INTER_CUBIC)
    oy = int(rng.integers(0, cell_px))
    ox = int(rng.integers(0, cell_px))
    return big[oy:oy + h, ox:ox + w]      # a strided view: OpenCV takes row-strided arrays as they are
