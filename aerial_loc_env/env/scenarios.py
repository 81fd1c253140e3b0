"""Scenarios: one TOML spec per registered Gymnasium id, read at ``import aerial_loc_env``.

A spec (``envs/<name>.toml``) has a top-level ``id`` (``AerialLoc/<Name>-v<N>``, the version bumped whenever the
scenario's behaviour changes: see the Version History of ``AerialLocEnv``) and ``description``, and sections
that map to frozen dataclasses through ``aerial_loc_env.config.build_config``:

======================  =====================================================================
``[map]``               ``MapConfig``: ``kind = "city"`` (the procedural city, see ``[city]``) or ``"file"``
                        (``path`` to a PNG/TIFF/GeoTIFF/bundle, optional ``gsd_m``, ``crs``); ``use_dsm``
``[city]``              the procedural city's config (``aerial_loc_env.world.city``)
``[flight]``            ``aerial_loc_env.sensors.flight.FlightConfig``
``[wind]``              ``aerial_loc_env.world.wind.WindConfig``: mean wind and gusts (off by default)
``[camera]``            ``aerial_loc_env.sensors.camera.CameraModel`` (the sensor)
``[odometry]``          ``aerial_loc_env.env.briefing.OdometryNoise``
``[shadows]``           ``aerial_loc_env.world.shadows.ShadowConfig``
``[database]``          ``aerial_loc_env.world.maps.acquisition.AcquisitionConfig`` (how the map was acquired)
``[epoch]``             ``aerial_loc_env.world.city.epochs.EpochConfig`` (what changed between map and flight)
``[photometry]``        ``aerial_loc_env.sensors.render.Photometry`` (exposure, noise, vignetting, blur)
``[perspective]``       ``aerial_loc_env.sensors.perspective.PerspectiveConfig``: the height model in perspective
``[gimbal]``            ``aerial_loc_env.sensors.camera.GimbalConfig``: roll/pitch jitter, heading offset
``[altimeter]``         ``aerial_loc_env.sensors.flight.AltimeterConfig``: barometric bias and drift
``[exposure]``          ``aerial_loc_env.sensors.camera.ExposureConfig``: auto-exposure
``[haze]``              ``aerial_loc_env.sensors.camera.HazeConfig``: airlight growing with altitude
``[observation]``       ``ObservationConfig``: the observation image size (the camera image resized)
``[episode]``           ``EpisodeConfig``: start mode, prior, failure rule
``[reward]``            ``RewardConfig``
======================  =====================================================================

Overrides (``gym.make(id, **overrides)`` or ``AerialLocEnv(scenario, **overrides)``), validated like the file:

- a section dict: ``gym.make(id, flight={"altitude_m": 150, "duration_s": 20})``;
- a dotted key: ``gym.make(id, **{"flight.altitude_m": 150})``;
- a bare field name that exists in exactly one section: ``gym.make(id, altitude_m=150)``
  (an ambiguous name such as ``width_px`` is an error naming the sections to choose from).

Unknown keys and out-of-range values raise ``ConfigError`` naming the key, the spec, and the allowed values.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import math
import re
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

from aerial_loc_env.config import build_config, check_value, config_to_dict, is_number, read_toml, rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.paths import spec_dir
from aerial_loc_env.world.scene import MapConfig

ENTRY_POINT = "aerial_loc_env.env.aerial_loc_env:AerialLocEnv"
#: ``gym.make_vec``'s vector_entry_point mode (its default for these ids): ``env/vector.py``
VECTOR_ENTRY_POINT = "aerial_loc_env.env.vector:AerialLocVectorEnv"
NAMESPACE = "AerialLoc"


@dataclass(frozen=True)
class ObservationConfig:
    """The observation image size (the camera image resized: same footprint, other pixel count); unset
    dimensions keep the camera's. ``info_shadow_mask`` adds the ground-truth shadow mask to ``info``."""

    width_px: int | None = None      # [4, 4096]; None keeps the camera's
    height_px: int | None = None     # [4, 4096]; None keeps the camera's
    info_shadow_mask: bool = False

    def validate(self, where: str) -> None:
        for name in ("width_px", "height_px"):
            if getattr(self, name) is not None:
                check_value(name, getattr(self, name), rng(4, 4096), where)


