"""Where a vehicle may fly over a map: the points whose camera footprint (a disc of the clearance radius) stays
on valid map data. The env samples tracks in it and the MCL draws particles in it."""

from __future__ import annotations

import math

import cv2
import numpy as np

from aerial_loc_env.errors import MapError


class FlyableRegion:
    """Where the vehicle may be: points whose disc of radius ``clearance_m`` lies inside the map and off
    no-data. Built once per map and clearance on a coarse grid (``cell_m``), conservative by half a cell
    diagonal, with one distance transform."""

    def __init__(self, width_m: float, height_m: float, clearance_m: float, *,
                 nodata: np.ndarray | None = None, cell_m: float | None = None, name: str = "map") -> None:
        self.width_m, self.height_m, self.clearance_m = float(width_m), float(height_m), float(clearance_m)
        cell = cell_m or max(1.0, min(width_m, height_m) / 400.0, clearance_m / 20.0)
        nx, ny = max(1, int(math.ceil(width_m / cell))), max(1, int(math.ceil(height_m / cell)))
        self.cell_x_m, self.cell_y_m = width_m / nx, height_m / ny
        invalid = np.zeros((ny, nx), dtype=bool)
        if nodata is not None:
            invalid = _block_any(np.asarray(nodata, dtype=bool), ny, nx)
        # Pad with one invalid ring: the map edge counts as no-data. Rows of the grid go south -> north.
        free = np.zeros((ny + 2, nx + 2), dtype=np.uint8)
        free[1:-1, 1:-1] = ~invalid[::-1]
        dist_cells = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
        cell_min = min(self.cell_x_m, self.cell_y_m)
        # distance between cell centres -> distance to the nearest invalid point: minus half a cell,
        # and any point of this cell is within half a diagonal of its centre.
        dist_m = dist_cells * cell_min - 0.5 * cell_min - 0.5 * math.hypot(self.cell_x_m, self.cell_y_m)
        self.ok = dist_m >= clearance_m            # (ny, nx), row 0 = southernmost
        self.name = name
        self._dist_m = dist_m
        self._cells = np.flatnonzero(self.ok)
        self._inner: dict[float, np.ndarray] = {}

    @property
    def area_m2(self) -> float:
        return float(self._cells.size * self.cell_x_m * self.cell_y_m)

    def contains(self, x_m: np.ndarray | float, y_m: np.ndarray | float) -> np.ndarray:
        """True where (x, y) is flyable; vectorized."""
        x, y = np.asarray(x_m, dtype=np.float64), np.asarray(y_m, dtype=np.float64)
        i = np.floor(y / self.cell_y_m).astype(np.int64)
        j = np.floor(x / self.cell_x_m).astype(np.int64)
        inside = (i >= 0) & (j >= 0) & (i < self.ok.shape[0]) & (j < self.ok.shape[1])
        out = np.zeros(np.broadcast(x, y).shape, dtype=bool)
        out[inside] = self.ok[i[inside], j[inside]]
        return out

    def contains_point(self, x_m: float, y_m: float) -> bool:
        """``contains`` for one point, in plain Python (a flight's step-by-step integration asks once per step)."""
        fi, fj = y_m / self.cell_y_m, x_m / self.cell_x_m
        if not (0.0 <= fi < self.ok.shape[0] and 0.0 <= fj < self.ok.shape[1]):    # (NaN: outside)
            return False
        return bool(self.ok[int(fi), int(fj)])

    def sample(self, rng: np.random.Generator, n: int = 1, inset_m: float = 0.0) -> np.ndarray:
        """``n`` uniform points (n, 2) of the region, or of its part at least ``inset_m`` further from the
        edge when that part is not empty."""
        if self._cells.size == 0:
            raise self.too_small_error()
        cells = self._cells
        if inset_m > 0.0:
            if inset_m not in self._inner:
                self._inner[inset_m] = np.flatnonzero(self._dist_m >= self.clearance_m + inset_m)
            if self._inner[inset_m].size:
                cells = self._inner[inset_m]
        idx = cells[rng.integers(0, cells.size, size=n)]
        i, j = np.divmod(idx, self.ok.shape[1])
        u = rng.random((n, 2))
        return np.stack([(j + u[:, 0]) * self.cell_x_m, (i + u[:, 1]) * self.cell_y_m], axis=1)

    def too_small_error(self, detail: str = "") -> MapError:
        return MapError(
            f"{self.name}: map too small for any track: the camera footprint plus margin needs "
            f"{self.clearance_m:.0f} m of valid map around the vehicle, but the map is "
            f"{self.width_m:.0f} x {self.height_m:.0f} m (flyable area {self.area_m2:.0f} m2){detail}; "
            "use a larger map, a lower flight.altitude_m, a smaller flight.margin_m, "
            "or a slower flight.speed_mps")


def _block_any(mask: np.ndarray, ny: int, nx: int) -> np.ndarray:
    """(ny, nx) grid (map rows north -> south), True where any pixel overlapping the cell is True."""
    if not mask.any():
        return np.zeros((ny, nx), dtype=bool)
    area = cv2.resize(mask.astype(np.float32), (nx, ny), interpolation=cv2.INTER_AREA)
    return area > 1e-6
