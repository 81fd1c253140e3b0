"""Street network and blocks of the procedural city (pure geometry, metres, x right / y down).

The network is a warped, jittered grid: arterial lines every 300-450 m with local streets between them, each
line slightly tilted, the whole grid bent by a gentle sinusoidal warp, a few local segments removed (merged
blocks, dead ends), plus one diagonal arterial and a river with a curved riverside road. Blocks are the grid
cells inset by half the road width plus the sidewalk.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from aerial_loc_env import portable

KEEPOUT_CELL_M = 1.0  # resolution of the coarse mask of land that blocks must not build on
MAX_GROUP = 4         # most grid cells one use (apartment complex, park, ...) spans


@dataclass
class Road:
    """A straight road segment (or a polyline for curved roads) with its width and markings style."""

    points: np.ndarray              # (K, 2) metres, K >= 2
    width_m: float
    arterial: bool
    sidewalk_m: float
    bridge: bool = False
    ext_m: tuple[float, float] | None = None   # grid segments: run-on into the junction at each end (flat ends)


@dataclass
class Block:
    quad: np.ndarray                # (4, 2) the grid cell's corners (road centre lines)
    inner: np.ndarray               # (4, 2) buildable area after roads and sidewalks
    group: int                      # blocks merged through removed streets share a group (and a use)
    use: str = ""


@dataclass
class Layout:
    width_m: float
    height_m: float
    roads: list[Road]
    blocks: list[Block]
    intersections: list[tuple[np.ndarray, list[tuple[np.ndarray, float]]]]  # node, [(unit dir, width)]
    centre_m: np.ndarray            # downtown centre
    downtown_radius_m: float
    keepout: np.ndarray             # (h, w) uint8 at KEEPOUT_CELL_M: 1 where nothing may be built
    river: np.ndarray | None = None  # (K, 2) centre line
    river_width_m: float = 0.0
    notes: dict = field(default_factory=dict)

    def is_free(self, pts_m: np.ndarray) -> bool:
        """True when no point of ``pts_m`` (N, 2) falls on the keep-out mask (points off the map are free)."""
        return not bool(_on_mask(self.keepout, pts_m).any())

    def downtown(self, p: np.ndarray) -> float:
        """1 at the centre of downtown, falling off as a Gaussian of the distance."""
        d2 = float(np.sum((np.asarray(p) - self.centre_m) ** 2))
        return portable.exp(-0.5 * d2 / self.downtown_radius_m**2)


def _grid_lines(rng: np.random.Generator, extent_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions of grid lines covering [-margin, extent + margin] and whether each is an arterial."""
    pos, art = [], []
    x = -float(rng.uniform(40.0, 140.0))
    next_art = x + float(rng.uniform(120.0, 350.0))
    while x < extent_m + 60.0:
        pos.append(x)
        art.append(False)
        gap = float(rng.uniform(85.0, 150.0))
        if x + gap >= next_art - 40.0:
            x = next_art
            pos.append(x)
            art.append(True)
            next_art = x + float(rng.uniform(330.0, 460.0))
            x += float(rng.uniform(85.0, 150.0))
        else:
            x += gap
    pos.append(x)
    art.append(False)
    p = np.asarray(pos)
    keep = np.concatenate([[True], np.diff(p) > 50.0])
    return p[keep], np.asarray(art)[keep]


def _inset_quad(quad: np.ndarray, inset: np.ndarray) -> np.ndarray:
    """Offset each edge k (quad[k] -> quad[k+1]) inward by inset[k] and intersect neighbouring edges."""
    centre = quad.mean(axis=0)
    p0 = quad
    d = np.roll(quad, -1, axis=0) - quad
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    flip = np.sum((centre - p0) * n, axis=1) < 0
    n[flip] *= -1
    q = p0 + n * inset[:, None]             # a point on each offset line
    out = np.empty_like(quad)
    for k in range(4):
        a, b = k - 1, k                     # corner k lies on edges k-1 and k
        m = np.stack([d[a], -d[b]], axis=1)
        det = np.linalg.det(m)
        if abs(det) < 1e-9:
            out[k] = q[b]
            continue
        t = np.linalg.solve(m, q[b] - q[a])
        out[k] = q[a] + d[a] * t[0]
    return out


