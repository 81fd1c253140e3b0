"""Two epochs of the same ground: the map database shows epoch A, the flight sees epoch B.

Real maps are months or years older than the flight: cars have moved, trees are in another season, lawns have
dried, roofs were repainted, buildings were torn down or built, construction sites opened, road markings were
renewed or wore off, the river changed colour. ``change_epoch(orthomap, config, seed)`` draws epoch B from epoch A
by editing A's layers where those things are (it reads the land-cover classes and the height model, so cars
move within lanes and parking bays, new buildings stand on open ground facing like their neighbours, and every
change of height is written to the DSM, so the camera's cast shadows, computed from epoch B's DSM, change too).

Each change kind has a rate in ``EpochConfig`` (the scenario's ``[epoch]`` section); all rates 0 means the same
epoch (``change_epoch`` returns its input). Every kind draws from its own generator spawned from
``(seed, config.seed)``, so turning one rate up never reshuffles another kind's changes. ``epoch_city`` caches
epoch B of the procedural city on disk beside the city, keyed by the city's key, this module's
``GENERATOR_VERSION`` and the config.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import config_to_dict, rng
from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.pages import small_pages
from aerial_loc_env.world.city.paint import WORLD_SATURATION
from aerial_loc_env.world.maps.cache import cached_bundle, spec_key
from aerial_loc_env.world.maps.landcover import LandCover as LC
from aerial_loc_env.world.maps.orthomap import Orthomap

#: Bump whenever change_epoch's output changes for a given input and config: it is part of the cache key and of
#: the benchmark's scenario fingerprint (env/fingerprint.py).
GENERATOR_VERSION = 4

def _muted(colours) -> np.ndarray:
    """Palette colours as the procedural city paints them: pulled towards their grey by ``WORLD_SATURATION``."""
    c = np.asarray(colours, np.float32)
    grey = portable.matmul(c.reshape(-1, 3), np.array([0.299, 0.587, 0.114], np.float32)).reshape(c.shape[:-1])
    return grey[..., None] + WORLD_SATURATION * (c - grey[..., None])


ROOF_COLOURS = _muted([(152, 150, 146), (96, 98, 102), (168, 92, 70), (74, 104, 142), (84, 118, 92),
                       (206, 204, 198), (140, 56, 48), (120, 112, 100), (182, 170, 150)])
STRAW_RGB = _muted([176, 162, 112])
BRANCH_RGB = np.array([112, 102, 92], np.float32)
FRESH_PAINT_RGB = np.array([238, 238, 234], np.float32)
WATER_TINTS = _muted([(112, 110, 78), (62, 104, 74), (38, 58, 86), (118, 126, 120)])
OPEN_GROUND = (LC.LAWN, LC.BARE_SOIL, LC.FIELD, LC.SHRUB)
PAVED = (LC.ROAD, LC.PARKING, LC.LANE_MARKING)
KINDS = ("water", "grass", "markings", "trees", "roofs", "demolished", "construction", "built", "cars_gone",
         "cars_new")


@dataclass(frozen=True)
class EpochConfig:
    """How epoch B (the flight) differs from epoch A (the map); every rate 0 = the same epoch.

    - ``seed``: the epoch's own seed (combined with the city's seed).
    - ``car_turnover``: fraction of A's vehicles gone in B; ``car_arrivals``: vehicles new in B per vehicle of A
      (parked in bays or driving in lanes, like A's).
    - ``leaf_off``: fraction of trees bare in B (leaf-off season: branches over the ground, sparse crown heights).
    - ``grass_dryness``: how far lawns, fields and shrubs turn to dry straw (0 green as in A, 1 fully dry).
    - ``roof_change``: fraction of buildings whose roofs were repainted or re-covered.
    - ``demolished``: fraction of buildings (up to 3000 m2) torn down, left as cleared sites.
    - ``built``: buildings new in B per building of A, on open ground, aligned and sized like their neighbours.
    - ``construction_per_km2``: construction sites opened on open ground per square kilometre.
    - ``marking_renewal``: fraction of road-marking pieces renewed (fresh white) or worn (faded), half each.
    - ``water_change``: how far the water's colour moves to another (turbid, algal, dark) tint.
    """

    seed: int = field(default=0, metadata=rng(0, 2**63 - 1))
    car_turnover: float = field(default=0.0, metadata=rng(0.0, 1.0))
    car_arrivals: float = field(default=0.0, metadata=rng(0.0, 2.0))
    leaf_off: float = field(default=0.0, metadata=rng(0.0, 1.0))
    grass_dryness: float = field(default=0.0, metadata=rng(0.0, 1.0))
    roof_change: float = field(default=0.0, metadata=rng(0.0, 1.0))
    demolished: float = field(default=0.0, metadata=rng(0.0, 0.5))
    built: float = field(default=0.0, metadata=rng(0.0, 2.0))
    construction_per_km2: float = field(default=0.0, metadata=rng(0.0, 100.0))
    marking_renewal: float = field(default=0.0, metadata=rng(0.0, 1.0))
    water_change: float = field(default=0.0, metadata=rng(0.0, 1.0))

    @property
    def is_identity(self) -> bool:
        """True when epoch B is epoch A (every rate 0; the seed alone changes nothing)."""
        return all(getattr(self, f.name) == 0 for f in dataclasses.fields(self) if f.name != "seed")

    def cache_key(self) -> str:
        return spec_key({"epoch_version": GENERATOR_VERSION, **config_to_dict(self)}, length=16)


# ------------------------------------------------------------------------------------------- helpers
class _Layers:
    """Epoch B's layers being edited (copies of A's), A's for reference, and shared per-map helpers."""

    def __init__(self, om: Orthomap) -> None:
        if om.classes is None or om.dsm_m is None:
            raise MapError(f"epoch changes need a map with land-cover classes and a height model (dsm_m); map "
                           f"'{om.name}' lacks {'classes' if om.classes is None else 'dsm_m'}: set every [epoch] "
                           "rate to 0 or use a map with both layers (the procedural city has them)")
        self.a_rgb = np.asarray(om.rgb)
        self.a_cls = np.asarray(om.classes)
        self.a_dsm = np.asarray(om.dsm_m, dtype=np.float32)
        self.rgb = self.a_rgb.copy()
        self.cls = self.a_cls.copy()
        self.dsm = self.a_dsm.copy()
        self.gsd = math.sqrt(om.gsd_x_m * om.gsd_y_m)
        self.h, self.w = self.cls.shape

    def px(self, metres: float) -> int:
        return max(1, int(round(metres / self.gsd)))

    def mask(self, classes) -> np.ndarray:
        return np.isin(self.cls, np.asarray(classes, np.uint8))


