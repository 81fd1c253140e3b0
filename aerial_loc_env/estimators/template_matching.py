"""Practitioners' baseline: OpenCV template matching of the camera image against the map around the estimate.

Every step the agent first dead-reckons (``DeadReckoningAgent``, the same integrator as the floor baseline),
then looks for the camera image in a search window of the database around that prediction. The camera image is
warped north-up into the map's pixel grid at a working resolution (``work_gsd_m``) with the camera model's own
eq. (3) affine (``CameraModel.camera_to_map`` at the predicted position, the measured heading and altitude),
cropped to the square inscribed in the footprint, and matched with normalized cross-correlation
(``cv2.TM_CCOEFF_NORMED``). A peak above ``min_score`` that is not on the window's border is a fix: the estimate
jumps there (sub-pixel by a parabola through the peak), and dead reckoning continues from it, unless the
fix lies beyond ``gate_sigma`` standard deviations of the prediction (an innovation gate against false
matches, e.g. under large shadows; after ``regate_after`` gated frames in a row the match is accepted, so
that one false fix cannot lock the agent out). Otherwise the agent says so: status ``"dead_reckoning"`` with the
reason in ``extras["reason"]``.

``WindowMatchingAgent`` (the window, the fix/fallback logic and the frame conversions) is shared with the
feature-matching baseline (``feature_matching.py``).

On a map read by window (``estimators/database.py``) the working level is made for the map window around the
search window only, on the whole map's level grid (the same values as the whole map's level there), and made
again for a new map window when the search window nears its edge; the global search (a uniform prior) is refused
there.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple

import cv2
import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.database import (
    DatabaseWindow,
    WindowPolicy,
    derived_once,
    read_by_window,
    refuse_global_search,
)
from aerial_loc_env.estimators.dead_reckoning import DeadReckoningAgent
from aerial_loc_env.estimators.patches import to_gray
from aerial_loc_env.estimators.protocol import Agent, Estimate, Observation, default_altitude_range_m, parse_observation
from aerial_loc_env.sensors.camera import apply_affine, invert_affine, world_to_map_affine

if TYPE_CHECKING:
    from aerial_loc_env.env.briefing import Briefing


@dataclass(frozen=True)
class WindowMatchingParams:
    """Common settings: matching resolution, search window, and the covariance reported on a fix."""

    work_gsd_m: float | None = field(default=None, metadata=rng(0.01, 100.0, doc=(
        "ground size of a matching pixel; None: from the camera geometry (auto_work_gsd_m)")))
    search_radius_m: float = field(default=40.0, metadata=rng(0.0, 1e5, doc="window half-size around the "
                                                                              "prediction, beyond the footprint"))
    global_search: bool = True      # with a uniform prior, search the whole map until the first fix
    fix_std_m: float = field(default=3.0, metadata=rng(0.0, 1e4, lo_open=True, doc="1-sigma of a fix"))
    gate_sigma: float = field(default=3.0, metadata=rng(0.0, 1e3, doc="reject a fix farther than this many "
                                                                       "sigma from the prediction (0: never)"))
    regate_after: int = field(default=4, metadata=rng(1, 10000, doc="accept a gated fix after at least this "
                                                                     "many consecutive gated frames that agree "
                                                                     "over a footprint flown (re-localize)"))
    fine_level: bool = False        # below the working level's lowest altitude, match on the map's own pixels
    #                                 while tracking (a map held whole, finer than the working level)


def _working_level(m: Any, f: float, lw: int, lh: int) -> tuple[np.ndarray, np.ndarray | None]:
    """The map's gray level at (lw, lh), ``f`` map pixels per level pixel (``cv2.INTER_AREA``; the gray image
    itself at f = 1), and the level pixels touching no-data (None without any), read-only."""
    gray = to_gray(np.asarray(m.rgb))
    level = cv2.resize(gray, (lw, lh), interpolation=cv2.INTER_AREA) if f != 1 else gray
    bad = None
    if m.nodata is not None and np.any(m.nodata):
        bad = cv2.resize(np.asarray(m.nodata, np.float32), (lw, lh), interpolation=cv2.INTER_AREA) > 0
        bad.flags.writeable = False
    level.flags.writeable = False
    return level, bad


class Fix(NamedTuple):
    x_m: float
    y_m: float
    extras: dict


class Window(NamedTuple):
    image: np.ndarray        # gray float32 crop of the working-resolution database
    u0: int                  # its top-left corner in working-level pixels
    v0: int


class WindowMatchingAgent(Agent):
    """Dead reckoning corrected by matching each frame against a map window (subclasses: ``match``)."""

    Params = WindowMatchingParams

    def __init__(self, params: WindowMatchingParams | None = None) -> None:
        self.params = params or type(self).Params()
        self.dr: DeadReckoningAgent | None = None

    # ---------------------------------------------------------------- episode
    def reset(self, briefing: Briefing, *, seed: int | None = None) -> Estimate:
        m = briefing.orthomap
        self.briefing, self.orthomap, self.camera = briefing, m, briefing.camera
        self.work_gsd_m = self.params.work_gsd_m or self.auto_work_gsd_m(briefing)
        self.altitude_range = self.altitude_range_m(briefing)
        f = self.work_gsd_m / min(m.gsd_x_m, m.gsd_y_m)
        lw, lh = max(2, int(round(m.width_px / f))), max(2, int(round(m.height_px / f)))
        self.level_nodata: np.ndarray | None = None
        self._policy: WindowPolicy | None = None
        self._window: DatabaseWindow | None = None
        if read_by_window(m):   # the level is made window by window (_cover)
            if briefing.prior.kind != "gaussian" and self.params.global_search:
                refuse_global_search(m, type(self).__name__, f"global_search with a {briefing.prior.kind} prior")
            self._policy = WindowPolicy(m, lambda alt: self.footprint_half_diagonal_m(alt))
            self.level = np.zeros((lh, lw), np.float32)   # (replaced by the first window's)
        else:   # made once per map and working resolution (``derived_once``): resets that follow are cheap
            self.level, self.level_nodata = derived_once(m.rgb, ("working level", f, id(m.nodata)),
                                                         lambda: _working_level(m, f, lw, lh), (m.nodata,))
        sx, sy = m.width_px / lw, m.height_px / lh
        to_level = np.array([[1 / sx, 0, 0.5 / sx - 0.5], [0, 1 / sy, 0.5 / sy - 0.5], [0, 0, 1.0]])
        self.map_to_level = to_level                                # (3, 3) map pixel -> level pixel
        self.world_to_level = to_level @ np.vstack([world_to_map_affine(m), [0, 0, 1.0]])
        self.level_to_world = invert_affine(self.world_to_level[:2])
        self.level_gsd = (m.gsd_x_m * sx, m.gsd_y_m * sy)
        self._coarse = self._level_state()
        self._fine = self._fine_state(m) if self.fine_level_floor_m(briefing) is not None else None
        self._on_fine = False
        self.dr = DeadReckoningAgent()
        self.has_fix = False
        # consecutive gated matches: (match - prediction x, y, prediction x, y)
        self.gated_offsets: list[tuple[float, float, float, float]] = []
        return self.dr.reset(briefing, seed=seed)

    #: ``work_gsd_m = None``: the template (the square inscribed in the footprint) spans this many pixels
    #: across the footprint's short side; the paper's 100 m footprint gives its 1 m working resolution
    AUTO_PX_ACROSS = 100

    def auto_work_gsd_m(self, briefing: Briefing) -> float:
        """The working resolution for this camera geometry: ``AUTO_PX_ACROSS`` pixels across the footprint's
        short side, never finer than the map (so any altitude, field of view or image size works alike)."""
        m = briefing.orthomap
        short_m = min(briefing.camera.footprint_m(briefing.altitude_m))
        return max(min(m.gsd_x_m, m.gsd_y_m), short_m / self.AUTO_PX_ACROSS)

    #: the lowest altitude matched at: the footprint's short side spans this many working pixels. Measured on
    #: PaperShadows-v2 (1 m working pixels, template-ncc, 22 m/s, 4 Hz; docs/mavlink.md): 20 px (40 m) still
    #: fixes 56 % of frames within 0.8 m RMSE; at 15 px (30 m) the matches thin out and the track drifts to
    #: 24 m between them; below 8 px no template can be cut
    MIN_PX_ACROSS = 20

    def altitude_range_m(self, briefing: Briefing) -> tuple[float, float]:
        """Down to where the footprint spans ``MIN_PX_ACROSS`` working pixels (the warp follows the measured
        altitude; only the template shrinks), or with ``fine_level`` as many of the map's own pixels; up to the
        default (the search window is sized at the nominal)."""
        hi = default_altitude_range_m(briefing)[1]
        fine = self.fine_level_floor_m(briefing)
        return min(hi, self.working_floor_m(briefing) if fine is None else fine), hi

    def working_floor_m(self, briefing: Briefing) -> float:
        """The lowest altitude the working level matches at: its footprint spans ``MIN_PX_ACROSS`` pixels."""
        work_gsd_m = self.params.work_gsd_m or self.auto_work_gsd_m(briefing)
        return self.MIN_PX_ACROSS * work_gsd_m / min(briefing.camera.footprint_m(1.0))

    def fine_level_floor_m(self, briefing: Briefing) -> float | None:
        """With ``fine_level``, on a map held whole whose pixels are finer than the working level's: the lowest
        altitude matched on the map's own pixels (its footprint spans ``MIN_PX_ACROSS`` of them); else None.
        The fine level serves a landing's last metres: it is used below ``working_floor_m`` and only while
        tracking (a first fix needs the working level's larger footprint: a small template in a prior's
        window finds false peaks)."""
        m = briefing.orthomap
        map_gsd_m = min(m.gsd_x_m, m.gsd_y_m)
        work_gsd_m = self.params.work_gsd_m or self.auto_work_gsd_m(briefing)
        if not self.params.fine_level or read_by_window(m) or map_gsd_m >= work_gsd_m:
            return None
        return self.MIN_PX_ACROSS * map_gsd_m / min(briefing.camera.footprint_m(1.0))

    _LEVEL_KEYS = ("level", "level_nodata", "map_to_level", "world_to_level", "level_to_world", "level_gsd")

    def _level_state(self) -> dict:
        return {k: getattr(self, k) for k in self._LEVEL_KEYS}

    def _fine_state(self, m: Any) -> dict:
        """The map's own pixel grid as a level (its gray image made window by window in ``window``)."""
        to_map = np.vstack([world_to_map_affine(m), [0, 0, 1.0]])
        nodata = None if m.nodata is None or not np.any(m.nodata) else np.asarray(m.nodata, bool)
        return {"level": np.zeros((0, 0), np.float32), "level_nodata": nodata,
                "map_to_level": np.eye(3), "world_to_level": to_map, "level_to_world": invert_affine(to_map[:2]),
                "level_gsd": (m.gsd_x_m, m.gsd_y_m)}

    def _select_level(self, altitude_m: float) -> bool:
        """Match this frame on the fine level (below the working floor, while tracking) or the working one;
        False when the frame is below the working floor and the agent has no fix yet (no match)."""
        fine = self._fine is not None and altitude_m < self.working_floor_m(self.briefing)
        if fine and not self.has_fix:
            return False
        if fine != self._on_fine:
            if not self._on_fine:
                self._coarse = self._level_state()       # (a map read by window changes its level)
            for k, v in (self._fine if fine else self._coarse).items():
                setattr(self, k, v)
            self._on_fine = fine
        return True

    def step(self, observation: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None) -> Estimate:
        if self.dr is None:
            raise ConfigError(f"{type(self).__name__}.step called before reset(briefing, seed=...)")
        pred = self.dr.step(observation)
        obs = parse_observation(observation, self.briefing, self.altitude_range, type(self).__name__)
        if not self._select_level(obs.altitude_m):
            return self._dead_reckoning(pred, f"no fix: below {self.working_floor_m(self.briefing):.0f} m the "
                                              "agent matches only while tracking")
        if self.has_fix or self.briefing.prior.kind == "gaussian" or not self.params.global_search:
            prior = self.briefing.prior
            radius = self.params.search_radius_m
            if not self.has_fix and prior.kind == "gaussian":
                radius = max(radius, 3.0 * float(prior.std_xy_m))
            window = self.window((pred.x_m, pred.y_m), radius, obs)
        else:
            window = Window(self.level, 0, 0)
        if window is None:
            return self._dead_reckoning(pred, "the search window lies outside the map")
        try:
            fix = self.match(obs, pred, window)
        except cv2.error as exc:  # OpenCV refused the inputs (e.g. a window smaller than the template)
            return self._dead_reckoning(pred, f"opencv: {exc.err}")
        if isinstance(fix, str):
            return self._dead_reckoning(pred, fix)
        jump = math.hypot(fix.x_m - pred.x_m, fix.y_m - pred.y_m)
        limit = self.params.gate_sigma * math.hypot(pred.std_m or 0.0, self.params.fix_std_m)
        if self.params.gate_sigma > 0 and jump > limit:
            # a lone far match is likely false; several in a row that agree on the same offset mean the estimate
            # itself is off (e.g. after a false fix), so the agent re-localizes instead of staying locked out.
            # False matches scatter: accepting any run of them made the agent run away on repetitive ground.
            self.gated_offsets = (self.gated_offsets + [(fix.x_m - pred.x_m, fix.y_m - pred.y_m,
                                                         pred.x_m, pred.y_m)])[-MAX_GATED:]
            if not self._gated_agree(obs.altitude_m):
                return self._dead_reckoning(pred, f"no fix: the match is {jump:.0f} m from the prediction, beyond"
                                                  f" the {self.params.gate_sigma:g}-sigma gate ({limit:.0f} m)")
        self.gated_offsets = []
        self.has_fix = True
        self.dr.anchor((fix.x_m, fix.y_m), np.eye(2) * self.fix_std_now_m() ** 2)
        return Estimate(fix.x_m, fix.y_m, yaw_rad=obs.yaw_rad, cov_xy_m2=self.dr.cov.copy(), status="ok",
                        extras={"match": True, **fix.extras})

    def fix_std_now_m(self) -> float:
        """The 1-sigma this frame's fix is reported with: ``fix_std_m`` on the working level, scaled down by the
        pixel on the fine level (a fix is as sharp as the pixels it is matched on), so that an autopilot fusing the
        fix weighs a landing's last fixes as they deserve."""
        if not self._on_fine:
            return self.params.fix_std_m
        return self.params.fix_std_m * max(self.level_gsd) / max(self._coarse["level_gsd"])

    def _gated_agree(self, altitude_m: float) -> bool:
        """Re-localize only after a fix (before it, a tracking prior is the authority) on ``regate_after``
        gated matches in a row that agree on the offset from the prediction (within 2 ``fix_std_m``) while the
        vehicle flew at least the footprint's short side: a static false match (a look-alike bridge truss or
        orchard row) agrees with itself over a few frames, but not once the camera sees other ground."""
        if not self.has_fix or len(self.gated_offsets) < self.params.regate_after:
            return False
        d = np.asarray(self.gated_offsets)
        agree = np.hypot(*(d[:, :2] - d[-1, :2]).T) <= 2.0 * self.params.fix_std_m
        run = len(agree) - (np.flatnonzero(~agree)[-1] + 1 if not agree.all() else 0)   # trailing agreement
        flown = math.hypot(*(d[-1, 2:] - d[-run, 2:]))
        return bool(run >= self.params.regate_after and flown >= min(self.camera.footprint_m(altitude_m)))

    def _dead_reckoning(self, pred: Estimate, reason: str) -> Estimate:
        return Estimate(pred.x_m, pred.y_m, yaw_rad=pred.yaw_rad, cov_xy_m2=pred.cov_xy_m2,
                        status="dead_reckoning", extras={"match": False, "reason": reason})

    # ---------------------------------------------------------------- helpers
    def footprint_half_diagonal_m(self, altitude_m: float) -> float:
        w_m, h_m = self.camera.footprint_m(altitude_m)
        return 0.5 * math.hypot(w_m, h_m)

    def window(self, center_xy_m: tuple[float, float], radius_m: float, obs: Observation) -> Window | None:
        """The working-level crop covering the footprint around ``center`` plus ``radius_m``, clipped to the
        map; None when nothing of it is on the map."""
        box = self._window_box(center_xy_m, radius_m, obs)
        if box is None:
            return None
        u0, v0, u1, v1 = box
        if self._on_fine:                   # the map's own pixels, made gray for this window only
            return Window(to_gray(np.asarray(self.orthomap.rgb[v0:v1, u0:u1])), u0, v0)
        self._cover(box, obs.altitude_m)
        return Window(self.level[v0:v1, u0:u1], u0, v0)

    def _window_box(self, center_xy_m: tuple[float, float], radius_m: float,
                    obs: Observation) -> tuple[int, int, int, int] | None:
        """``window``'s level pixels (u0, v0, u1, v1), or None."""
        half_m = radius_m + self.footprint_half_diagonal_m(obs.altitude_m)
        cu, cv = apply_affine(self.world_to_level[:2], np.array([center_xy_m]))[0]
        hu, hv = half_m / self.level_gsd[0], half_m / self.level_gsd[1]
        lh, lw = (self.orthomap.height_px, self.orthomap.width_px) if self._on_fine else self.level.shape
        u0, u1 = max(0, int(math.floor(cu - hu))), min(lw, int(math.ceil(cu + hu)) + 1)
        v0, v1 = max(0, int(math.floor(cv - hv))), min(lh, int(math.ceil(cv + hv)) + 1)
        if u1 - u0 < 2 or v1 - v0 < 2:
            return None
        return u0, v0, u1, v1

    def _cover(self, box: tuple[int, int, int, int], altitude_m: float) -> None:
        """A map read by window: make the working level's pixels ``box`` (and the no-data flags there) from a map
        window around them, read again when they near its edge."""
        if self._policy is None:
            return
        m = self.orthomap
        sx, sy = m.width_px / self.level.shape[1], m.height_px / self.level.shape[0]
        kx, ky = int(math.ceil(sx)) + 1, int(math.ceil(sy)) + 1          # a level pixel's source, and one more
        need = (max(0, int(math.floor(box[0] * sx)) - kx), max(0, int(math.floor(box[1] * sy)) - ky),
                min(m.width_px, int(math.ceil(box[2] * sx)) + kx), min(m.height_px, int(math.ceil(box[3] * sy)) + ky))
        read = self._policy.update_box(need, altitude_m)
        if read is None:
            return
        self._window = window = DatabaseWindow(m, read, where=type(self).__name__, previous=self._window)
        size = (self.level.shape[1], self.level.shape[0])
        self.level = window.level_of(to_gray, size, np.float32, key="level").array
        flags = window.level_nodata(size, key="level_nodata")
        self.level_nodata = None if flags is None else flags.array

    def level_point_to_world(self, u: float, v: float) -> tuple[float, float]:
        x, y = apply_affine(self.level_to_world, np.array([[u, v]]))[0]
        return float(x), float(y)

    def match(self, obs: Observation, pred: Estimate, window: Window) -> Fix | str:
        """A fix, or the reason there is none (a short sentence)."""
        raise NotImplementedError