@dataclass(frozen=True)
class EpisodeConfig:
    """Start mode and failure rule.

    ``start = "tracking"``: the prior is Gaussian, its mean drawn around the truth with ``prior_std_m`` per
    axis (the paper: 15 m). ``"global"``: no prior, uniform over the map (the second reference).
    The episode terminates (failure) when the estimate is off by more than ``failure_error_m`` for
    ``failure_steps`` consecutive steps; ``failure_error_m = 0`` disables that (the episode always runs to the
    end of the track, then truncates).
    """

    start: str = field(default="tracking", metadata=rng(choices=("tracking", "global")))
    prior_std_m: float = field(default=15.0, metadata=rng(0.0, 1e4, lo_open=True))
    failure_error_m: float = field(default=0.0, metadata=rng(0.0, 1e6))
    failure_steps: int = field(default=1, metadata=rng(1, 100000))


@dataclass(frozen=True)
class RewardConfig:
    """``reward = -position_error_m / scale_m`` each step (0 is perfect; 1 per ``scale_m`` metres off)."""

    scale_m: float = field(default=100.0, metadata=rng(0.0, 1e6, lo_open=True))


def _lazy(module: str, name: str):
    return lambda: getattr(importlib.import_module(module), name)


# section -> a callable returning its config class (lazy: the world/sensors layers load on first use)
SECTIONS: dict[str, Any] = {
    "map": lambda: MapConfig,
    "city": _lazy("aerial_loc_env.world.city", "CityConfig"),
    "flight": _lazy("aerial_loc_env.sensors.flight", "FlightConfig"),
    "wind": _lazy("aerial_loc_env.world.wind", "WindConfig"),
    "camera": _lazy("aerial_loc_env.sensors.camera", "CameraModel"),
    "odometry": _lazy("aerial_loc_env.env.briefing", "OdometryNoise"),
    "shadows": _lazy("aerial_loc_env.world.shadows", "ShadowConfig"),
    "database": _lazy("aerial_loc_env.world.maps.acquisition", "AcquisitionConfig"),
    "epoch": _lazy("aerial_loc_env.world.city.epochs", "EpochConfig"),
    "photometry": _lazy("aerial_loc_env.sensors.render", "Photometry"),
    "perspective": _lazy("aerial_loc_env.sensors.perspective", "PerspectiveConfig"),
    "gimbal": _lazy("aerial_loc_env.sensors.camera", "GimbalConfig"),
    "altimeter": _lazy("aerial_loc_env.sensors.flight", "AltimeterConfig"),
    "exposure": _lazy("aerial_loc_env.sensors.camera", "ExposureConfig"),
    "haze": _lazy("aerial_loc_env.sensors.camera", "HazeConfig"),
    "observation": lambda: ObservationConfig,
    "episode": lambda: EpisodeConfig,
    "reward": lambda: RewardConfig,
}
TOP_KEYS = ("id", "description")


@dataclass(frozen=True)
class Scenario:
    """A fully validated scenario: its id, the spec it came from, and one config object per section."""

    id: str
    description: str
    source: str
    sections: Mapping[str, Any]

    def __getattr__(self, name: str) -> Any:
        sections = self.__dict__.get("sections", {})
        if name in sections:
            return sections[name]
        raise AttributeError(name)

    def to_dict(self) -> dict:
        """The spec as a plain dict (TOML-able); ``build_scenario`` turns it back into this scenario."""
        out: dict[str, Any] = {"id": self.id, "description": self.description}
        for name, cfg in self.sections.items():
            out[name] = {k: v for k, v in config_to_dict(cfg).items() if v is not None}
        return out


def _section_fields(name: str) -> set[str]:
    return {f.name for f in dataclasses.fields(SECTIONS[name]()) if f.init}


def _fits(annotation: Any, value: Any, choices: tuple | None = None) -> bool:
    """Whether ``value`` could be a value of a field annotated ``annotation`` (for an example in a message)."""
    if choices is not None:
        return value in choices
    args = typing.get_args(annotation)
    kinds = [a for a in args if a is not type(None)] if args and typing.get_origin(annotation) is not tuple \
        else [annotation]
    for kind in kinds:
        origin = typing.get_origin(kind) or kind
        if isinstance(value, bool):
            if kind is bool:
                return True
        elif is_number(value) and kind in (float, int):
            return True
        elif isinstance(value, str) and kind is str:
            return True
        elif isinstance(value, (list, tuple)) and origin is tuple:
            return True
    return False