def _components(mask: np.ndarray):
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    return n - 1, labels, stats, centroids


def _mean_colour(rgb: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """(n + 1, 3) mean colour per label (label 0 included)."""
    flat = labels.ravel()
    count = np.maximum(np.bincount(flat, minlength=n + 1), 1)
    return np.stack([np.bincount(flat, rgb[..., c].ravel(), minlength=n + 1) / count for c in range(3)], axis=1)


def _long_axis(mask: np.ndarray) -> float:
    """The angle (radians) of the long side of the smallest rectangle around ``mask``'s pixels."""
    (_, _), (rw, rh), ang = cv2.minAreaRect(cv2.findNonZero(mask.astype(np.uint8)))
    return math.radians(ang) + (0.0 if rw >= rh else math.pi / 2)


def _noise(rng: np.random.Generator, h: int, w: int, cell_px: int) -> np.ndarray:
    """Smooth noise in [0, 1] with features about ``cell_px`` pixels across (float32)."""
    ch, cw = h // cell_px + 2, w // cell_px + 2
    coarse = rng.random((ch, cw)).astype(np.float32)
    big = cv2.resize(coarse, (cw * cell_px, ch * cell_px), interpolation=cv2.INTER_LINEAR)
    return big[:h, :w]


def _recolour(pixels: np.ndarray, old_mean: np.ndarray, new_mean: np.ndarray, amount: np.ndarray | float
              ) -> np.ndarray:
    """Move ``pixels`` (N, 3) towards the same texture around ``new_mean`` (per pixel or one colour)."""
    p = pixels.astype(np.float32)
    target = p * (np.asarray(new_mean, np.float32) / np.maximum(np.asarray(old_mean, np.float32), 1.0))
    a = np.asarray(amount, np.float32)
    if a.ndim == 1:
        a = a[:, None]
    return np.clip(p + a * (target - p), 0, 255).astype(np.uint8)


def _ground_under(L: _Layers, hidden: np.ndarray, sigma_m: float = 3.0) -> np.ndarray:
    """An estimate of the ground's colour where ``hidden``: a normalized convolution of the visible pixels, done
    at about 1 m resolution (the estimate is smooth anyway) and brought back to the map grid."""
    f = max(1, int(1.0 / L.gsd))
    sw, sh = max(1, L.w // f), max(1, L.h // f)
    vis = cv2.resize((~hidden).astype(np.float32), (sw, sh), interpolation=cv2.INTER_AREA)
    img = cv2.resize(L.rgb.astype(np.float32) * (~hidden)[..., None], (sw, sh), interpolation=cv2.INTER_AREA)
    s = sigma_m / (L.gsd * f)
    den = cv2.GaussianBlur(vis, (0, 0), s) + 1e-6
    est = cv2.GaussianBlur(img, (0, 0), s) / den[..., None]
    return cv2.resize(est, (L.w, L.h), interpolation=cv2.INTER_LINEAR)


def _rect_poly(cx: float, cy: float, a: float, b: float, ang: float) -> np.ndarray:
    """Corners (4, 2) in pixels of an a x b rectangle centred at (cx, cy), its side a at angle ``ang``."""
    u = np.array([math.cos(ang), math.sin(ang)])
    v = np.array([-u[1], u[0]])
    c = np.array([cx, cy])
    return np.stack([c + (su * a * u + sv * b * v) / 2 for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])


def _poly_mask(poly: np.ndarray, h: int, w: int) -> tuple[np.ndarray, tuple[slice, slice]] | None:
    """The filled polygon as a mask over its bounding box and the box's slices; None when it leaves the map."""
    x0, y0 = np.floor(poly.min(axis=0)).astype(int)
    x1, y1 = np.ceil(poly.max(axis=0)).astype(int) + 1
    if x0 < 0 or y0 < 0 or x1 > w or y1 > h:
        return None
    m = np.zeros((y1 - y0, x1 - x0), np.uint8)
    cv2.fillPoly(m, [np.rint((poly - [x0, y0]) * 4).astype(np.int32).reshape(-1, 1, 2)], 1, cv2.LINE_8, 2)
    return m.astype(bool), (slice(y0, y1), slice(x0, x1))


class _Buildings:
    """A's building footprints: components, their orientation and typical height, found on demand."""

    def __init__(self, L: _Layers) -> None:
        self.L = L
        self.n, self.labels, self.stats, self.centroids = _components(np.isin(L.a_cls, (LC.BUILDING,
                                                                                     LC.ROOF_EQUIPMENT)))

    def nearest(self, x: float, y: float) -> int:
        d = np.hypot(self.centroids[1:, 0] - x, self.centroids[1:, 1] - y)
        return int(np.argmin(d)) + 1

    def frame(self, i: int) -> tuple[float, float]:
        """(angle_rad of its long side, median height m) of building ``i``."""
        x, y, w, h, _ = self.stats[i]
        m = self.labels[y:y + h, x:x + w] == i
        return _long_axis(m), float(np.median(self.L.a_dsm[y:y + h, x:x + w][m]))


def _place(L: _Layers, rng: np.random.Generator, n: int, allowed: np.ndarray, size_m: tuple[float, float, float,
           float], margin_m: float, orient: Callable[[float, float], float], tries: int = 25):
    """Yield (mask, slices, (cx, cy, a, b, angle)) of up to ``n`` rectangles (pixels, radians; a x b metres
    in the given ranges, ``margin_m`` clear around) on pixels where ``allowed``; placed rectangles are taken out
    of ``allowed``."""
    cand = np.flatnonzero(allowed)
    if cand.size == 0:
        return
    a0, a1, b0, b1 = size_m
    placed = 0
    for _ in range(n * tries):
        if placed >= n:
            return
        k = int(cand[rng.integers(cand.size)])
        cy, cx = divmod(k, L.w)
        a, b = rng.uniform(a0, a1) / L.gsd, rng.uniform(b0, b1) / L.gsd
        ang = orient(cx, cy)
        m2 = margin_m / L.gsd
        outer = _poly_mask(_rect_poly(cx, cy, a + 2 * m2, b + 2 * m2, ang), L.h, L.w)
        if outer is None or not np.all(allowed[outer[1]][outer[0]]):
            continue
        inner = _poly_mask(_rect_poly(cx, cy, a, b, ang), L.h, L.w)
        if inner is None:
            continue
        allowed[outer[1]][outer[0]] = False
        placed += 1
        yield inner[0], inner[1], (cx, cy, a, b, ang)


# ------------------------------------------------------------------------------------------- change kinds
def _water(L: _Layers, rng: np.random.Generator, amount: float) -> None:
    m = L.cls == LC.WATER
    if not m.any():
        return
    tint = WATER_TINTS[rng.integers(len(WATER_TINTS))]
    px = L.rgb[m]
    L.rgb[m] = _recolour(px, px.reshape(-1, 3).mean(axis=0), tint, amount)


def _grass(L: _Layers, rng: np.random.Generator, amount: float) -> None:
    m = L.mask((LC.LAWN, LC.FIELD, LC.SHRUB))
    if not m.any():
        return
    patchy = 0.55 + 0.45 * _noise(rng, L.h, L.w, L.px(40.0))         # some lawns are watered, others not
    px = L.rgb[m]
    L.rgb[m] = _recolour(px, px.reshape(-1, 3).mean(axis=0), STRAW_RGB, amount * patchy[m])


def _markings(L: _Layers, rng: np.random.Generator, rate: float) -> None:
    n, labels, _, _ = _components(L.cls == LC.LANE_MARKING)
    if n == 0:
        return
    pick = np.concatenate([[0], rng.random(n) < rate]).astype(bool)
    renew = np.concatenate([[0], rng.random(n) < 0.5]).astype(bool)
    k = L.px(2.0) | 1
    road = cv2.morphologyEx(L.rgb, cv2.MORPH_OPEN, np.ones((k, k), np.uint8))   # the asphalt under thin paint
    mean = _mean_colour(L.rgb, labels, n)
    fresh = pick[labels] & renew[labels]
    worn = pick[labels] & ~renew[labels]
    if fresh.any():
        L.rgb[fresh] = _recolour(L.rgb[fresh], mean[labels[fresh]], FRESH_PAINT_RGB, 1.0)
    if worn.any():
        p = L.rgb[worn].astype(np.float32)
        L.rgb[worn] = np.clip(p + 0.7 * (road[worn].astype(np.float32) - p), 0, 255).astype(np.uint8)


def _trees(L: _Layers, rng: np.random.Generator, rate: float) -> None:
    """Leaf-off crowns: the ground shows through a branch structure and a haze of twigs; only the trunk and the
    thick inner part of the limbs keep height, so a bare tree casts thin shadows instead of a solid crown's (the
    height model is 2.5-D: a twig with a height would stand as a pole down to the ground)."""
    n, labels, _, _ = _components(L.cls == LC.TREE)
    if n == 0:
        return
    pick = np.concatenate([[0], rng.random(n) < rate]).astype(bool)
    bare = pick[labels]
    if not bare.any():
        return
    ground = _ground_under(L, L.cls == LC.TREE)
    grain = 0.9 + 0.2 * rng.random((L.h, L.w), dtype=np.float32)[bare]          # the ground's own grain
    # trunks: the crowns' tops (local maxima of the smoothed height within 2.5 m), radius from the outline
    crown = bare.astype(np.uint8)
    inside_m = cv2.distanceTransform(crown, cv2.DIST_L2, 5) * L.gsd
    top = cv2.GaussianBlur(np.where(bare, L.a_dsm, 0.0).astype(np.float32), (0, 0), 1.0 / L.gsd)
    k = 2 * L.px(2.5) + 1
    peak = bare & (top >= cv2.dilate(top, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))) - 1e-4) & (
        inside_m >= 1.0)
    ys, xs = np.nonzero(peak)
    branches = np.zeros((L.h, L.w), np.uint8)
    height = np.zeros((L.h, L.w), np.float32)
    twigs = np.zeros((L.h, L.w), np.float32)
    for y, x in zip(ys, xs, strict=True):
        r_m = float(np.clip(inside_m[y, x] * 1.15, 1.5, 8.0))
        h_m = 0.8 * float(L.a_dsm[y, x])
        cv2.circle(twigs, (int(x), int(y)), L.px(r_m), 1.0, -1)
        cv2.circle(height, (int(x), int(y)), max(1, L.px(0.35)), h_m, -1)
        for a in rng.uniform(0, 2 * np.pi, int(rng.integers(6, 11))):
            length = r_m * rng.uniform(0.6, 1.0) / L.gsd
            end = (x + length * math.cos(a), y + length * math.sin(a))
            mid = (x + 0.5 * length * math.cos(a), y + 0.5 * length * math.sin(a))
            limbs = [((x, y), end, 2 if length > 12 else 1)]
            for side in (-1.0, 1.0):
                if rng.random() < 0.7:
                    b = a + side * rng.uniform(0.35, 0.8)
                    fl = length * rng.uniform(0.35, 0.55)
                    limbs.append((mid, (mid[0] + fl * math.cos(b), mid[1] + fl * math.sin(b)), 1))
            for p0, p1, t in limbs:
                q0 = (int(round(p0[0])), int(round(p0[1])))
                q1 = (int(round(p1[0])), int(round(p1[1])))
                cv2.line(branches, q0, q1, 1, t, cv2.LINE_AA)
                if p0 == (x, y):                           # the limb's thick inner part
                    cv2.line(height, q0, (int(round(mid[0] * 0.6 + x * 0.4)), int(round(mid[1] * 0.6 + y * 0.4))),
                             h_m, 1, cv2.LINE_8)
    twigs = cv2.GaussianBlur(twigs, (0, 0), 0.8 / L.gsd)[bare]
    limb = branches[bare].astype(np.float32) / max(float(branches.max()), 1.0)
    haze = 0.4 * twigs * (0.5 + rng.random(twigs.shape, dtype=np.float32))
    b = np.clip(np.maximum(haze, 0.7 * limb), 0.0, 0.85)[:, None]
    branch = BRANCH_RGB * (0.85 + 0.3 * rng.random(b.shape, dtype=np.float32))
    L.rgb[bare] = np.clip(ground[bare] * grain[:, None] * (1 - b) + branch * b, 0, 255).astype(np.uint8)
    L.dsm[bare] = np.minimum(L.dsm[bare], height[bare])