#: gated matches remembered for the re-localization test
MAX_GATED = 1000


def second_peak(res: np.ndarray, peak: tuple[int, int], radius_px: int) -> float:
    """The highest value of ``res`` farther than ``radius_px`` (square) from ``peak`` (-1 when none)."""
    mx, my = peak
    masked = res.copy()
    masked[max(0, my - radius_px):my + radius_px + 1, max(0, mx - radius_px):mx + radius_px + 1] = -1.0
    return float(masked.max()) if masked.size else -1.0


def parabola_offset(left: float, centre: float, right: float) -> float:
    """Sub-pixel offset in [-0.5, 0.5] of the vertex of the parabola through three samples around a peak."""
    den = left - 2.0 * centre + right
    if den >= 0 or not np.isfinite(den):
        return 0.0
    return float(np.clip(0.5 * (left - right) / den, -0.5, 0.5))


@dataclass(frozen=True)
class TemplateMatchingParams(WindowMatchingParams):
    min_score: float = field(default=0.5, metadata=rng(-1.0, 1.0, doc="NCC peak needed for a fix"))
    min_peak_margin: float = field(default=0.05, metadata=rng(0.0, 2.0, doc=(
        "NCC peak minus the highest other peak (beyond a quarter template) needed for a fix: repetitive "
        "ground (bridge trusses, orchard rows, water) gives near-equal peaks, and any of them may be false")))


