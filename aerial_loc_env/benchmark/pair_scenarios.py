"""A folder of real two-epoch pairs as benchmark scenarios: one ``AerialLoc/RealPair-v2`` per pair, its flight
fitted to the pair (``fit_flight``), and the simulated presets flown at that geometry (``sim_overrides``).

**The flight, fitted to a pair**: the geometry of ``AerialLoc/RealPair-v2`` (the paper's 600 x 400 camera, 41.1 deg
field of view, 5 m/s, 4 Hz, a 15 m prior and a 45 m margin for it), flown at the highest altitude, at most 200 m,
whose footprint leaves a flyable square of at least ``FLYABLE_SHARE`` of the pair's short side (the footprint's
half-diagonal plus the margin kept from every edge), for as long as a track of ``TRACK_PER_SIDE`` times that
square's side takes, at most 60 s. A 512 m tile at 0.5 m/px (the LEVIR-CD pairs) gets RealPair's own: 200 m (a
150 x 100 m footprint), a 240 m square, 60 s (a 300 m track).

An experiment's ``[[scenarios]]`` entry ``pairs = "DIR"`` expands here (``benchmark/grid.py``); ``aerial-loc
fidelity`` flies every pair and preset at the smallest pair's flight (``benchmark/fidelity.py``). Scenarios come
out as plain ``{"id", "overrides", "label"}`` tables, which the grid turns into its entries.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from aerial_loc_env.errors import ConfigError, MapError

PAIR_ID = "AerialLoc/RealPair-v2"
#: the flyable square kept of the pair's short side (RealPair-v2's 240 m of 512 m)
FLYABLE_SHARE = 0.46
MAX_ALTITUDE_M = 200.0
MIN_ALTITUDE_M = 20.0
#: the track flies this many times the flyable square's side (RealPair-v2: 300 m over 240 m), at most MAX_DURATION_S
TRACK_PER_SIDE = 1.25
MAX_DURATION_S = 60.0


@dataclass(frozen=True)
class PairSource:
    """A real pair: epoch A (the map), epoch B (the camera's ground), the sampling of images without a
    georeference, and its label in tables."""

    path_a: Path
    path_b: Path
    gsd_m: float | None
    label: str


def pair_sources(folder: str | os.PathLike, gsd_m: float | None = None) -> list[PairSource]:
    """The pairs of a folder laid out as ``A/<name>``, ``B/<name>`` (``world.maps.pairs.pairs_in``)."""
    from aerial_loc_env.world.maps.pairs import pairs_in

    root = Path(folder).expanduser()
    return [PairSource(a, b, gsd_m, f"{root.resolve().name}/{a.name}") for a, b in pairs_in(root)]


def pair_extent_m(source: PairSource) -> tuple[float, float]:
    """The ground a pair covers on its common grid, metres (east-west, north-south)."""
    from aerial_loc_env.world.maps.pairs import load_pair

    pair = load_pair(source.path_a, source.path_b, gsd_m=source.gsd_m, max_shift_m=None, where=source.label)
    return pair.surveyed.width_m, pair.surveyed.height_m


def _pair_geometry() -> Any:
    """RealPair-v2's scenario (its paths are placeholders: only the flight, camera and prior are read)."""
    from aerial_loc_env.env import load_scenario

    return load_scenario(PAIR_ID, {"map.path_a": "A.png", "map.path_b": "B.png"})


def fit_flight(extent_m: tuple[float, float]) -> dict[str, float]:
    """The flight over a pair of ``extent_m`` (see the module doc): ``flight.altitude_m`` and
    ``flight.duration_s`` overrides of RealPair-v2."""
    sc = _pair_geometry()
    short = float(min(extent_m))
    per_m = 0.5 * math.hypot(*sc.camera.footprint_m(1.0))          # the footprint's half-diagonal per metre
    margin, jitter = sc.flight.margin_m, 3.0 * sc.flight.altitude_noise_m
    altitude = min(MAX_ALTITUDE_M, ((1.0 - FLYABLE_SHARE) / 2.0 * short - margin) / per_m - jitter)
    if altitude < MIN_ALTITUDE_M:
        raise ConfigError(f"fidelity: a pair covering {extent_m[0]:.0f} x {extent_m[1]:.0f} m is too small for "
                          f"{PAIR_ID}'s camera and {sc.episode.prior_std_m:g} m prior: the flight would be at "
                          f"{altitude:.0f} m, below {MIN_ALTITUDE_M:g} m (a pair needs at least "
                          f"{2 * (per_m * (MIN_ALTITUDE_M + jitter) + margin) / (1 - FLYABLE_SHARE):.0f} m across)")
    altitude = math.floor(altitude * 10.0) / 10.0
    side = short - 2.0 * (per_m * (altitude + jitter) + margin)
    duration = min(MAX_DURATION_S, math.floor(TRACK_PER_SIDE * side / sc.flight.speed_mps * 4.0) / 4.0)
    return {"flight.altitude_m": altitude, "flight.duration_s": duration}


def pair_entries(sources: Sequence[PairSource], flight: Mapping[str, float] | None = None,
                 overrides: Mapping[str, Any] | None = None, label_prefix: str = "") -> list[dict[str, Any]]:
    """One benchmark scenario (``{"id": RealPair-v2, "overrides", "label"}``) per pair, each at ``flight``
    (default: its own ``fit_flight``), with ``overrides`` on top."""
    out = []
    for s in sources:
        fitted = dict(flight) if flight is not None else fit_flight(pair_extent_m(s))
        paths = {"map.path_a": str(s.path_a), "map.path_b": str(s.path_b)}
        if s.gsd_m is not None:
            paths["map.gsd_m"] = float(s.gsd_m)
        out.append({"id": PAIR_ID, "overrides": {**fitted, **paths, **dict(overrides or {})},
                    "label": f"{label_prefix}{s.label}"})
    return out


def expand_pairs_entry(item: Mapping[str, Any], where: str, base_dir: Path | None = None) -> list[dict[str, Any]]:
    """An experiment's ``[[scenarios]]`` entry ``pairs = "DIR"`` (optional ``gsd_m``, ``label``, ``overrides``):
    one RealPair-v2 scenario per pair of the folder, each at its own fitted flight (``grid.py``)."""
    unknown = set(item) - {"pairs", "gsd_m", "label", "overrides", "id"}
    if unknown or not isinstance(item.get("pairs"), str):
        raise ConfigError(f"{where}: a pairs entry needs pairs = \"DIR\" (a folder with A/ and B/) and may have "
                          f"gsd_m, label, overrides (got {sorted(item)})")
    if item.get("id", PAIR_ID) != PAIR_ID:
        raise ConfigError(f"{where}: a pairs entry flies {PAIR_ID}; leave 'id' out (got {item['id']!r})")
    gsd = item.get("gsd_m")
    if gsd is not None and not (isinstance(gsd, (int, float)) and not isinstance(gsd, bool) and gsd > 0):
        raise ConfigError(f"{where}: pairs entry gsd_m = {gsd!r} must be metres per pixel > 0")
    overrides = item.get("overrides") or {}
    if not isinstance(overrides, Mapping):
        raise ConfigError(f"{where}: pairs entry overrides must be a table, got {overrides!r}")
    folder = Path(item["pairs"]).expanduser()
    if base_dir is not None and not folder.is_absolute():
        folder = base_dir / folder
    prefix = f"{item['label']}: " if item.get("label") else ""
    try:
        return pair_entries(pair_sources(folder, gsd), None, overrides, prefix)
    except MapError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def sim_overrides(flight: Mapping[str, float]) -> dict[str, Any]:
    """A simulated preset flown at the pairs' geometry: RealPair-v2's camera, flight and prior at ``flight``."""
    sc = _pair_geometry()
    f, c = sc.flight, sc.camera
    return {"flight": {"altitude_m": flight["flight.altitude_m"], "duration_s": flight["flight.duration_s"],
                       "speed_mps": f.speed_mps, "rate_hz": f.rate_hz, "turn_rate_deg_s": f.turn_rate_deg_s,
                       "min_leg_m": f.min_leg_m},
            "camera": {"width_px": c.width_px, "height_px": c.height_px, "hfov_deg": c.hfov_deg},
            "episode": {"start": sc.episode.start, "prior_std_m": sc.episode.prior_std_m}}