def _roofs(L: _Layers, rng: np.random.Generator, rate: float, bl: _Buildings) -> None:
    n, labels = bl.n, bl.labels
    if n == 0:
        return
    pick = np.concatenate([[0], rng.random(n) < rate]).astype(bool)
    new = np.concatenate([ROOF_COLOURS[:1], ROOF_COLOURS[rng.integers(len(ROOF_COLOURS), size=n)]])
    recover = np.concatenate([[0], rng.random(n) < 0.5]).astype(bool)       # new material, not just paint
    m = pick[labels] & (L.cls == LC.BUILDING)
    if not m.any():
        return
    lab = labels[m]
    mean = _mean_colour(L.rgb, labels, n)
    px = L.rgb[m].astype(np.float32)
    lum = px.mean(axis=1) / np.maximum(mean[lab].mean(axis=1), 1.0)
    flat = np.where(recover[lab], portable.power(lum, 0.35), lum)[:, None]   # a new cover flattens the old texture
    L.rgb[m] = np.clip(new[lab] * flat, 0, 255).astype(np.uint8)


SOIL_TINTS = _muted([(150, 126, 98), (168, 150, 120), (128, 100, 76), (176, 136, 96), (142, 136, 124)])
MACHINE_RGB = _muted([(212, 170, 40), (222, 128, 36), (232, 232, 226), (184, 54, 40), (70, 110, 60),
                      (60, 90, 150)])


