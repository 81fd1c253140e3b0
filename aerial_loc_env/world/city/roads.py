"""Roads, markings, river and traffic of the procedural city, drawn onto a ``Canvas``."""

from __future__ import annotations

import numpy as np

from aerial_loc_env.world.city.content import Filler, paint_cars, paint_trees
from aerial_loc_env.world.city.layout import Layout, Road
from aerial_loc_env.world.city.paint import Canvas, Material

WHITE = (232, 232, 228)
_RING = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], axis=1)
_TALL = np.array([Material.ROOF_FLAT, Material.ROOF_TILE, Material.ROOF_METAL, Material.ROOF_GREEN,
                  Material.ROOF_UNIT, Material.TREE, Material.WATER])
YELLOW = (226, 182, 52)


def _node_widths(layout: Layout) -> dict[tuple[float, float], float]:
    out: dict[tuple[float, float], float] = {}
    for node, arms in layout.intersections:
        out[(round(float(node[0]), 3), round(float(node[1]), 3))] = max(w for _, w in arms)
    return out


def _dashes(p0: np.ndarray, d: np.ndarray, t0: float, t1: float, on_m: float, off_m: float,
            offset: np.ndarray) -> list[np.ndarray]:
    starts = np.arange(t0, t1 - 0.5, on_m + off_m)
    ends = np.minimum(starts + on_m, t1)
    a = p0 + offset + starts[:, None] * d
    b = p0 + offset + ends[:, None] * d
    return list(np.stack([a, b], axis=1))


