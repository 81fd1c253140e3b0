"""What stands in the blocks of the procedural city: parcels, buildings, trees, parking lots, cars.

Block fillers only *describe* the content (a ``Scene`` of grounds, trees, buildings, cars); ``paint_scene``
then draws it in a fixed order (grounds, trees, buildings) so that trees never cover roofs and no block
overwrites a neighbour's buildings.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from aerial_loc_env.world.city.layout import Block, Layout
from aerial_loc_env.world.city.paint import NEUTRAL_SHADE, Canvas, Material

# ---------------------------------------------------------------------------------------------------------
# palettes (RGB)
ROOF_TILE_COLOURS = np.array([(168, 78, 58), (128, 52, 44), (72, 98, 138), (84, 120, 92), (108, 108, 114),
                              (122, 88, 68), (176, 110, 62), (60, 70, 82)], np.int32)
ROOF_FLAT_COLOURS = np.array([(178, 176, 170), (150, 150, 146), (196, 192, 184), (132, 130, 126),
                              (112, 146, 118), (110, 138, 146), (170, 160, 140), (120, 124, 130),
                              (186, 180, 168), (160, 158, 154), (142, 136, 128), (78, 78, 82),
                              (96, 92, 90), (204, 204, 200)], np.int32)
ROOF_METAL_COLOURS = np.array([(168, 172, 176), (92, 132, 166), (198, 200, 202), (150, 86, 70),
                               (104, 150, 144), (206, 200, 184)], np.int32)
CAR_COLOURS = np.array([(232, 232, 232), (226, 228, 230), (30, 30, 34), (150, 152, 156), (96, 98, 104),
                        (170, 30, 30), (30, 60, 130), (200, 200, 195), (110, 80, 60), (40, 90, 60)], np.int32)
CAR_WEIGHTS = np.array([0.26, 0.1, 0.18, 0.16, 0.12, 0.05, 0.05, 0.04, 0.02, 0.02])
TREE_COLOURS = np.array([(52, 88, 42), (62, 96, 46), (44, 76, 40), (74, 104, 52), (58, 82, 50),
                         (86, 110, 60)], np.int32)


# ground cover kinds: base colour (RGB), colour jitter, material
GROUND_KINDS: dict[str, tuple[tuple[int, int, int], int, Material]] = {
    "lawn": ((96, 132, 66), 14, Material.GRASS),
    "soil": ((150, 124, 96), 14, Material.SOIL),
    "paving": ((172, 166, 156), 14, Material.PLAZA),
    "gravel": ((150, 144, 134), 10, Material.GRAVEL),
    "asphalt": ((92, 92, 94), 10, Material.PARKING),
    "field": ((140, 146, 82), 18, Material.FIELD),
}


def _jitter(rng: np.random.Generator, colour: np.ndarray, amount: int) -> tuple[int, int, int]:
    c = np.clip(colour + rng.integers(-amount, amount + 1) + rng.integers(-amount // 4, amount // 4 + 1, 3),
                0, 255)
    return (int(c[0]), int(c[1]), int(c[2]))


# ---------------------------------------------------------------------------------------------------------
# geometry helpers
def bilinear(quad: np.ndarray, s: float, t: float) -> np.ndarray:
    """Point at parameters (s along quad[0]->quad[1], t along quad[0]->quad[3]) of a quadrilateral."""
    return ((1 - s) * (1 - t) * quad[0] + s * (1 - t) * quad[1] + s * t * quad[2] + (1 - s) * t * quad[3])


def sub_quad(quad: np.ndarray, s0: float, s1: float, t0: float, t1: float) -> np.ndarray:
    return np.stack([bilinear(quad, s0, t0), bilinear(quad, s1, t0), bilinear(quad, s1, t1),
                     bilinear(quad, s0, t1)])


def quad_frame(quad: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Centre, unit axis along s, and mean side lengths (along s, along t) of a quadrilateral."""
    es = ((quad[1] - quad[0]) + (quad[2] - quad[3])) / 2
    et = ((quad[3] - quad[0]) + (quad[2] - quad[1])) / 2
    u = es / max(np.linalg.norm(es), 1e-9)
    return quad.mean(axis=0), u, float(np.linalg.norm(es)), float(np.linalg.norm(et))


def orect(centre: np.ndarray, u: np.ndarray, a: float, b: float) -> np.ndarray:
    """Oriented rectangle (4, 2): ``a`` long along unit ``u``, ``b`` along its normal."""
    v = np.array([-u[1], u[0]])
    ha, hb = a / 2, b / 2
    return np.stack([centre - u * ha - v * hb, centre + u * ha - v * hb, centre + u * ha + v * hb,
                     centre - u * ha + v * hb])