def _soil(L: _Layers, rng: np.random.Generator, sel: np.ndarray) -> None:
    """Cleared ground (a construction site's floor) where ``sel``: soil of one of several tints with tyre tracks,
    gravel and sand heaps, sometimes a darker excavation; height 0."""
    ys, xs = np.nonzero(sel)
    if ys.size == 0:
        return
    y0, y1, x0, x1 = ys.min(), ys.max() + 1, xs.min(), xs.max() + 1
    h, w = y1 - y0, x1 - x0
    tex = 0.78 + 0.3 * _noise(rng, h, w, L.px(1.5)) + 0.1 * rng.random((h, w), dtype=np.float32)
    marks = np.zeros((h, w), np.uint8)
    if rng.random() < 0.4:                         # an excavation: a darker, moister pit
        c = (int(rng.integers(w)), int(rng.integers(h)))
        axes = (L.px(rng.uniform(3.0, 10.0)), L.px(rng.uniform(3.0, 8.0)))
        cv2.ellipse(marks, c, axes, float(rng.uniform(0, 180)), 0, 360, 3, -1)
    for _ in range(int(rng.integers(1, 7))):       # tyre tracks: dark curves across the site
        p = rng.uniform([0, 0], [w, h], (int(rng.integers(3, 6)), 2))
        cv2.polylines(marks, [np.rint(p).astype(np.int32).reshape(-1, 1, 2)], False, 1, L.px(rng.uniform(0.4, 0.9)))
    for _ in range(int(rng.integers(0, 6))):       # gravel and sand heaps: light blobs
        c = (int(rng.integers(w)), int(rng.integers(h)))
        cv2.circle(marks, c, L.px(rng.uniform(1.0, 4.0)), 2, -1)
    col = SOIL_TINTS[rng.integers(len(SOIL_TINTS))] * tex[..., None]
    col[marks == 1] *= rng.uniform(0.78, 0.92)
    col[marks == 3] *= rng.uniform(0.55, 0.75)
    heap = SOIL_TINTS[rng.integers(len(SOIL_TINTS))] * 1.15 if rng.random() < 0.5 else np.array(
        [178, 172, 160], np.float32)
    col[marks == 2] = heap * tex[marks == 2][:, None]
    m = sel[y0:y1, x0:x1]
    L.rgb[y0:y1, x0:x1][m] = np.clip(col[m], 0, 255).astype(np.uint8)
    L.cls[y0:y1, x0:x1][m] = LC.BARE_SOIL
    L.dsm[y0:y1, x0:x1][m] = 0.0