class TemplateMatchingAgent(WindowMatchingAgent):
    """Normalized cross-correlation of the north-up camera image over a map window."""

    Params = TemplateMatchingParams

    def template(self, obs: Observation, pred: Estimate) -> np.ndarray:
        """The camera image warped north-up into the working-level grid, centred on the vehicle: the square
        inscribed in the footprint."""
        cam = self.camera
        a = cam.camera_to_map(self.orthomap, pred.x_m, pred.y_m, obs.yaw_rad, obs.altitude_m)   # eq. (3)
        full = self.map_to_level @ np.vstack([a, [0, 0, 1.0]])        # camera pixel -> level pixel
        w_m, h_m = cam.footprint_m(obs.altitude_m)
        angle = math.pi / 2 - obs.yaw_rad                              # camera -> map rotation
        side_m = min(w_m, h_m) / (abs(math.cos(angle)) + abs(math.sin(angle)))
        side = int(math.floor(side_m / max(self.level_gsd)))
        if side < 8:
            raise ConfigError("template matching: the footprint is smaller than 8 working pixels; lower work_gsd_m")
        centre_level = full[:2] @ np.array([*cam.center_px, 1.0])
        shift = np.array([[1, 0, (side - 1) / 2 - centre_level[0]], [0, 1, (side - 1) / 2 - centre_level[1]],
                          [0, 0, 1.0]])
        m = (shift @ full)[:2]
        gray = to_gray(obs.image)
        return cv2.warpAffine(gray, m, (side, side), flags=cv2.INTER_AREA)

    def match(self, obs: Observation, pred: Estimate, window: Window) -> Fix | str:
        tpl = self.template(obs, pred)
        img = window.image
        if img.shape[0] < tpl.shape[0] + 2 or img.shape[1] < tpl.shape[1] + 2:
            return "the search window is smaller than the template (near the map edge)"
        if float(tpl.std()) < 1e-3:
            return "the camera image is uniform"
        res = cv2.matchTemplate(img, tpl, cv2.TM_CCOEFF_NORMED)
        res = np.nan_to_num(res, nan=-1.0)
        _, score, _, (mx, my) = cv2.minMaxLoc(res)
        if score < self.params.min_score:
            return f"no match: NCC peak {score:.2f} < min_score {self.params.min_score:.2f}"
        if mx in (0, res.shape[1] - 1) or my in (0, res.shape[0] - 1):
            return f"no match: the NCC peak ({score:.2f}) is on the window border"
        margin = score - second_peak(res, (mx, my), max(2, tpl.shape[0] // 4))
        if margin < self.params.min_peak_margin:
            return (f"no match: ambiguous NCC peak {score:.2f}, another peak is within {margin:.2f} "
                    f"(< min_peak_margin {self.params.min_peak_margin:.2f})")
        dx = parabola_offset(res[my, mx - 1], res[my, mx], res[my, mx + 1])
        dy = parabola_offset(res[my - 1, mx], res[my, mx], res[my + 1, mx])
        half = (tpl.shape[0] - 1) / 2
        u = window.u0 + mx + dx + half
        v = window.v0 + my + dy + half
        if self.level_nodata is not None and self.level_nodata[int(round(v)), int(round(u))]:
            return "no match: the NCC peak lies on no-data"
        x, y = self.level_point_to_world(u, v)
        return Fix(x, y, {"score": float(score), "peak_margin": float(margin)})