def not_a_section_error(where: str, section: str, value: Any, *, toml: bool = False) -> ConfigError:
    """The error for a section given a single value (``haze=0.5``): it names the section's fields, with an
    example of setting one of them to that value (a field of the value's type), and, when another section
    has a field of that name (``database.haze``), that one."""
    cls = SECTIONS[section]()
    hints = typing.get_type_hints(cls)
    fields = [f for f in dataclasses.fields(cls) if f.init]
    names = [f.name for f in fields]
    fit = next((f.name for f in fields if _fits(hints.get(f.name), value, f.metadata.get("choices"))), None)
    shown = json.dumps(value) if toml else repr(value)
    field_name, example = (fit, shown) if fit else (names[0], "...")
    if toml:
        how = f"write it as a table: [{section}] with a line such as {field_name} = {example}"
    else:
        how = (f"set one of its fields, e.g. {section}={{'{field_name}': {example}}} or "
               f"**{{'{section}.{field_name}': {example}}}")
    owners = [f"'{s}.{section}'" for s in SECTIONS if s != section and section in _section_fields(s)]
    also = f" (or did you mean the field {' or '.join(owners)}?)" if owners else ""
    return ConfigError(f"{where}: {section} = {shown}: '{section}' is a section of fields, not one value; {how}"
                       f"{also}. Fields of [{section}]: {', '.join(names)}")


def split_overrides(overrides: Mapping[str, Any], where: str = "gym.make overrides") -> dict[str, dict]:
    """Turn the three override forms (section dict, dotted key, unique bare field) into section dicts."""
    out: dict[str, dict] = {}
    for key, value in overrides.items():
        if key in SECTIONS:
            if not isinstance(value, Mapping):
                raise not_a_section_error(where, key, value)
            out.setdefault(key, {}).update(value)
            continue
        if "." in key:
            section, _, name = key.partition(".")
            if section not in SECTIONS:
                raise ConfigError(f"{where}: unknown section {section!r} in {key!r}; "
                                  f"sections: {', '.join(SECTIONS)}")
            out.setdefault(section, {})[name] = value
            continue
        owners = [s for s in SECTIONS if key in _section_fields(s)]
        if not owners:
            raise ConfigError(
                f"{where}: unknown key {key!r}; use a field of a section (e.g. altitude_m, duration_s), "
                f"a dotted key like 'flight.altitude_m', or a section dict; sections: {', '.join(SECTIONS)}")
        if len(owners) > 1:
            raise ConfigError(f"{where}: key {key!r} is ambiguous (it is in sections {', '.join(owners)}); "
                              f"use a dotted key such as '{owners[0]}.{key}' or a section dict")
        out.setdefault(owners[0], {})[key] = value
    return out


def build_scenario(spec: Mapping[str, Any], overrides: Mapping[str, Any] | None = None, *,
                   where: str = "scenario") -> Scenario:
    """Validate a spec dict (as read from TOML) plus overrides into a ``Scenario``."""
    unknown = sorted(set(spec) - set(SECTIONS) - set(TOP_KEYS))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(map(repr, unknown))}; "
                          f"allowed: {', '.join(TOP_KEYS + tuple(SECTIONS))}")
    sid = spec.get("id")
    if not isinstance(sid, str) or not re.fullmatch(rf"{NAMESPACE}/[A-Za-z0-9_]+-v\d+", sid):
        raise ConfigError(f"{where}: 'id' = {sid!r} must look like '{NAMESPACE}/<Name>-v<version>' "
                          "(e.g. 'AerialLoc/Small-v3'; bump the version when the scenario's behaviour changes)")
    extra = split_overrides(overrides or {}, where=f"{sid} overrides")
    sections = {}
    for name, cls_fn in SECTIONS.items():
        table = spec.get(name, {})
        if not isinstance(table, Mapping):
            raise not_a_section_error(where, name, table, toml=True)
        if name in extra:
            table = {**table, **extra[name]}
            label = f"{sid} [{name}] (spec {where} + overrides {sorted(extra[name])})"
        else:
            label = f"{where} [{name}]"
        sections[name] = build_config(cls_fn(), table, where=label)
    sections["altimeter"].check_flight(sections["flight"], sid)     # checks across sections
    sections["wind"].check_flight(sections["flight"].speed_mps, sid)
    return Scenario(id=sid, description=str(spec.get("description", "")), source=where, sections=sections)