def _site_object(L: _Layers, rng: np.random.Generator, sel: np.ndarray, m: np.ndarray, origin: tuple[int, int],
                 size_m: tuple[float, float], rgb, cls: int, height_m: float, ang: float | None = None) -> None:
    """A rectangle (machine, container, pallet stack) at a random point of site ``m`` (offset ``origin``),
    kept on the site ``sel``."""
    ys, xs = np.nonzero(m)
    k = int(rng.integers(ys.size))
    a = rng.uniform(0, np.pi) if ang is None else ang
    got = _poly_mask(_rect_poly(xs[k] + origin[1], ys[k] + origin[0], size_m[0] / L.gsd, size_m[1] / L.gsd, a),
                     L.h, L.w)
    if got is None:
        return
    mm, (my, mx) = got
    mm = mm & sel[my, mx]
    L.rgb[my, mx][mm] = np.clip(np.asarray(rgb, np.float32) * (0.9 + 0.2 * rng.random((int(mm.sum()), 1))), 0,
                                255).astype(np.uint8)
    L.cls[my, mx][mm] = cls
    L.dsm[my, mx][mm] = height_m


def _construction(L: _Layers, rng: np.random.Generator, per_km2: float, bl: _Buildings) -> None:
    """Sites of several kinds: earthworks, a foundation slab with its formwork grid, a structure going up
    (a grey deck at storey height), material yards; machines of several colours, site cabins, a fence."""
    area_km2 = L.h * L.w * L.gsd ** 2 / 1e6
    n = int(rng.poisson(per_km2 * area_km2))
    allowed = L.mask(OPEN_GROUND + (LC.TREE, LC.PLAZA))

    def orient(x: float, y: float) -> float:
        return bl.frame(bl.nearest(x, y))[0] if bl.n else 0.0

    for m, (sy, sx), (cx, cy, a, b, ang) in list(_place(L, rng, n, allowed, (20.0, 50.0, 15.0, 40.0), 1.0,
                                                        orient)):
        sel = np.zeros((L.h, L.w), bool)
        sel[sy, sx] = m
        _soil(L, rng, sel)
        origin = (sy.start, sx.start)
        kind = str(rng.choice(["earthworks", "slab", "structure", "yard"]))
        if kind in ("slab", "structure"):
            fa, fb = a * rng.uniform(0.4, 0.7), b * rng.uniform(0.4, 0.7)
            got = _poly_mask(_rect_poly(cx, cy, fa, fb, ang), L.h, L.w)
            if got is not None:
                fm, (fy, fx) = got
                fm = fm & sel[fy, fx]
                grey = np.array([176, 174, 168], np.float32) * rng.uniform(0.85, 1.05)
                tex = 0.92 + 0.12 * rng.random(fm.shape, dtype=np.float32)
                yy, xx = np.mgrid[fy, fx]
                along = (xx - cx) * math.cos(ang) + (yy - cy) * math.sin(ang)
                across = -(xx - cx) * math.sin(ang) + (yy - cy) * math.cos(ang)
                pitch = L.px(rng.uniform(3.0, 6.0))
                grid = (np.abs(np.mod(along, pitch)) < 1.0) | (np.abs(np.mod(across, pitch)) < 1.0)
                tex = np.where(grid, tex * rng.uniform(0.6, 0.8), tex)      # formwork, rebar, columns
                L.rgb[fy, fx][fm] = np.clip(grey * tex[fm][:, None], 0, 255).astype(np.uint8)
                L.cls[fy, fx][fm] = LC.BUILDING if kind == "structure" else LC.PLAZA
                L.dsm[fy, fx][fm] = float(rng.uniform(3.0, 12.0)) if kind == "structure" else 0.0
        if kind == "yard":                          # stacks of material: pallets, pipes, rebar bundles
            for _ in range(int(rng.integers(3, 10))):
                tone = np.array([150, 120, 86] if rng.random() < 0.5 else [120, 122, 126], np.float32)
                _site_object(L, rng, sel, m, origin, (rng.uniform(1.5, 5.0), rng.uniform(1.0, 3.0)), tone * (
                    rng.uniform(0.7, 1.2)), LC.OTHER, 1.0, ang)
        for _ in range(int(rng.integers(0, 4))):   # machines
            col = MACHINE_RGB[rng.integers(len(MACHINE_RGB))]
            _site_object(L, rng, sel, m, origin, (rng.uniform(4.0, 8.0), rng.uniform(2.2, 3.0)), col, LC.CAR, 3.0)
        for _ in range(int(rng.integers(0, 3))):   # site cabins and containers, along the site's axis
            col = _muted([(226, 226, 220), (70, 100, 150), (190, 80, 50), (120, 130, 110)][int(rng.integers(4))])
            _site_object(L, rng, sel, m, origin, (6.0, 2.5), col, LC.BUILDING, 2.6, ang)
        if rng.random() < 0.5:                      # a fence or hoarding around it: a thin dark outline
            edge = m & ~cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            L.rgb[sy, sx][edge] = (L.rgb[sy, sx][edge] * 0.6).astype(np.uint8)


