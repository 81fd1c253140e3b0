"""Land-cover class codes of the `Orthomap.classes` layer, with preview colours.

The codes are stored as uint8 in map bundles, so they are part of the on-disk format: append new classes at
the end, never renumber. ``NODATA`` is 0 so that a zero-initialised class map means "unknown".
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class LandCover(IntEnum):
    """Land-cover class of one map pixel (uint8 code)."""

    NODATA = 0
    ROAD = 1
    LANE_MARKING = 2
    SIDEWALK = 3
    BUILDING = 4
    TREE = 5
    LAWN = 6
    BARE_SOIL = 7
    PARKING = 8
    CAR = 9
    WATER = 10
    ROOF_EQUIPMENT = 11
    SHRUB = 12
    PLAZA = 13
    RAILWAY = 14
    FIELD = 15
    WALL = 16
    POOL = 17
    OTHER = 18


#: RGB preview colours (uint8), for legends and class-map previews; not used for rendering imagery.
LANDCOVER_COLORS_RGB: dict[LandCover, tuple[int, int, int]] = {
    LandCover.NODATA: (0, 0, 0),
    LandCover.ROAD: (90, 90, 90),
    LandCover.LANE_MARKING: (250, 250, 250),
    LandCover.SIDEWALK: (190, 180, 170),
    LandCover.BUILDING: (200, 60, 50),
    LandCover.TREE: (20, 110, 30),
    LandCover.LAWN: (120, 200, 90),
    LandCover.BARE_SOIL: (170, 130, 80),
    LandCover.PARKING: (140, 140, 160),
    LandCover.CAR: (240, 200, 0),
    LandCover.WATER: (40, 90, 200),
    LandCover.ROOF_EQUIPMENT: (230, 120, 120),
    LandCover.SHRUB: (70, 150, 60),
    LandCover.PLAZA: (220, 210, 180),
    LandCover.RAILWAY: (110, 70, 60),
    LandCover.FIELD: (210, 200, 110),
    LandCover.WALL: (150, 40, 40),
    LandCover.POOL: (80, 200, 230),
    LandCover.OTHER: (255, 0, 255),
}


def landcover_palette() -> np.ndarray:
    """A (256, 3) uint8 lookup table code -> preview colour (unknown codes map to OTHER's magenta)."""
    lut = np.tile(np.asarray(LANDCOVER_COLORS_RGB[LandCover.OTHER], np.uint8), (256, 1))
    for code, rgb in LANDCOVER_COLORS_RGB.items():
        lut[int(code)] = rgb
    return lut


def colorize_classes(classes: np.ndarray) -> np.ndarray:
    """Preview image (H, W, 3) uint8 of a uint8 class map, vectorized through the palette."""
    classes = np.asarray(classes)
    if classes.dtype != np.uint8:
        raise TypeError(f"classes: expected a uint8 class map, got dtype {classes.dtype}")
    return landcover_palette()[classes]