def check_relief(scenario: Scenario, world: Any) -> None:
    """Refuse a perspective camera without a height model to draw (a map without a DSM, or ``map.use_dsm =
    false``: it would be the affine camera without a word), and one flying too low over its world's height
    model: the perspective view clips
    heights at a share of the camera's altitude (``sensors.perspective``; a camera among the roofs has no view
    down), so taller buildings would be cut off without a word. ``world``: the scenario's ``world.scene.World``."""
    if scenario.perspective.enabled and (world.ground.dsm_m is None or not scenario.map.use_dsm):
        what = "map.use_dsm = false turns the height model off" if world.ground.dsm_m is not None else \
            f"the map '{world.ground.name}' has no height model (a real image or pair carries none; a bundle " \
            "with a dsm_m layer, or load_orthomap(..., dsm=...), does)"
        raise ConfigError(
            f"{scenario.id}: perspective.enabled = true renders the ground's relief from a height model, but "
            f"{what}, so the perspective camera would silently be the affine one; set perspective.enabled = false "
            "(gym.make(id, perspective={'enabled': False})) or fly a map with a height model")
    if not scenario.perspective.enabled or world.ground.dsm_m is None:
        return
    from aerial_loc_env.sensors.perspective import _MAX_HEIGHT_FRACTION as share

    tallest_m, altitude_m = float(world.dsm_max_m), float(scenario.flight.altitude_m)
    if tallest_m <= share * altitude_m:
        return
    if scenario.map.kind == "city":
        meta = {f.name: f.metadata for f in dataclasses.fields(scenario.city)}["max_building_height_m"]
        lower = (f"lower the city's towers: city.max_building_height_m (allowed [{meta['lo']:g}, {meta['hi']:g}] m, "
                 f"now {scenario.city.max_building_height_m:g}) at most {share * altitude_m:.4g} for this altitude")
    else:
        lower = "turn the height model off (map.use_dsm = false)"
    raise ConfigError(
        f"{scenario.id}: the tallest building of the map is {tallest_m:.1f} m, but flight.altitude_m = "
        f"{altitude_m:g} m: the perspective camera sees heights only up to {share:.0%} of its altitude "
        f"({share * altitude_m:.4g} m), so taller buildings would be cut off; fly higher (flight.altitude_m >= "
        f"{math.ceil(tallest_m / share):g} m), or {lower}, or render without perspective (perspective.enabled = "
        "false)")


def _read(path: Path) -> dict:
    return read_toml(path, "scenario spec")


@dataclass(frozen=True)
class BrokenSpec:
    """A spec file in envs/ that cannot be used: reported when used or listed, never fatal for the others."""

    path: Path
    id: str | None          # the id the file seems to declare, if it can be read at all
    error: str


_ID_LINE = re.compile(rb'^[ \t]*id[ \t]*=[ \t]*"([^"\r\n]+)"', re.MULTILINE)


@cache
def _scan() -> tuple[dict[str, tuple[Path, dict]], tuple[BrokenSpec, ...]]:
    good: dict[str, tuple[Path, dict]] = {}
    broken: list[BrokenSpec] = []
    for path in sorted(spec_dir("envs").glob("*.toml")):
        try:
            raw = _read(path)
            sid = raw.get("id")
            if not isinstance(sid, str) or not sid.startswith(f"{NAMESPACE}/"):
                raise ConfigError(f"{path}: 'id' = {sid!r} must look like '{NAMESPACE}/<Name>-v<N>'")
            if sid in good:
                raise ConfigError(f"{path}: id {sid!r} is already used by {good[sid][0]}")
        except ConfigError as exc:
            try:
                found = _ID_LINE.search(path.read_bytes())
            except OSError:
                found = None
            broken.append(BrokenSpec(path, found.group(1).decode("utf-8", "replace") if found else None,
                                     str(exc)))
            continue
        good[sid] = (path, raw)
    return good, tuple(broken)


def specs() -> dict[str, tuple[Path, dict]]:
    """Registered id -> (spec file, raw spec), read once from ``spec_dir('envs')`` (broken files left out)."""
    return _scan()[0]


def broken_specs() -> tuple[BrokenSpec, ...]:
    """The spec files of ``spec_dir('envs')`` that could not be read or validated."""
    return _scan()[1]


def _short_name(sid: str) -> str:
    """``Small`` for ``AerialLoc/Small-v3`` (the part between the namespace and the version)."""
    return sid.split("/", 1)[1].rsplit("-v", 1)[0]