def _road_markings(road: Road, trims: tuple[float, float]) -> tuple[list, list, list]:
    """(white solid, white dashed, yellow) polylines of one road, kept clear of the intersections."""
    white, dashed, yellow = [], [], []
    w = road.width_m
    pts = road.points
    for p0, p1 in zip(pts[:-1], pts[1:], strict=True):
        L = float(np.linalg.norm(p1 - p0))
        if L < 1e-6:
            continue
        d = (p1 - p0) / L
        n = np.array([-d[1], d[0]])
        t0, t1 = (trims[0], L - trims[1]) if len(pts) == 2 else (0.0, L)
        if t1 - t0 < 4.0:
            continue
        a, b = p0 + d * t0, p0 + d * t1
        if road.arterial:
            for s in (-0.2, 0.2):
                yellow.append(np.stack([a + n * s, b + n * s]))
            for s in (-1.0, 1.0):
                white.append(np.stack([a + n * s * (w / 2 - 0.5), b + n * s * (w / 2 - 0.5)]))
            lanes = max(1, int((w / 2 - 0.6) // 3.2))
            lw = (w / 2 - 0.6) / lanes
            for k in range(1, lanes):
                for s in (-1.0, 1.0):
                    dashed += _dashes(p0, d, t0, t1, 3.0, 5.0, n * s * k * lw)
        elif w >= 9.0:
            dashed += _dashes(p0, d, t0, t1, 3.0, 3.0, n * 0.0)
    return white, dashed, yellow


def _crosswalks(layout: Layout, rng: np.random.Generator) -> tuple[list, list]:
    bars, stops = [], []
    for node, arms in layout.intersections:
        wmax = max(w for _, w in arms)
        busy = wmax >= 18.0
        for d, w in arms:
            if not (busy or rng.random() < 0.35):
                continue
            n = np.array([-d[1], d[0]])
            others = max([wo for do, wo in arms if abs(float(np.dot(do, d))) < 0.7] or [w])
            dist = others / 2 + 5.5
            c = node + d * dist
            for o in np.arange(-w / 2 + 0.6, w / 2 - 0.4, 0.9):
                q = c + n * o
                bars.append(np.stack([q - d * 1.8 - n * 0.22, q + d * 1.8 - n * 0.22, q + d * 1.8 + n * 0.22,
                                      q - d * 1.8 + n * 0.22]))
            sc = c + d * 3.0
            stops.append(np.stack([sc, sc + n * (w / 2 - 0.5)]))
    return bars, stops


def _repairs(canvas: Canvas, roads: list[Road], rng: np.random.Generator) -> None:
    """Patched asphalt (darker or lighter rectangles) and manhole covers: roads are not uniform either."""
    patches: list[list[np.ndarray]] = [[], []]
    covers = []
    for r in roads:
        for p0, p1 in zip(r.points[:-1], r.points[1:], strict=True):
            L = float(np.linalg.norm(p1 - p0))
            d = (p1 - p0) / max(L, 1e-9)
            n = np.array([-d[1], d[0]])
            for t in rng.uniform(0.0, L, rng.poisson(L / 45.0)):
                c = p0 + d * t + n * rng.uniform(-0.4, 0.4) * r.width_m
                a, b = rng.uniform(1.5, 8.0), rng.uniform(1.0, 3.5)
                q = np.stack([c - d * a / 2 - n * b / 2, c + d * a / 2 - n * b / 2, c + d * a / 2 + n * b / 2,
                              c - d * a / 2 + n * b / 2])
                patches[int(rng.random() < 0.35)].append(q)
            for t in rng.uniform(0.0, L, rng.poisson(L / 60.0)):
                covers.append(p0 + d * t + n * rng.uniform(-0.3, 0.3) * r.width_m)
    canvas.shade_fill(patches[0], 112)
    canvas.shade_fill(patches[1], 140)
    for c in covers:
        canvas.circle_px(canvas.shade, tuple(int(v) for v in canvas.px(c)), int(canvas.px_radius(0.35)), 84)


def paint_roads(canvas: Canvas, layout: Layout, filler: Filler, rng: np.random.Generator) -> None:
    """Sidewalks, asphalt, markings, crosswalks, the river with its banks, bridges, traffic, street trees."""
    roads = layout.roads
    ground_roads = [r for r in roads if not r.bridge]
    bridges = [r for r in roads if r.bridge]
    nodes = _node_widths(layout)

    def trims(r: Road) -> tuple[float, float]:
        out = []
        for p in (r.points[0], r.points[-1]):
            w = nodes.get((round(float(p[0]), 3), round(float(p[1]), 3)))
            out.append(0.0 if w is None else w / 2 + 9.0)
        return out[0], out[1]

    def surface(r: Road, width_m: float, extra_m: float, col, mat: Material) -> None:
        if r.ext_m is None:          # curved or long roads: round joins, ends off the map
            canvas.lines([r.points], col, mat, width_m)
            return
        p0, p1 = r.points
        d = (p1 - p0) / np.linalg.norm(p1 - p0)
        n = np.array([-d[1], d[0]]) * width_m / 2
        a = p0 - d * (r.ext_m[0] + extra_m if r.ext_m[0] > 0 else 0.0)
        b = p1 + d * (r.ext_m[1] + extra_m if r.ext_m[1] > 0 else 0.0)
        canvas.fill([np.stack([a - n, b - n, b + n, a + n])], col, mat)

    def draw(group: list[Road]) -> None:
        for r in group:
            col = np.clip(np.array([196, 188, 176]) + rng.integers(-12, 13), 0, 255)
            surface(r, r.width_m + 2 * r.sidewalk_m, r.sidewalk_m, col, Material.SIDEWALK)
        for r in group:
            g = int(rng.integers(72, 100)) if r.arterial else int(rng.integers(84, 112))
            surface(r, r.width_m, 0.0, (g, g, g + int(rng.integers(0, 5))), Material.ASPHALT)
        white, dashed, yellow = [], [], []
        for r in group:
            wt, ds, ye = _road_markings(r, trims(r))
            white += wt
            dashed += ds
            yellow += ye
        canvas.paint_lines(white + dashed, WHITE, Material.MARKING, 0.15)
        canvas.paint_lines(yellow, YELLOW, Material.MARKING, 0.15)

    draw(ground_roads)
    _repairs(canvas, ground_roads, rng)
    bars, stops = _crosswalks(layout, rng)
    canvas.paint_fill(bars, WHITE, Material.MARKING)
    canvas.paint_lines(stops, WHITE, Material.MARKING, 0.45)

    if layout.river is not None:
        w = layout.river_width_m
        line = [layout.river]
        canvas.lines(line, (104, 134, 72), Material.GRASS, w + 28.0)
        for s in (-1.0, 1.0):
            n = np.array([0.0, 1.0])
            canvas.lines([layout.river + n * s * (w / 2 + 8.0)], (176, 110, 90), Material.PLAZA, 3.0)
        canvas.lines(line, (150, 142, 122), Material.GRAVEL, w + 4.0)
        canvas.lines(line, (62, 86, 88), Material.WATER, w)
    draw(bridges)

    # traffic on the straight grid roads and on the curved ones
    cars_before = len(filler.scene.cars)
    for r in roads:
        t0, t1 = trims(r)
        for p0, p1 in zip(r.points[:-1], r.points[1:], strict=True):
            L = float(np.linalg.norm(p1 - p0))
            if L < 12.0:
                continue
            d = (p1 - p0) / L
            n = np.array([-d[1], d[0]])
            lanes = max(1, int((r.width_m / 2 - 0.6) // 3.2))
            lw = (r.width_m / 2 - 0.6) / lanes
            lo, hi = (t0, L - t1) if len(r.points) == 2 else (0.0, L)
            k = rng.poisson(filler.cd * L / (25.0 if r.arterial else 60.0))
            for t in rng.uniform(lo, max(lo, hi), k):
                side = 1.0 if rng.random() < 0.5 else -1.0
                lane = int(rng.integers(lanes))
                off = side * (lane + 0.5) * lw
                filler.car(p0 + d * t + n * off, d * -side, None if rng.random() < 0.93 else rng.uniform(8, 11))
    paint_cars(canvas, filler.scene.cars[cars_before:])

    # street trees on the sidewalks of some roads
    trees = []
    for r in roads:
        if r.bridge or rng.random() > (0.75 if r.arterial else 0.45) * min(1.0, filler.td):
            continue
        t0, t1 = trims(r)
        p0, p1 = r.points[0], r.points[-1]
        if len(r.points) != 2:
            continue
        L = float(np.linalg.norm(p1 - p0))
        d = (p1 - p0) / L
        n = np.array([-d[1], d[0]])
        spacing = rng.uniform(7.0, 11.0)
        for t in np.arange(max(t0, 4.0), L - max(t1, 4.0), spacing):
            for s in (-1.0, 1.0):
                p = p0 + d * t + n * s * (r.width_m / 2 + r.sidewalk_m * 0.5)
                rad = float(rng.uniform(1.8, 3.2))
                ring = p + rad * _RING
                uv = np.rint(np.vstack([p, ring]) / canvas.gsd_m - 0.5).astype(np.int64)
                if (uv < 0).any() or (uv[:, 0] >= canvas.width_px).any() or (uv[:, 1] >= canvas.height_px).any():
                    continue
                mats = canvas.material[uv[:, 1], uv[:, 0]]
                if mats[0] == Material.SIDEWALK and not np.isin(mats, _TALL).any():
                    trees.append((float(p[0]), float(p[1]), rad, float(rng.uniform(6.5, 11.0)),
                                  int(rng.integers(6))))
    paint_trees(canvas, trees, rng)