def _demolish(L: _Layers, rng: np.random.Generator, rate: float, bl: _Buildings) -> None:
    if bl.n == 0:
        return
    small = bl.stats[1:, cv2.CC_STAT_AREA] * L.gsd ** 2 <= 3000.0
    pick = np.concatenate([[0], (rng.random(bl.n) < rate) & small]).astype(bool)
    sel = pick[bl.labels]
    if sel.any():
        _soil(L, rng, cv2.dilate(sel.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
              & np.isin(L.cls, (LC.BUILDING, LC.ROOF_EQUIPMENT, LC.WALL)) | sel)


def _built(L: _Layers, rng: np.random.Generator, rate: float, bl: _Buildings) -> None:
    if bl.n == 0:
        return
    n = int(rng.poisson(rate * bl.n))
    allowed = L.mask(OPEN_GROUND)
    allowed &= L.dsm < 0.5

    def orient(x: float, y: float) -> float:
        return bl.frame(bl.nearest(x, y))[0] + (math.pi / 2 if rng.random() < 0.5 else 0.0)

    for m, (sy, sx), (cx, cy, a, b, ang) in list(_place(L, rng, n, allowed, (8.0, 24.0, 8.0, 16.0), 2.0,
                                                        orient)):
        like = bl.frame(bl.nearest(cx, cy))[1]                          # as tall as its neighbour, roughly
        h = float(np.clip(like * rng.uniform(0.7, 1.3), 3.0, 40.0))
        col = ROOF_COLOURS[rng.integers(len(ROOF_COLOURS))]
        gain = 0.92 + 0.16 * _noise(rng, m.shape[0], m.shape[1], L.px(1.0))
        height = np.full(m.shape, h, np.float32)
        if rng.random() < 0.5:                  # a gable roof: two slopes lit differently, the ridge higher
            yy, xx = np.mgrid[sy, sx]
            along_b = (xx - cx) * -math.sin(ang) + (yy - cy) * math.cos(ang)      # across the side a
            if b > a:
                along_b = (xx - cx) * math.cos(ang) + (yy - cy) * math.sin(ang)
            half = 0.5 * min(a, b)
            gain *= np.where(along_b > 0, 1.12, 0.86)
            height += (0.3 * L.gsd * half * (1.0 - np.abs(along_b) / half)).clip(0.0)
        else:                                   # a flat roof with a lighter parapet
            edge = m & ~cv2.erode(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
            gain *= np.where(edge, 1.15, 1.0)
        roof = np.clip(col * gain[..., None], 0, 255).astype(np.uint8)
        L.rgb[sy, sx][m] = roof[m]
        L.cls[sy, sx][m] = LC.BUILDING
        L.dsm[sy, sx][m] = height[m]


def _cars_gone(L: _Layers, rng: np.random.Generator, rate: float) -> None:
    n, labels, stats, _ = _components(L.a_cls == LC.CAR)
    if n == 0:
        return
    pick = rng.random(n) < rate
    pad = L.px(1.0) + 4
    ring_k = np.ones((3, 3), np.uint8)
    for i in np.flatnonzero(pick) + 1:
        x, y, w, h, _ = stats[i]
        y0, y1, x0, x1 = max(0, y - pad), min(L.h, y + h + pad), max(0, x - pad), min(L.w, x + w + pad)
        m = (labels[y0:y1, x0:x1] == i) & (L.cls[y0:y1, x0:x1] == LC.CAR)
        if not m.any():
            continue
        m8 = m.astype(np.uint8)
        cls = L.cls[y0:y1, x0:x1]
        ring = cv2.dilate(m8, ring_k, iterations=4).astype(bool) & ~cv2.dilate(m8, ring_k, iterations=2).astype(
            bool) & (cls != LC.CAR)
        if not ring.any():
            continue
        under = np.bincount(cls[ring]).argmax()
        plain = ring & (cls == under)              # the pavement around it, not its bay lines
        fill = cv2.dilate(m8, ring_k, iterations=2).astype(bool) & ((cls == LC.CAR) | (cls == under))
        crop = L.rgb[y0:y1, x0:x1]
        ref = crop[plain].astype(np.float32)
        grain = rng.normal(0.0, 1.0, (int(fill.sum()), 1)).astype(np.float32) * ref.std(axis=0)
        crop[fill] = np.clip(np.median(ref, axis=0) + grain, 0, 255).astype(np.uint8)
        cls[m] = under
        L.dsm[y0:y1, x0:x1][m] = np.median(L.dsm[y0:y1, x0:x1][plain])


def _cars_new(L: _Layers, rng: np.random.Generator, rate: float) -> None:
    from aerial_loc_env.world.city.content import CAR_COLOURS, CAR_WEIGHTS

    n, labels, stats, _ = _components(L.a_cls == LC.CAR)
    if n == 0:
        return
    want = int(rng.poisson(rate * n))
    paved = L.mask(PAVED)
    k3 = np.ones((5, 5), np.uint8)
    placed = 0
    for _ in range(want * 20):
        if placed >= want:
            return
        i = int(rng.integers(n)) + 1
        x, y, w, h, area = stats[i]
        if area * L.gsd ** 2 > 30.0:            # a truck or a merged queue: keep to single cars
            continue
        m = labels[y:y + h, x:x + w] == i
        a = _long_axis(m)                       # along the car
        if rng.random() < 0.5:                  # on along the lane
            d = rng.uniform(6.0, 40.0) * (1 if rng.random() < 0.5 else -1)
            off = np.array([math.cos(a), math.sin(a)]) * d / L.gsd
        else:                                   # a few bays over
            d = 2.5 * int(rng.integers(1, 5)) * (1 if rng.random() < 0.5 else -1)
            off = np.array([-math.sin(a), math.cos(a)]) * d / L.gsd
        dx, dy = int(round(off[0])), int(round(off[1]))
        ty, tx = y + dy, x + dx
        if ty < 2 or tx < 2 or ty + h > L.h - 2 or tx + w > L.w - 2:
            continue
        need = cv2.dilate(m.astype(np.uint8), k3).astype(bool)
        win = (slice(ty - 2, ty + h + 2), slice(tx - 2, tx + w + 2))
        big = np.zeros((h + 4, w + 4), bool)
        big[2:-2, 2:-2] = need[:, :]
        big = cv2.dilate(big.astype(np.uint8), k3).astype(bool)
        if not np.all(paved[win][big]) or np.any(L.dsm[win][big] != L.dsm[win][big].flat[0]):
            continue
        src = L.a_rgb[y:y + h, x:x + w][m].astype(np.float32)
        col = _muted(CAR_COLOURS[int(rng.choice(len(CAR_COLOURS), p=CAR_WEIGHTS))])
        ground = float(L.dsm[win][big].flat[0])
        tgt = (slice(ty, ty + h), slice(tx, tx + w))
        L.rgb[tgt][m] = _recolour(src, np.median(src, axis=0), col, 1.0)
        L.cls[tgt][m] = LC.CAR
        L.dsm[tgt][m] = ground + 1.5
        paved[tgt][m] = False
        placed += 1


# ------------------------------------------------------------------------------------------- entry points
def change_epoch(orthomap: Orthomap, config: EpochConfig, seed: int = 0) -> Orthomap:
    """Epoch B of ``orthomap`` (epoch A) under ``config``, deterministic from ``(seed, config.seed)``.

    Needs the classes and DSM layers; returns ``orthomap`` itself when every rate is 0. Its full-map planes, each
    filled a few times, take normal memory pages (``pages.small_pages``).
    """
    cfg = config
    if cfg.is_identity:
        return orthomap
    with small_pages():
        return _changed(orthomap, cfg, seed)


def _changed(orthomap: Orthomap, cfg: EpochConfig, seed: int) -> Orthomap:
    L = _Layers(orthomap)
    gens = dict(zip(KINDS, (np.random.default_rng(s) for s in
                            np.random.SeedSequence([int(seed), int(cfg.seed), 0xE90C]).spawn(len(KINDS))),
                    strict=True))
    bl = _Buildings(L) if (cfg.roof_change or cfg.demolished or cfg.built or cfg.construction_per_km2) else None
    if cfg.water_change:
        _water(L, gens["water"], cfg.water_change)
    if cfg.grass_dryness:
        _grass(L, gens["grass"], cfg.grass_dryness)
    if cfg.marking_renewal:
        _markings(L, gens["markings"], cfg.marking_renewal)
    if cfg.leaf_off:
        _trees(L, gens["trees"], cfg.leaf_off)
    if cfg.roof_change:
        _roofs(L, gens["roofs"], cfg.roof_change, bl)
    if cfg.demolished:
        _demolish(L, gens["demolished"], cfg.demolished, bl)
    if cfg.construction_per_km2:
        _construction(L, gens["construction"], cfg.construction_per_km2, bl)
    if cfg.built:
        _built(L, gens["built"], cfg.built, bl)
    if cfg.car_turnover:
        _cars_gone(L, gens["cars_gone"], cfg.car_turnover)
    if cfg.car_arrivals:
        _cars_new(L, gens["cars_new"], cfg.car_arrivals)
    source = f"{orthomap.source or orthomap.name} epoch B v{GENERATOR_VERSION} seed={cfg.seed}"
    return dataclasses.replace(orthomap, rgb=L.rgb, dsm_m=L.dsm, classes=L.cls, name=f"{orthomap.name}-epoch-b",
                               source=source)


def epoch_cache_path(city_config, config: EpochConfig) -> Path:
    from aerial_loc_env.paths import cache_dir

    return cache_dir("maps") / f"{city_config.name}-{city_config.cache_key()}-epoch-{config.cache_key()}.alm"


def epoch_city(city_config, config: EpochConfig) -> Orthomap:
    """Epoch B of the procedural city ``city_config``, memory-mapped from the cache (built on first use)."""
    from aerial_loc_env.world.city import default_city
    from aerial_loc_env.world.city.generator import GENERATOR_VERSION as CITY_VERSION

    if not isinstance(config, EpochConfig):
        raise ConfigError(f"epoch_city: expected an EpochConfig, got {type(config).__name__}")
    base = default_city(city_config)
    if config.is_identity:
        return base
    return cached_bundle(epoch_cache_path(city_config, config),
                         lambda: change_epoch(base, config, seed=city_config.seed),
                         {"generator": "aerial_loc_env.world.city.epochs", "generator_version": GENERATOR_VERSION,
                          "city_generator_version": CITY_VERSION, "city": config_to_dict(city_config),
                          "epoch": config_to_dict(config)},
                         size_px=(base.width_px, base.height_px))


__all__ = ["GENERATOR_VERSION", "EpochConfig", "change_epoch", "epoch_cache_path", "epoch_city"]
