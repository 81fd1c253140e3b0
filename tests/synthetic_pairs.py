"""Synthetic two-epoch pairs with known geometry, written as PNG + world file + .prj (tests of world/maps/pairs.py,
the RealPair scenario, the gap report and the fidelity report).

The ground is a broadband texture defined in projected metres (noise at 0.75-12 m scales on a fine raster, sampled
bicubically), so an image of any grid, pixel size or offset shows the ground its georeference says, and a shifted
epoch B is shifted by exactly that much."""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

CRS = "EPSG:32633"                       # UTM 33N, around 15 E, 45 N: a plausible place for a map
ORIGIN_EN_M = (500_000.0, 5_000_000.0)   # the projected coordinates of the tiles' top-left outer corner


#: the ground is a raster of this spacing over [-50, 650) m east and (-650, 50] m north of the origin, sampled with
#: bicubic interpolation: it is smooth over several of its cells, so any grid samples the same ground
_RASTER_M = 0.25
_RASTER_PX = 2800


@functools.cache
def _ground(seed: int) -> np.ndarray:
    """Broadband ground: noise smoothed at 0.75 m, 3 m and 12 m, summed (float32, 0..1)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((_RASTER_PX, _RASTER_PX), np.float32)
    for sigma_m, weight in ((0.75, 1.0), (3.0, 1.5), (12.0, 2.0)):
        step = max(1, int(sigma_m / _RASTER_M / 3))          # draw the coarse scales coarser, then enlarge
        n = _RASTER_PX // step + 1
        layer = cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0), sigma_m / _RASTER_M / step)
        layer = cv2.resize(layer, (n * step, n * step), interpolation=cv2.INTER_CUBIC)[:_RASTER_PX, :_RASTER_PX]
        out += weight * layer / (layer.std() + 1e-12)
    return (out - out.min()) / (np.ptp(out) + 1e-12)


def texture(x_m: np.ndarray, y_m: np.ndarray, seed: int = 0) -> np.ndarray:
    """Grey values (0..1) of the synthetic ground at projected metres relative to ``ORIGIN_EN_M``."""
    col = ((np.asarray(x_m) + 50.0) / _RASTER_M - 0.5).astype(np.float32)
    row = ((50.0 - np.asarray(y_m)) / _RASTER_M - 0.5).astype(np.float32)
    return cv2.remap(_ground(seed), col, row, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT).astype(np.float64)


def write_image(path: Path, width_px: int, height_px: int, gsd_xy_m: tuple[float, float], *,
                offset_px: tuple[float, float] = (0.0, 0.0), shift_m: tuple[float, float] = (0.0, 0.0),
                gain: float = 1.0, world_file: bool = True, seed: int = 0) -> Path:
    """A PNG of the ground on a north-up grid whose pixel (0, 0) centre lies ``offset_px`` grid pixels from the
    common origin's first pixel centre; its content shifted ``shift_m`` (east, north) from where its
    georeference says (the misregistration to measure); a world file and .prj beside it unless
    ``world_file=False``."""
    gx, gy = gsd_xy_m
    u, v = np.meshgrid(np.arange(width_px, dtype=np.float64), np.arange(height_px, dtype=np.float64))
    x = (u + 0.5 + offset_px[0]) * gx                 # metres east of the origin corner
    y = -(v + 0.5 + offset_px[1]) * gy                # metres north of it (negative: below)
    grey = texture(x - shift_m[0], y - shift_m[1], seed)
    rgb = np.clip(np.stack([grey * 200 + 30, grey * 180 + 50, grey * 150 + 60], axis=-1) * gain, 0, 255)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.ascontiguousarray(rgb.astype(np.uint8)[..., ::-1]))
    if world_file:
        c = ORIGIN_EN_M[0] + (0.5 + offset_px[0]) * gx
        f = ORIGIN_EN_M[1] - (0.5 + offset_px[1]) * gy
        path.with_suffix(".pgw").write_text(f"{gx!r}\n0.0\n0.0\n{-gy!r}\n{c!r}\n{f!r}\n")
        path.with_suffix(".prj").write_text(CRS + "\n")
    return path


def write_pair(folder: Path, name: str = "p.png", *, size_px: int = 512, gsd_m: float = 0.5,
               b_gsd_xy_m: tuple[float, float] | None = None, b_offset_px: tuple[float, float] = (0.0, 0.0),
               shift_m: tuple[float, float] = (0.0, 0.0), world_file: bool = True) -> tuple[Path, Path]:
    """``folder/A/name`` and ``folder/B/name``: the same ground, B on its own grid (``b_gsd_xy_m``, sub-pixel
    ``b_offset_px``) with content shifted ``shift_m`` and another exposure; both covering ``size_px * gsd_m``."""
    a = write_image(folder / "A" / name, size_px, size_px, (gsd_m, gsd_m), world_file=world_file)
    bx, by = b_gsd_xy_m or (gsd_m, gsd_m)
    extent = size_px * gsd_m
    b = write_image(folder / "B" / name, int(round(extent / bx)), int(round(extent / by)), (bx, by),
                    offset_px=b_offset_px, shift_m=shift_m, gain=0.85, world_file=world_file)
    return a, b