def registered_version(scenario: str) -> str | None:
    """The registered id of the scenario that ``scenario`` names in another version (``AerialLoc/Small-v3`` for
    ``AerialLoc/Small-v0``); None when ``scenario`` is no versioned id of a registered name."""
    if not (scenario.startswith(f"{NAMESPACE}/") and "-v" in scenario):
        return None
    asked = _short_name(scenario)
    return next((sid for sid in specs() if _short_name(sid) == asked), None)


def resolve(scenario: str) -> tuple[Path, dict]:
    """Find a spec by full id (``AerialLoc/Small-v3``), short name (``Small``) or file stem (``small``)."""
    table = specs()
    if scenario in table:
        return table[scenario]
    for sid, (path, raw) in table.items():
        if scenario in (_short_name(sid), path.stem):
            return path, raw
    sid = registered_version(scenario)
    if sid is not None:
        raise ConfigError(f"scenario {scenario!r} is not registered: this version of the package has {sid!r} "
                          "(an id's version changes when its frames change for the same seed; see "
                          "AerialLocEnv's Version History). Use that id; results of two versions differ.")
    for bad in broken_specs():
        names = {bad.path.stem, bad.id}
        if bad.id and "/" in bad.id:
            names.add(_short_name(bad.id))
        if scenario in names:
            raise ConfigError(f"scenario {scenario!r} cannot be used: {bad.error}")
    raise ConfigError(f"unknown scenario {scenario!r}; registered: {', '.join(table)} "
                      "(`aerial-loc scenarios` lists them)")


def load_scenario(scenario: str, overrides: Mapping[str, Any] | None = None) -> Scenario:
    """The validated scenario ``scenario`` (id, short name or spec stem) with ``overrides``."""
    path, raw = resolve(scenario)
    return build_scenario(raw, overrides, where=str(path))


def register_all() -> list[str]:
    """Register every spec with Gymnasium (idempotent); returns the ids. A broken spec whose id can be read
    is registered too, so that ``gym.make`` of it reports the problem (the others are not affected)."""
    import gymnasium as gym

    ids = []
    broken = [b.id for b in broken_specs() if b.id and b.id.startswith(f"{NAMESPACE}/") and b.id not in specs()]
    for sid in list(specs()) + broken:
        if sid not in gym.registry:
            gym.register(id=sid, entry_point=ENTRY_POINT, vector_entry_point=VECTOR_ENTRY_POINT,
                         kwargs={"scenario": sid}, disable_env_checker=False)
        if sid in specs():
            ids.append(sid)
    return ids


_REQUIRED = "<required>"


def main(argv: list[str] | None = None) -> int:
    """``aerial-loc scenarios``: list the registered ids (``--show ID`` prints one validated spec as TOML)."""
    parser = argparse.ArgumentParser(prog="aerial-loc scenarios", description="list the registered scenarios")
    parser.add_argument("--show", metavar="ID", help="print the full validated spec of one scenario")
    args = parser.parse_args(argv)
    if args.show:
        _path, raw = resolve(args.show)
        table = raw.get("map") if isinstance(raw.get("map"), Mapping) else {}
        required = {"file": ("path",), "pair": ("path_a", "path_b")}.get(table.get("kind"), ())
        # a file or pair scenario names its map at gym.make: show the spec with those fields marked as required
        sc = load_scenario(args.show, {f"map.{n}": _REQUIRED for n in required if not table.get(n)} or None)
        for key in TOP_KEYS:
            print(f"{key} = {json.dumps(getattr(sc, key))}")
        for name, table in sc.to_dict().items():
            if isinstance(table, dict):
                print(f"\n[{name}]")
                for k, v in table.items():
                    example = f"{k}='tile.tif'" if k == "path" else f"{k}='{k[-1].upper()}/tile.png'"
                    print(f"# {k} = (required: gym.make(id, {example}), or map.{k} in an experiment's "
                          "overrides)" if v == _REQUIRED else f"{k} = {json.dumps(v)}")
        return 0
    for sid, (_path, raw) in specs().items():
        print(f"{sid:36s} {raw.get('description', '')}")
    for bad in broken_specs():
        print(f"{(bad.id or bad.path.name) + ' (BROKEN)':36s} {bad.error}")
    return 0


def scenario_spec_dict(scenario: str, **overrides: Any) -> dict:
    """The fully resolved spec of ``scenario`` with ``overrides`` (saved beside trained models and reports)."""
    return load_scenario(scenario, overrides).to_dict()