def _signed_area(q: np.ndarray) -> float:
    x, y = q[:, 0], q[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def rotate(u: np.ndarray, ang: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    return np.array([c * u[0] - s * u[1], s * u[0] + c * u[1]])


# ---------------------------------------------------------------------------------------------------------
@dataclass
class Building:
    wings: list[tuple[np.ndarray, np.ndarray, float, float]]  # (centre, unit u, a along u, b) per wing
    style: str                                              # flat | gable | hip | metal | green
    colour: tuple[int, int, int]
    height_m: float
    units: list[tuple[np.ndarray, float]] = field(default_factory=list)   # rooftop units (poly, extra h)
    courtyard: np.ndarray | None = None
    cap_m: float = 60.0                                     # nothing of it (ridges, units) rises above this
    panels: list[np.ndarray] = field(default_factory=list)  # rooftop solar panel rows
    vents: list[np.ndarray] = field(default_factory=list)   # small rooftop boxes (vents, AC units), 0.5 m tall
    skylights: list[tuple[np.ndarray, int]] = field(default_factory=list)   # flat glass (poly, shade)
    stains: list[tuple[np.ndarray, int]] = field(default_factory=list)      # roof patches (poly, shade)


@dataclass
class Scene:
    grounds: list[tuple[list[np.ndarray], tuple[int, int, int], Material]] = field(default_factory=list)
    lines: list[tuple[list[np.ndarray], tuple[int, int, int], Material, float, float]] = field(
        default_factory=list)
    trees: list[tuple[float, float, float, float, int]] = field(default_factory=list)  # x, y, r, h, col
    buildings: list[Building] = field(default_factory=list)
    cars: list[tuple[np.ndarray, int]] = field(default_factory=list)                  # poly, colour idx
    markings: list[np.ndarray] = field(default_factory=list)                            # white paint


class Filler:
    """Builds the content of blocks according to their use."""

    def __init__(self, layout: Layout, rng: np.random.Generator, *, building_density: float,
                 tree_density: float, car_density: float, max_height_m: float) -> None:
        self.layout = layout
        self.rng = rng
        self.bd = building_density
        self.td = tree_density
        self.cd = car_density
        self.hmax = max_height_m
        self.scene = Scene()

    # -- primitives ---------------------------------------------------------------------------------------
    def ground(self, poly: np.ndarray, kind: str) -> None:
        try:
            base, spread, mat = GROUND_KINDS[kind]
        except KeyError:
            raise ValueError(f"unknown ground kind {kind!r}; use one of {sorted(GROUND_KINDS)}") from None
        self.scene.grounds.append(([poly], _jitter(self.rng, np.array(base), spread), mat))
        if kind == "paving":
            self._plaza_clutter(poly)

    def _green_lot(self, quad: np.ndarray) -> None:
        """A lot left unbuilt: lawn with a path's worth of paving kept, shrubs and trees."""
        r = self.rng
        self.scene.grounds.append(([quad], _jitter(r, np.array(GROUND_KINDS["lawn"][0]), 14), Material.GRASS))
        for _ in range(int(r.integers(0, 3))):
            self.scene.grounds.append(([sub_quad(quad, *sorted(r.uniform(0.05, 0.95, 2)),
                                                 *sorted(r.uniform(0.05, 0.95, 2)))],
                                       _jitter(r, np.array([70, 100, 56]), 14), Material.SHRUB))
        self.trees_in(quad, 70.0)

    def _plaza_clutter(self, quad: np.ndarray) -> None:
        """What open paving carries: planters, benches and kiosks, bands of a second paving, drain lines (drawn
        with the grounds: buildings stand over them)."""
        r = self.rng
        c, u, a, b = quad_frame(quad)
        if min(a, b) < 8.0:
            return
        v = np.array([-u[1], u[0]])
        for _ in range(int(r.poisson(a * b / 500.0))):
            p = c + u * r.uniform(-0.42, 0.42) * a + v * r.uniform(-0.42, 0.42) * b
            kind = r.random()
            if kind < 0.4:                                   # a planter: shrubs in a box
                self.scene.grounds.append(([orect(p, u, r.uniform(1.5, 6.0), r.uniform(1.0, 2.5))],
                                           _jitter(r, np.array([70, 100, 56]), 14), Material.SHRUB))
            elif kind < 0.7:                                 # a bench or a bin: a small dark or light box
                grey = int(r.choice([60, 90, 190]))
                self.scene.grounds.append(([orect(p, u, r.uniform(0.5, 2.0), r.uniform(0.4, 0.8))],
                                           _jitter(r, np.array([grey, grey, grey]), 8), Material.PLAZA))
            else:                                            # a band of another paving
                self.scene.grounds.append(([orect(p, u if r.random() < 0.5 else v, r.uniform(4.0, 20.0),
                                                  r.uniform(1.0, 3.0))],
                                           _jitter(r, np.array([150, 140, 132]), 20), Material.PLAZA))

    def tree(self, p: np.ndarray, r_m: float | None = None) -> None:
        r = self.rng
        rad = float(r_m if r_m is not None else r.uniform(2.0, 5.5))
        h = float(np.clip(2.2 * rad + r.normal(2.0, 1.5), 6.0, 20.0))
        if self.layout.is_free(p[None, :]):
            self.scene.trees.append((float(p[0]), float(p[1]), rad, h, int(r.integers(len(TREE_COLOURS)))))

    def trees_in(self, quad: np.ndarray, density_per_ha: float) -> None:
        c, u, a, b = quad_frame(quad)
        n = self.rng.poisson(density_per_ha * self.td * a * b / 1e4)
        for s, t in self.rng.random((n, 2)):
            self.tree(bilinear(quad, s, t))

    def height(self, lo: float, hi: float, tail: float = 0.0) -> float:
        h = self.rng.uniform(lo, hi) + tail * self.rng.exponential(1.0)
        return float(np.clip(h, 3.0, self.hmax))

    def building(self, centre: np.ndarray, u: np.ndarray, a: float, b: float, style: str,
                 colour: tuple[int, int, int], height_m: float, shape: str = "rect", units: int = 0) -> bool:
        """Add a building of bounding box a x b (shape rect/L/T/U/court) if it is clear of keep-out land."""
        v = np.array([-u[1], u[0]])
        wa, wb = a * self.rng.uniform(0.3, 0.45), b * self.rng.uniform(0.35, 0.5)
        spec: list[tuple[float, float, float, float]]
        if shape == "L":
            spec = [(0, -(b - wb) / 2, a, wb), ((a - wa) / 2, wb / 2, wa, b - wb)]
        elif shape == "T":
            spec = [(0, -(b - wb) / 2, a, wb), (0, wb / 2, wa, b - wb)]
        elif shape == "U":
            spec = [(0, -(b - wb) / 2, a, wb), (-(a - wa) / 2, wb / 2, wa, b - wb),
                    ((a - wa) / 2, wb / 2, wa, b - wb)]
        elif shape == "court":
            wb2 = min(wb, b * 0.3)
            wa2 = min(wa, a * 0.3)
            spec = [(0, -(b - wb2) / 2, a, wb2), (0, (b - wb2) / 2, a, wb2),
                    (-(a - wa2) / 2, 0, wa2, b - 2 * wb2), ((a - wa2) / 2, 0, wa2, b - 2 * wb2)]
        else:
            spec = [(0, 0, a, b)]
        outline = orect(centre, u, a, b)
        if not self.layout.is_free(np.vstack([outline, centre[None, :]])):
            return False
        wings = [(centre + u * du + v * dv, u, wa_, wb_) for du, dv, wa_, wb_ in spec if wa_ > 2 and wb_ > 2]
        bld = Building(wings, style, colour, height_m, cap_m=self.hmax)
        if shape == "court":
            bld.courtyard = orect(centre, u, a - 2 * min(wa, a * 0.3), b - 2 * min(wb, b * 0.3))
        for _ in range(units):
            wc, wu, wa_, wb_ = wings[int(self.rng.integers(len(wings)))]
            su, sv = self.rng.uniform(1.2, 4.0, 2)
            if su + 2 > wa_ or sv + 2 > wb_:
                continue
            off = (self.rng.uniform(-0.5, 0.5) * (wa_ - su - 1.5), self.rng.uniform(-0.5, 0.5) * (wb_ - sv - 1.5))
            wv = np.array([-wu[1], wu[0]])
            cc = wc + wu * off[0] + wv * off[1]
            extra = float(min(self.rng.uniform(1.0, 3.5), self.hmax - height_m))
            if extra > 0.3:
                bld.units.append((orect(cc, wu, su, sv), extra))
        if style in ("flat", "metal") and self.rng.random() < 0.12 and height_m + 0.6 <= self.hmax:
            bld.panels = self._solar_rows(wings[int(self.rng.integers(len(wings)))])
        if style in ("flat", "green", "metal") and height_m + 0.6 <= self.hmax:
            self._roof_clutter(bld, wings, style)
        self.scene.buildings.append(bld)
        return True

    def _roof_clutter(self, bld: Building, wings: list, style: str) -> None:
        """What real flat roofs carry: vents and AC boxes (often in a row along a wall), skylights, repaired
        patches and water stains: small, high-contrast detail where real images have their keypoints."""
        r = self.rng
        for c, u, a, b in wings:
            v = np.array([-u[1], u[0]])
            area = a * b
            if style != "metal":
                for _ in range(int(r.poisson(area / 120.0))):
                    s_ = r.uniform(0.5, 1.3)
                    p = c + u * r.uniform(-0.45, 0.45) * (a - 2) + v * r.uniform(-0.45, 0.45) * (b - 2)
                    bld.vents.append(orect(p, u, s_, s_ * r.uniform(0.6, 1.5)))
                if r.random() < 0.35 and a > 8:             # a row of AC units along one side
                    side = 1.0 if r.random() < 0.5 else -1.0
                    n_ac = int(r.integers(2, 7))
                    for j in range(n_ac):
                        p = c + u * ((j - (n_ac - 1) / 2) * 1.6) + v * side * (b / 2 - 1.4)
                        bld.vents.append(orect(p, u, 1.1, 0.9))
            if r.random() < (0.25 if style == "metal" else 0.2) and a > 10 and b > 8:   # skylights in a row
                n_sky = int(r.integers(2, 8))
                shade = int(r.choice([70, 84, 176]))
                pitch = r.uniform(3.0, 6.0)
                for j in range(n_sky):
                    off = (j - (n_sky - 1) / 2) * pitch
                    if abs(off) < a / 2 - 2.0:
                        bld.skylights.append((orect(c + u * off, u, r.uniform(1.2, 2.2), r.uniform(1.2, 3.0)),
                                              shade))
            for _ in range(int(r.poisson(area / 400.0)) if min(a, b) > 4.0 else 0):   # patches, ponding stains
                p = c + u * r.uniform(-0.4, 0.4) * a + v * r.uniform(-0.4, 0.4) * b
                q = orect(p, rotate(u, r.normal(0, 0.05)), r.uniform(1.5, min(8.0, a * 0.5)),
                          r.uniform(1.0, min(5.0, b * 0.5)))
                bld.stains.append((q, int(r.choice([104, 112, 118, 140, 146]))))

    def _solar_rows(self, wing: tuple[np.ndarray, np.ndarray, float, float]) -> list[np.ndarray]:
        """Rows of solar panels (1.7 m deep, 0.9 m apart) over part of a flat roof wing."""
        c, u, a, b = wing
        v = np.array([-u[1], u[0]])
        fa, fb = a * self.rng.uniform(0.4, 0.8), b * self.rng.uniform(0.4, 0.8)
        rows = []
        for off in np.arange(-fb / 2 + 0.85, fb / 2 - 0.85, 2.6):
            rows.append(orect(c + v * off, u, fa, 1.7))
        return rows

    def parking(self, centre: np.ndarray, u: np.ndarray, a: float, b: float, occupancy: float) -> None:
        """Surface lot: asphalt, rows of 2.5 m x 5 m bays along ``u`` with 6 m aisles, parked cars."""
        self.ground(orect(centre, u, a, b), "asphalt")
        v = np.array([-u[1], u[0]])
        n_bays = int((a - 2.0) // 2.5)
        n_rows = int((b - 2.0) // 16.0)
        single = n_rows == 0 and b >= 11.5               # one row of bays along a 6 m aisle
        if n_bays < 1 or (n_rows < 1 and not single):
            return
        occ = min(1.0, occupancy * self.cd)
        x0 = -n_bays * 2.5 / 2
        for row in range(max(n_rows, 1)):
            yc = -b / 2 + 1.0 + 8.0 + row * 16.0        # aisle centre of this double row
            if single:
                yc = -b / 2 + 0.5 + 3.0
            for side in ((1.0,) if single else (-1.0, 1.0)):
                y_in, y_out = yc + side * 3.0, yc + side * 8.0
                xs = x0 + 2.5 * np.arange(n_bays + 1)
                for x in xs:
                    p0 = centre + u * x + v * y_in
                    p1 = centre + u * x + v * y_out
                    self.scene.markings.append(np.stack([p0, p1]))
                full = self.rng.random(n_bays) < occ
                for k in np.flatnonzero(full):
                    cc = centre + u * (x0 + 2.5 * k + 1.25) + v * ((y_in + y_out) / 2 + self.rng.normal(0, 0.15))
                    self.car(cc, rotate(v, self.rng.normal(0, 0.03)))

    def car(self, centre: np.ndarray, heading: np.ndarray, length_m: float | None = None) -> None:
        length = float(length_m if length_m is not None else self.rng.uniform(4.0, 5.0))
        width = 1.8 if length < 6 else 2.5
        col = int(self.rng.choice(len(CAR_COLOURS), p=CAR_WEIGHTS))
        self.scene.cars.append((orect(centre, heading, length, width), col))

    # -- block uses ---------------------------------------------------------------------------------------
    def fill(self, block: Block) -> None:
        """Fill a block by its use; slivers left between wide roads (or inverted insets) become paved."""
        inner = block.inner
        _, _, a, b = quad_frame(inner)
        if min(a, b) < 12.0 or _signed_area(inner) * _signed_area(block.quad) <= 0:
            if min(a, b) > 1.0 and _signed_area(inner) * _signed_area(block.quad) > 0:
                self.ground(inner, "paving")
            return
        getattr(self, "_use_" + block.use)(inner)

    def _parcels(self, quad: np.ndarray, frontage: tuple[float, float], two_rows_from_m: float):
        """Split a block into parcels (sub-quads): rows along s, one or two rows deep."""
        _, _, a, b = quad_frame(quad)
        rows = [(0.0, 1.0)]
        if b > two_rows_from_m:
            m = float(self.rng.uniform(0.42, 0.58))
            rows = [(0.0, m), (m, 1.0)]
        out = []
        for t0, t1 in rows:
            n = max(1, int(round(a / self.rng.uniform(*frontage))))
            cuts = np.linspace(0, 1, n + 1)
            cuts[1:-1] += self.rng.uniform(-0.25, 0.25, n - 1) / n
            for s0, s1 in zip(cuts[:-1], cuts[1:], strict=True):
                out.append(sub_quad(quad, s0, s1, t0, t1))
        return out

    def _use_houses(self, quad: np.ndarray) -> None:
        r = self.rng
        for parcel in self._parcels(quad, (12.0, 22.0), 40.0):
            c, u, a, b = quad_frame(parcel)
            self.ground(parcel, str(r.choice(["lawn", "paving", "soil", "lawn"])))
            self.scene.lines.append(([parcel], (150, 146, 140), Material.WALL, 0.3, 1.2))
            if r.random() < 0.25 * self.td * 2:
                self.tree(c + (r.random(2) - 0.5) * [a, b] * 0.8)
            if r.random() < 0.3 * self.td * 2:
                self.tree(bilinear(parcel, r.uniform(0.1, 0.9), r.uniform(0.05, 0.2)))
            if r.random() > 0.85 * self.bd:
                continue
            ba, bb = a * r.uniform(0.55, 0.8), b * r.uniform(0.45, 0.7)
            if ba < 5 or bb < 5:
                continue
            off = (r.random(2) - 0.5) * [a - ba, b - bb] * 0.6
            bc = c + u * off[0] + np.array([-u[1], u[0]]) * off[1]
            bu = rotate(u, r.normal(0, 0.04)) if r.random() < 0.3 else u
            style = str(r.choice(["gable", "hip", "flat", "flat", "gable"]))
            if style == "flat":
                col = _jitter(r, ROOF_FLAT_COLOURS[r.integers(len(ROOF_FLAT_COLOURS))], 12)
            else:
                col = _jitter(r, ROOF_TILE_COLOURS[r.integers(len(ROOF_TILE_COLOURS))], 12)
            shape = "L" if r.random() < 0.3 else "rect"
            self.building(bc, bu, ba, bb, style, col, self.height(3.0, 10.0), shape,
                          units=int(r.integers(0, 3)) if style == "flat" else 0)
            if r.random() < 0.4 * self.cd:
                self.car(bilinear(parcel, r.uniform(0.2, 0.8), 0.12), u)

    def _use_midrise(self, quad: np.ndarray) -> None:
        r = self.rng
        z = self.layout.downtown(quad.mean(axis=0))
        for parcel in self._parcels(quad, (20.0, 40.0), 50.0):
            c, u, a, b = quad_frame(parcel)
            self.ground(parcel, str(r.choice(["paving", "asphalt", "paving"])))
            if r.random() > 0.9 * self.bd:
                self.parking(c, u, a * 0.9, b * 0.9, 0.6)
                continue
            ba, bb = a * r.uniform(0.7, 0.92), b * r.uniform(0.6, 0.85)
            if ba < 6 or bb < 6:
                continue
            col = _jitter(r, ROOF_FLAT_COLOURS[r.integers(len(ROOF_FLAT_COLOURS))], 14)
            style = "green" if r.random() < 0.08 else "flat"
            shape = str(r.choice(["rect", "rect", "rect", "rect", "L", "L", "T", "U"]))
            if not self.building(c, u, ba, bb, style, col, self.height(9.0, 16.0 + 20.0 * z, 4.0 + 6 * z), shape,
                                 units=int(r.integers(1, 6))):
                self._green_lot(parcel)
            if r.random() < 0.5 * self.td:
                self.tree(bilinear(parcel, r.uniform(0.1, 0.9), 0.04), 3.0)

    def _use_towers(self, quad: np.ndarray) -> None:
        r = self.rng
        c, u, a, b = quad_frame(quad)
        self.ground(quad, "paving")
        for lot in self._parcels(quad, (45.0, 70.0), 70.0):
            lc, lu, la, lb = quad_frame(lot)
            if r.random() < 0.2:
                self.ground(lot, "lawn")
                self.trees_in(lot, 90.0)
                continue
            z = self.layout.downtown(lc)
            podium_h = self.height(6.0, 14.0)
            pa, pb = la * r.uniform(0.75, 0.92), lb * r.uniform(0.7, 0.9)
            col = _jitter(r, ROOF_FLAT_COLOURS[r.integers(len(ROOF_FLAT_COLOURS))], 12)
            if not self.building(lc, lu, pa, pb, "flat", col, podium_h, "rect", units=int(r.integers(0, 4))):
                self._green_lot(lot)             # land that cannot be built on (a riverbank): a pocket park
                continue
            ta, tb = pa * r.uniform(0.45, 0.8), pb * r.uniform(0.45, 0.8)
            tu = rotate(lu, r.choice([0.0, 0.0, r.uniform(-0.4, 0.4)]))
            tcol = _jitter(r, ROOF_FLAT_COLOURS[r.integers(len(ROOF_FLAT_COLOURS))], 16)
            th = max(podium_h + 6.0, self.height(20.0, 30.0 + 20 * z, 10.0 + 12.0 * z))
            self.building(lc + (r.random(2) - 0.5) * 4, tu, ta, tb, str(r.choice(["flat", "flat", "metal"])),
                          tcol, min(th, self.hmax), str(r.choice(["rect", "rect", "L", "court", "U"])),
                          units=int(r.integers(2, 7)))
            for s in np.linspace(0.08, 0.92, 5):
                self.tree(bilinear(lot, s, 0.04), 2.5)

    def _use_apartments(self, quad: np.ndarray) -> None:
        r = self.rng
        c, u, a, b = quad_frame(quad)
        self.ground(quad, "lawn")
        ang = r.choice([0.0, 0.0, r.uniform(-0.5, 0.5)])
        au = rotate(u, ang)
        av = np.array([-au[1], au[0]])
        depth = r.uniform(12.0, 16.0)
        pitch = r.uniform(30.0, 42.0)
        length = r.uniform(45.0, 85.0)
        n_rows = max(1, int((b - 10) // pitch))
        n_cols = max(1, int((a - 10) // (length + 12)))
        col = _jitter(r, np.array([200, 198, 192]), 10)
        roof = str(r.choice(["flat", "flat", "hip"]))
        for i in range(n_rows):
            for j in range(n_cols):
                bc = c + av * ((i - (n_rows - 1) / 2) * pitch) + au * ((j - (n_cols - 1) / 2) * (length + 12))
                if r.random() < 0.7:
                    self.parking(bc + av * (pitch / 2), au, length, min(16.5, pitch - depth - 3), 0.75)
                if r.random() > 0.95 * self.bd:
                    continue
                self.building(bc, au, length * r.uniform(0.85, 1.0), depth, roof, _jitter(r, np.array(col), 6),
                              self.height(30.0, 45.0, 6.0), "rect", units=int(r.integers(2, 4)))
                for s in np.linspace(-0.5, 0.5, int(length // 9) + 1):
                    self.tree(bc + au * s * length - av * (depth / 2 + 4.0), r.uniform(2.0, 3.5))
        self.trees_in(quad, 20.0)

    def _use_industrial(self, quad: np.ndarray) -> None:
        r = self.rng
        c, u, a, b = quad_frame(quad)
        self.ground(quad, str(r.choice(["paving", "gravel", "asphalt"])))
        for lot in self._parcels(quad, (50.0, 90.0), 80.0):
            lc, lu, la, lb = quad_frame(lot)
            if r.random() < 0.25:
                self.parking(lc, lu, la * 0.85, lb * 0.85, 0.5)
                continue
            wa, wb = la * r.uniform(0.6, 0.85), lb * r.uniform(0.55, 0.8)
            col = _jitter(r, ROOF_METAL_COLOURS[r.integers(len(ROOF_METAL_COLOURS))], 10)
            self.building(lc, lu, wa, wb, "metal", col, self.height(6.0, 14.0), "rect", units=int(r.integers(0, 3)))
            for _ in range(int(r.poisson(2.0 * self.cd))):
                self.car(bilinear(lot, r.uniform(0.05, 0.95), r.uniform(0.02, 0.1)), lu, r.uniform(8.0, 12.0))

    def _use_park(self, quad: np.ndarray) -> None:
        r = self.rng
        c, u, a, b = quad_frame(quad)
        self.ground(quad, "lawn")
        for _ in range(int(r.integers(1, 4))):
            pc = bilinear(quad, *r.uniform(0.2, 0.8, 2))
            self.ground(orect(pc, rotate(u, r.uniform(0, np.pi)), r.uniform(10, 40), r.uniform(10, 30)),
                        str(r.choice(["soil", "lawn"])))
        if r.random() < 0.35:
            pc = bilinear(quad, *r.uniform(0.3, 0.7, 2))
            ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
            rad = r.uniform(10, 25) * (1 + 0.2 * np.sin(3 * ang + r.uniform(0, 6)))
            pond = pc + np.stack([np.cos(ang) * rad * 1.4, np.sin(ang) * rad], axis=1)
            self.scene.grounds.append(([pond], _jitter(r, np.array([58, 84, 86]), 8), Material.WATER))
        # winding paths
        for _ in range(int(r.integers(2, 4))):
            t = np.linspace(0, 1, 12)
            s0, s1 = r.random(2)
            wig = 0.08 * np.sin(2 * np.pi * t * r.uniform(0.5, 1.5) + r.uniform(0, 6))
            pts = np.stack([bilinear(quad, (1 - ti) * s0 + ti * s1, np.clip(ti + wi, 0, 1))
                            for ti, wi in zip(t, wig, strict=True)])
            self.scene.lines.append(([pts], _jitter(r, np.array([186, 176, 160]), 8), Material.PLAZA,
                                     r.uniform(2.0, 4.0), 0.0))
        self.trees_in(quad, 110.0)

    def _use_school(self, quad: np.ndarray) -> None:
        r = self.rng
        c, u, a, b = quad_frame(quad)
        self.ground(quad, "soil")
        v = np.array([-u[1], u[0]])
        ta, tb = min(a * 0.6, 140.0), min(b * 0.6, 80.0)
        tc = c + v * (b - tb) / 2 * 0.7
        if ta > 40 and tb > 30:
            rr = tb / 2
            ang = np.linspace(-np.pi / 2, np.pi / 2, 20)
            half = np.stack([np.cos(ang), np.sin(ang)], axis=1)
            straight = ta / 2 - rr
            loc = np.vstack([half * rr + [straight, 0], -half * rr - [straight, 0]])
            oval = tc + loc[:, :1] * u + loc[:, 1:] * v
            self.scene.grounds.append(([oval], _jitter(r, np.array([176, 84, 66]), 10), Material.TRACK))
            inner = tc + loc[:, :1] * u * ((ta - 12) / ta) + loc[:, 1:] * v * ((tb - 12) / tb)
            self.ground(inner, str(r.choice(["lawn", "soil"])))
            self.scene.lines.append(([oval, inner], (236, 236, 236), Material.MARKING, 0.12, 0.0))
        bc = c - v * (b / 2 - min(25.0, b * 0.2))
        self.building(bc, u, min(a * 0.7, 90.0), min(16.0, b * 0.3), "flat",
                      _jitter(r, ROOF_FLAT_COLOURS[r.integers(len(ROOF_FLAT_COLOURS))], 10),
                      self.height(12.0, 18.0), str(r.choice(["rect", "L", "T"])), units=3)
        self.trees_in(quad, 25.0)

    def _use_parking(self, quad: np.ndarray) -> None:
        c, u, a, b = quad_frame(quad)
        self.ground(quad, "paving")
        self.parking(c, u, a * 0.92, b * 0.92, self.rng.uniform(0.3, 0.9))

    def _use_construction(self, quad: np.ndarray) -> None:
        r = self.rng
        c, u, a, b = quad_frame(quad)
        self.ground(quad, str(r.choice(["soil", "soil", "gravel", "field"])))
        for _ in range(int(r.integers(2, 10))):
            pc = bilinear(quad, *r.uniform(0.1, 0.9, 2))
            self.ground(orect(pc, rotate(u, r.uniform(0, np.pi) if r.random() < 0.4 else 0.0), r.uniform(4, 28),
                              r.uniform(3, 20)), str(r.choice(["gravel", "soil", "paving", "asphalt"])))
        for _ in range(int(r.integers(0, 7))):
            pc = bilinear(quad, *r.uniform(0.1, 0.9, 2))
            self.car(pc, rotate(u, r.uniform(0, np.pi)), r.uniform(5.0, 10.0))
        for _ in range(int(r.integers(0, 4))):     # site cabins and containers
            pc = bilinear(quad, *r.uniform(0.1, 0.9, 2))
            col = ((226, 226, 220), (70, 100, 150), (190, 80, 50), (120, 130, 110))[int(r.integers(4))]
            self.building(pc, u, 6.0, 2.5, "flat", _jitter(r, np.array(col), 10), 2.6, "rect", 0)
        if r.random() < 0.5:                        # a structure going up: a grey deck on its storeys
            self.building(c, u, a * r.uniform(0.25, 0.55), b * r.uniform(0.2, 0.45), "flat",
                          _jitter(r, np.array([168, 166, 160]), 16), self.height(3.0, 24.0), "rect", 0)

    def _use_fields(self, quad: np.ndarray) -> None:
        r = self.rng
        c, u, a, b = quad_frame(quad)
        self.ground(quad, "field")
        n = int(b // 1.2)
        v = np.array([-u[1], u[0]])
        rows = [np.stack([c - u * a / 2 + v * (k * 1.2 - b / 2), c + u * a / 2 + v * (k * 1.2 - b / 2)])
                for k in range(n)]
        self.scene.lines.append((rows, _jitter(r, np.array([96, 120, 60]), 12), Material.FIELD, 0.4, 0.0))
        self.trees_in(quad, 4.0)


USES = ("houses", "midrise", "towers", "apartments", "industrial", "park", "school", "parking",
        "construction", "fields")


def choose_use(rng: np.random.Generator, z: float, park_fraction: float) -> str:
    """Block use by downtown score z in [0, 1]: towers in the centre, houses and fields outside."""
    w_down = np.array([0.02, 0.28, 0.48, 0.15, 0.0, 0.06, 0.0, 0.03, 0.0, 0.0])
    w_mid = np.array([0.24, 0.3, 0.05, 0.22, 0.06, 0.07, 0.04, 0.015, 0.02, 0.0])
    w_out = np.array([0.47, 0.08, 0.0, 0.12, 0.14, 0.08, 0.03, 0.01, 0.04, 0.03])
    w = np.where(z > 0.5, (z - 0.5) * 2 * w_down + (1 - (z - 0.5) * 2) * w_mid,
                 z * 2 * w_mid + (1 - z * 2) * w_out)
    w[USES.index("park")] *= park_fraction / 0.08
    return USES[int(rng.choice(len(USES), p=w / w.sum()))]


# ---------------------------------------------------------------------------------------------------------
def paint_scene(canvas: Canvas, scene: Scene, rng: np.random.Generator) -> None:
    """Draw grounds, lines, markings, cars, trees, buildings, in that order."""
    for polys, col, mat in scene.grounds:
        canvas.fill(polys, col, mat)
    for polys, col, mat, width, height in scene.lines:
        if mat == Material.MARKING:
            canvas.paint_lines(polys, col, mat, width)
        else:
            canvas.lines(polys, col, mat, width, height, closed=mat == Material.WALL)
    canvas.paint_lines(scene.markings, (226, 226, 222), Material.MARKING, 0.12)
    paint_cars(canvas, scene.cars)
    paint_trees(canvas, scene.trees, rng)
    for b in scene.buildings:
        paint_building(canvas, b)


def paint_cars(canvas: Canvas, cars: list[tuple[np.ndarray, int]]) -> None:
    """Cars grouped by colour (one fill per colour), with darker glass front and back."""
    if not cars:
        return
    polys = np.stack([c[0] for c in cars])
    cols = np.array([c[1] for c in cars])
    for k in np.unique(cols):
        sel = polys[cols == k]
        canvas.fill(list(sel), CAR_COLOURS[k], Material.CAR, 1.5, NEUTRAL_SHADE)
    centre = polys.mean(axis=1, keepdims=True)
    glass = centre + (polys - centre) * 0.72
    roof = centre + (polys - centre) * 0.45
    canvas.shade_fill(list(glass), 70)
    for k, q in enumerate(roof):               # each car its own shade of its colour (paint, dirt, sheen)
        canvas.shade_fill([q], 112 + (k * 53) % 33)


#: Direction (image x right, y down) the crowns' baked-in light comes from: the map's late-morning sun in the
#: south-south-east, as the realistic presets' database sun.
CROWN_LIGHT = np.array([0.5, 0.75, 0.43])


def paint_trees(canvas: Canvas, trees: list[tuple[float, float, float, float, int]],
                rng: np.random.Generator) -> None:
    """Crowns of several foliage clumps each: an irregular outline, a lumpy height surface and its shading.

    A crown is the union of 3-8 clumps (ellipsoid caps of 0.35-0.65 of the crown radius scattered over it); the
    height of a pixel is the highest clump over it, so neighbouring clumps meet in darker creases. Brightness
    is the surface lit from ``CROWN_LIGHT`` with an ambient share and a leaf-cluster grain at 0.3-0.6 m; the
    colour varies per tree (hue, value) and slightly per clump. Nothing is stepped, so no ring appears, and the
    darkest crease stays above half the crown's brightness (no black fringe). Drawn tree by tree over its
    bounding box, into all four layers where the crown is.
    """
    if not trees:
        return
    g = canvas.gsd_m
    light = CROWN_LIGHT / np.linalg.norm(CROWN_LIGHT)
    for x, y, rad, h, k in trees:
        n_clumps = int(rng.integers(3, 6)) + int(rad > 3.5) * int(rng.integers(0, 4))
        ang = rng.uniform(0, 2 * np.pi, n_clumps)
        dist = rad * np.sqrt(rng.uniform(0.0, 1.0, n_clumps)) * 0.5
        cr = rad * rng.uniform(0.35, 0.65, n_clumps)
        cx = np.concatenate([[x], x + dist * np.cos(ang)])
        cy = np.concatenate([[y], y + dist * np.sin(ang)])
        cr = np.concatenate([[rad * rng.uniform(0.5, 0.7)], cr])
        ch = np.concatenate([[1.0], rng.uniform(0.8, 0.97, n_clumps)])           # relative clump tops
        x0 = int(np.floor((cx - cr).min() / g - 0.5))
        x1 = int(np.ceil((cx + cr).max() / g - 0.5)) + 1
        y0 = int(np.floor((cy - cr).min() / g - 0.5))
        y1 = int(np.ceil((cy + cr).max() / g - 0.5)) + 1
        x0c, y0c = max(x0, 0), max(y0, 0)
        x1c, y1c = min(x1, canvas.width_px), min(y1, canvas.height_px)
        if x1c <= x0c or y1c <= y0c:
            continue
        ys, xs = np.mgrid[y0c:y1c, x0c:x1c].astype(np.float32)
        xs = (xs + 0.5) * g
        ys = (ys + 0.5) * g
        dx = xs[None] - cx[:, None, None].astype(np.float32)
        dy = ys[None] - cy[:, None, None].astype(np.float32)
        q = 1.0 - (dx * dx + dy * dy) / (cr[:, None, None] ** 2).astype(np.float32)
        cap = np.sqrt(np.clip(q, 0.0, None))                        # ellipsoid cap of each clump, 0..1
        z = np.where(q > 0, (0.55 + 0.45 * cap) * ch[:, None, None].astype(np.float32), 0.0)
        best = z.argmax(axis=0)
        top = np.take_along_axis(z, best[None], axis=0)[0]
        inside = top > 0
        if not inside.any():
            continue
        # surface normal of the winning clump (cap slope), lit from `light`
        bx = np.take_along_axis(dx, best[None], axis=0)[0]
        by = np.take_along_axis(dy, best[None], axis=0)[0]
        r2 = cr[best].astype(np.float32) ** 2
        c_b = np.maximum(np.take_along_axis(cap, best[None], axis=0)[0], 0.15)
        nx, ny, nz = bx / r2 / c_b, by / r2 / c_b, np.full_like(c_b, 1.0 / float(rad))
        norm = np.sqrt(nx * nx + ny * ny + nz * nz)
        lam = np.clip((nx * light[0] + ny * light[1] + nz * light[2]) / norm, 0.0, 1.0)
        grain = rng.random((top.shape[0] + 1, top.shape[1] + 1), dtype=np.float32)
        grain = 0.25 * (grain[:-1, :-1] + grain[1:, :-1] + grain[:-1, 1:] + grain[1:, 1:])   # clusters ~0.5 m
        gain = (0.55 + 0.5 * lam) * (0.8 + 0.2 * top) * (0.55 + 0.9 * grain)
        shade = np.clip(NEUTRAL_SHADE * gain, 60, 190).astype(np.uint8)
        base = TREE_COLOURS[k].astype(np.float32)
        tint = np.array([rng.normal(1.0, 0.07), rng.normal(1.0, 0.05), rng.normal(1.0, 0.08)], np.float32)
        clump_tint = 1.0 + rng.normal(0.0, 0.04, len(cx)).astype(np.float32)
        col = np.clip(base * tint * rng.uniform(0.85, 1.12) * clump_tint[best][..., None], 0, 255)
        win = (slice(y0c, y1c), slice(x0c, x1c))
        canvas.rgb[win][inside] = col[inside].astype(np.uint8)
        canvas.shade[win][inside] = shade[inside]
        canvas.material[win][inside] = int(Material.TREE)
        canvas.dsm_m[win][inside] = np.maximum(top[inside] * float(h), 5.0)


def paint_building(canvas: Canvas, b: Building) -> None:
    col = b.colour
    h = b.height_m
    rects = [orect(c, u, a, bb) for c, u, a, bb in b.wings]
    mat = {"flat": Material.ROOF_FLAT, "gable": Material.ROOF_TILE, "hip": Material.ROOF_TILE,
           "metal": Material.ROOF_METAL, "green": Material.ROOF_GREEN}[b.style]
    if b.style == "green":
        col = (92, 130, 70)
    canvas.fill(rects, col, mat, h)
    if b.style in ("flat", "green"):
        canvas.shade_lines([np.vstack([r, r[:1]]) for r in rects], 150, 0.5)
        joints = []
        for c, u, a, bb in b.wings:
            long_u, L, W = (u, a, bb) if a >= bb else (np.array([-u[1], u[0]]), bb, a)
            n = np.array([-long_u[1], long_u[0]])
            if L > 28:
                k = int(L // 14)
                for s in np.linspace(-L / 2, L / 2, k + 1)[1:-1]:
                    joints.append(np.stack([c + long_u * s - n * W / 2, c + long_u * s + n * W / 2]))
        canvas.shade_lines(joints, 142, 0.3)
    elif b.style == "metal":
        lines = []
        for c, u, a, bb in b.wings:
            v = np.array([-u[1], u[0]])
            long_u = u if a >= bb else v
            short_len, long_len = min(a, bb), max(a, bb)
            n = np.array([-long_u[1], long_u[0]])
            for s in np.arange(-long_len / 2 + 0.5, long_len / 2, 1.0):
                lines.append(np.stack([c + long_u * s - n * short_len / 2, c + long_u * s + n * short_len / 2]))
            if long_len > 30:
                canvas.shade_fill([orect(c, long_u, long_len * 0.8, 2.0)], 175)
        canvas.shade_lines(lines, 116)
        canvas.shade_lines([np.vstack([r, r[:1]]) for r in rects], 140, 0.4)
    else:
        for c, u, a, bb in b.wings:
            ru = u if a >= bb else np.array([-u[1], u[0]])      # ridge direction: along the long side
            L, W = max(a, bb), min(a, bb)
            n = np.array([-ru[1], ru[0]])
            side1 = orect(c + n * W / 4, ru, L, W / 2)
            side2 = orect(c - n * W / 4, ru, L, W / 2)
            if b.style == "gable":
                canvas.shade_fill([side1], 146)
                canvas.shade_fill([side2], 106)
            else:
                r1, r2 = c - ru * (L - W) / 2, c + ru * (L - W) / 2
                q = orect(c, ru, L, W)
                canvas.shade_fill([np.stack([q[0], q[1], r2, r1])], 106)
                canvas.shade_fill([np.stack([q[3], q[2], r2, r1])], 146)
                canvas.shade_fill([np.stack([q[0], r1, q[3]])], 122)
                canvas.shade_fill([np.stack([q[1], r2, q[2]])], 134)
            rows = [np.stack([c - ru * L / 2 + n * o, c + ru * L / 2 + n * o])
                    for o in np.arange(-W / 2 + 0.6, W / 2, 0.9) if abs(o) > 0.3]
            canvas.shade_lines(rows, 118)
            canvas.shade_lines([np.stack([c - ru * L / 2, c + ru * L / 2])], 168, 0.3)
            cv_ridge = orect(c, ru, L - 1.0, W / 3 - 0.5)   # kept inside the wing despite rounding
            canvas.dsm_fill([cv_ridge], min(h + 0.15 * W, b.cap_m))
    if b.courtyard is not None:
        canvas.fill([b.courtyard], (150, 146, 138), Material.PLAZA, 0.0)
    for q, shade in b.stains:
        canvas.shade_fill([q], shade)
    for q, shade in b.skylights:
        canvas.shade_fill([q], shade)
    if b.vents:
        grey = 150 + int(h * 7) % 60
        canvas.fill(b.vents, (grey, grey, grey + 3), Material.ROOF_UNIT, min(h + 0.5, b.cap_m), 140)
    if b.panels:
        canvas.fill(b.panels, (40, 50, 76), Material.ROOF_UNIT, min(b.height_m + 0.6, b.cap_m), 128)
        canvas.shade_lines([np.vstack([p, p[:1]]) for p in b.panels], 150)
    for k, (poly, extra) in enumerate(b.units):
        unit_grey = 150 + (k * 37 + int(h * 10)) % 50
        canvas.fill([poly], (unit_grey, unit_grey, unit_grey + 2), Material.ROOF_UNIT, h + extra, 136)