def _smooth_curve(rng: np.random.Generator, length_m: float, amp_m: float, n: int) -> np.ndarray:
    """A smooth random offset profile: sum of three sinusoids with random phases."""
    s = np.linspace(0.0, 1.0, n)
    out = np.zeros(n)
    for k, a in ((1, 1.0), (2, 0.5), (3, 0.25)):
        out += a * amp_m * np.sin(2 * np.pi * (k * s * length_m / 1400.0) + rng.uniform(0, 2 * np.pi))
    return out


def _on_mask(mask: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Per point (N, 2) metres: True where it falls on ``mask`` (points off the map are not on it)."""
    ij = np.floor(np.asarray(pts) / KEEPOUT_CELL_M).astype(np.int64)
    h, w = mask.shape
    ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
    out = np.zeros(len(ij), bool)
    out[ok] = mask[ij[ok, 1], ij[ok, 0]] > 0
    return out


def _water_share(mask: np.ndarray, pts: np.ndarray) -> float:
    """Share of points along a polyline (resampled every ~5 m) that fall on ``mask`` (river and banks)."""
    seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    t = np.linspace(0.0, s[-1], max(8, int(s[-1] / 5.0)))
    xy = np.stack([np.interp(t, s, pts[:, 0]), np.interp(t, s, pts[:, 1])], axis=1)
    return float(_on_mask(mask, xy).mean())


def build_layout(rng: np.random.Generator, width_m: float, height_m: float, *, river: bool,
                 downtown_radius_m: float, street_removal: float) -> Layout:
    """Draw the street network, river and blocks (geometry only)."""
    xs, x_art = _grid_lines(rng, width_m)
    ys, y_art = _grid_lines(rng, height_m)
    nx, ny = len(xs), len(ys)
    tilt_x = rng.normal(0.0, 0.035, nx)
    tilt_y = rng.normal(0.0, 0.035, ny)
    tilt_x[x_art] *= 0.5
    tilt_y[y_art] *= 0.5
    X, Y = np.meshgrid(xs, ys, indexing="ij")     # (nx, ny)
    px = X + tilt_x[:, None] * (Y - height_m / 2)
    py = Y + tilt_y[None, :] * (X - width_m / 2)
    # gentle large-scale warp so long streets bend
    wa, wl, wp = rng.uniform(8.0, 22.0), rng.uniform(1100.0, 2200.0), rng.uniform(0, 2 * np.pi, 2)
    px = px + wa * np.sin(2 * np.pi * Y / wl + wp[0])
    py = py + wa * np.sin(2 * np.pi * X / wl + wp[1])
    jit = rng.normal(0.0, 2.5, (2, nx, ny))
    local_node = ~(x_art[:, None] | y_art[None, :])
    px = px + jit[0] * local_node
    py = py + jit[1] * local_node
    nodes = np.stack([px, py], axis=-1)

    wx = np.where(x_art, rng.uniform(20.0, 30.0, nx), rng.uniform(8.0, 12.0, nx))   # vertical lines
    wy = np.where(y_art, rng.uniform(20.0, 30.0, ny), rng.uniform(8.0, 12.0, ny))
    swx = np.where(x_art, rng.uniform(3.5, 5.0, nx), rng.uniform(2.0, 3.5, nx))
    swy = np.where(y_art, rng.uniform(3.5, 5.0, ny), rng.uniform(2.0, 3.5, ny))
    # vertical edge (i, j)-(i, j+1) exists unless removed; horizontal edge (i, j)-(i+1, j) likewise
    v_on = np.ones((nx, ny - 1), bool)
    h_on = np.ones((nx - 1, ny), bool)
    v_on &= x_art[:, None] | (rng.random((nx, ny - 1)) >= street_removal)
    h_on &= y_art[None, :] | (rng.random((nx - 1, ny)) >= street_removal)

    # river: a meandering band crossing the map roughly east-west, with a riverside road on one bank
    kh = int(np.ceil(height_m / KEEPOUT_CELL_M))
    kw = int(np.ceil(width_m / KEEPOUT_CELL_M))
    keepout = np.zeros((kh, kw), np.uint8)
    river_line, river_w = None, 0.0
    roads: list[Road] = []
    if river:
        river_w = float(rng.uniform(45.0, 75.0))
        n = 80
        xr = np.linspace(-100.0, width_m + 100.0, n)
        yr = rng.uniform(0.2, 0.8) * height_m + _smooth_curve(rng, width_m, 60.0, n)
        yr += np.linspace(0.0, 1.0, n) * rng.uniform(-0.15, 0.15) * height_m
        river_line = np.stack([xr, yr], axis=1)
        bank = river_w / 2 + 14.0
        side = 1.0 if rng.random() < 0.5 else -1.0
        road_off = bank + 9.0
        ride = np.stack([xr, yr + side * road_off], axis=1)
        roads.append(Road(ride, float(rng.uniform(10.0, 14.0)), True, 3.0))
        cv2.polylines(keepout, [np.rint(river_line / KEEPOUT_CELL_M).astype(np.int32)], False, 1,
                      max(1, int(2 * bank / KEEPOUT_CELL_M)))
        cv2.polylines(keepout, [np.rint(ride / KEEPOUT_CELL_M).astype(np.int32)], False, 1,
                      max(1, int(2 * (road_off - bank + 12.0) / KEEPOUT_CELL_M)))
    river_mask = keepout.copy()
    river_slope = None if river_line is None else np.gradient(river_line[:, 1], river_line[:, 0])

    # one diagonal arterial crossing the map corner to corner-ish
    ang = rng.uniform(np.radians(25), np.radians(65)) * (1 if rng.random() < 0.5 else -1)
    c = np.array([rng.uniform(0.3, 0.7) * width_m, rng.uniform(0.3, 0.7) * height_m])
    d = np.array([np.cos(ang), np.sin(ang)])
    L = float(np.hypot(width_m, height_m))
    diag = np.stack([c - d * L, c + d * L])
    diag_w = float(rng.uniform(20.0, 26.0))
    roads.append(Road(diag, diag_w, True, 4.0))
    cv2.polylines(keepout, [np.rint(diag / KEEPOUT_CELL_M).astype(np.int32)], False, 1,
                  max(1, int((diag_w + 2 * 4.0 + 6.0) / KEEPOUT_CELL_M)))

    if _water_share(river_mask, diag) > 0:
        roads[-1].bridge = True

    def crossing(p0: np.ndarray, p1: np.ndarray, arterial: bool) -> bool | None:
        """None: drop the segment (it runs in the river, or is a local street reaching it); else bridge?"""
        share = _water_share(river_mask, np.stack([p0, p1]))
        if share == 0:
            return False
        if arterial and share < 0.95 and river_line is not None:
            # a bridge must cross the river, not run along it
            slope = float(np.interp((p0[0] + p1[0]) / 2, river_line[:, 0], river_slope))
            tangent = np.array([1.0, slope]) / np.hypot(1.0, slope)
            if abs(float(np.dot(p1 - p0, tangent))) < 0.6 * float(np.linalg.norm(p1 - p0)):
                return True
        return None

    # grid road segments: drop those in the river, then those left isolated (both ends dead)
    cand = []      # (on-array, i, j, key0, key1, width, arterial, sidewalk, bridge)
    for i in range(nx):
        for j in range(ny - 1):
            if v_on[i, j]:
                cand.append((v_on, i, j, (i, j), (i, j + 1), wx[i], x_art[i], swx[i]))
    for i in range(nx - 1):
        for j in range(ny):
            if h_on[i, j]:
                cand.append((h_on, i, j, (i, j), (i + 1, j), wy[j], y_art[j], swy[j]))
    kept = []
    for on, i, j, k0, k1, w, art, sw in cand:
        bridge = crossing(nodes[k0], nodes[k1], bool(art))
        if bridge is None:
            on[i, j] = False
        else:
            kept.append((on, i, j, k0, k1, float(w), bool(art), float(sw), bridge))
    degree: dict[tuple[int, int], int] = {}
    for seg in kept:
        for k in (seg[3], seg[4]):
            degree[k] = degree.get(k, 0) + 1
    node_arms: dict[tuple[int, int], list[tuple[np.ndarray, float]]] = {}
    segs = []
    for on, i, j, k0, k1, w, art, sw, bridge in kept:
        if degree[k0] == 1 and degree[k1] == 1:
            on[i, j] = False
            continue
        p0, p1 = nodes[k0], nodes[k1]
        dvec = (p1 - p0) / np.linalg.norm(p1 - p0)
        node_arms.setdefault(k0, []).append((dvec, w))
        node_arms.setdefault(k1, []).append((-dvec, w))
        segs.append((k0, k1, w, art, sw, bridge))
    for k0, k1, w, art, sw, bridge in segs:
        # run on into the junction by the half-width of the widest other road there; dead ends stop flat
        ext = []
        for k in (k0, k1):
            others = sorted(wo for _, wo in node_arms[k])
            others.remove(w)
            ext.append(max(others) / 2 if others else 0.0)
        roads.append(Road(np.stack([nodes[k0], nodes[k1]]), w, art, sw, bridge, (ext[0], ext[1])))
    intersections = [(nodes[k], arms) for k, arms in node_arms.items() if len(arms) >= 3]

    # blocks, merged through removed streets (union-find over cells)
    parent = np.arange((nx - 1) * (ny - 1))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = int(parent[a])
        return a

    def cell(i: int, j: int) -> int:
        return i * (ny - 1) + j

    size = np.ones_like(parent)

    def union(a: int, b: int) -> None:
        """Merge two cells' groups unless that makes a superblock of more than MAX_GROUP cells."""
        ra, rb = find(a), find(b)
        if ra != rb and size[ra] + size[rb] <= MAX_GROUP:
            parent[ra] = rb
            size[rb] += size[ra]

    for i in range(1, nx - 1):
        for j in range(ny - 1):
            if not v_on[i, j]:
                union(cell(i - 1, j), cell(i, j))
    for i in range(nx - 1):
        for j in range(1, ny - 1):
            if not h_on[i, j]:
                union(cell(i, j - 1), cell(i, j))

    blocks: list[Block] = []
    for i in range(nx - 1):
        for j in range(ny - 1):
            quad = np.stack([nodes[i, j], nodes[i + 1, j], nodes[i + 1, j + 1], nodes[i, j + 1]])
            lo, hi = quad.min(axis=0), quad.max(axis=0)
            if hi[0] < 0 or hi[1] < 0 or lo[0] > width_m or lo[1] > height_m:
                continue
            inset = np.array([
                (wy[j] / 2 + swy[j]) if h_on[i, j] else 0.0,
                (wx[i + 1] / 2 + swx[i + 1]) if v_on[i + 1, j] else 0.0,
                (wy[j + 1] / 2 + swy[j + 1]) if h_on[i, j + 1] else 0.0,
                (wx[i] / 2 + swx[i]) if v_on[i, j] else 0.0,
            ])
            blocks.append(Block(quad, _inset_quad(quad, inset), find(cell(i, j))))

    centre = np.array([rng.uniform(0.35, 0.65) * width_m, rng.uniform(0.35, 0.65) * height_m])
    return Layout(width_m, height_m, roads, blocks, intersections, centre, downtown_radius_m, keepout,
                  river_line, river_w)
