"""Experiment grids: agents x scenarios x seeds, from spec files or from Python."""

from __future__ import annotations

import itertools
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

EXPERIMENT_DIR = Path(__file__).resolve().parent / "experiments"


@dataclass(frozen=True)
class AgentEntry:
    """One agent configuration of a grid: a spec name (agents/<name>.toml) plus parameter overrides."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)
    label: str = ""

    @property
    def display(self) -> str:
        return self.label or self.name

    def spec(self) -> dict[str, Any]:
        return {"name": self.name, "params": dict(sorted(self.params.items())), "label": self.display}


@dataclass(frozen=True)
class ScenarioEntry:
    """One scenario of a grid: a registered id plus gym.make overrides."""

    id: str
    overrides: dict[str, Any] = field(default_factory=dict)
    label: str = ""

    @property
    def display(self) -> str:
        return self.label or self.id

    def spec(self) -> dict[str, Any]:
        return {"id": self.id, "overrides": dict(sorted(self.overrides.items())), "label": self.display}


@dataclass(frozen=True)
class Grid:
    name: str
    agents: tuple[AgentEntry, ...]
    scenarios: tuple[ScenarioEntry, ...]
    seeds: tuple[int, ...]
    description: str = ""
    converge_threshold_m: float = 10.0
    plots: tuple[str, ...] = ("error_vs_time",)

    def trials(self) -> int:
        return len(self.agents) * len(self.scenarios) * len(self.seeds)


def _expand_agents(items: list[dict], where: str) -> list[AgentEntry]:
    out = []
    for i, item in enumerate(items):
        item = dict(item)
        unknown = set(item) - {"name", "params", "label", "sweep"}
        if unknown or "name" not in item:
            raise ConfigError(f"{where}: agents[{i}] needs 'name' and may have 'params', 'label', 'sweep' "
                              f"(got {sorted(item)})")
        sweep = item.get("sweep") or {}
        keys = sorted(sweep)
        for values in itertools.product(*(sweep[k] for k in keys)) if keys else [()]:
            params = dict(item.get("params") or {})
            params.update(dict(zip(keys, values, strict=True)))
            label = item.get("label") or item["name"]
            if keys:
                label += " " + " ".join(f"{k}={v}" for k, v in zip(keys, values, strict=True))
            out.append(AgentEntry(item["name"], params, label))
    return out


def _seeds(value: Any, where: str) -> tuple[int, ...]:
    if isinstance(value, dict):
        if set(value) - {"start", "count"} or "count" not in value:
            raise ConfigError(f"{where}: seeds must be a list of integers or {{start = 0, count = N}}")
        start, count = int(value.get("start", 0)), int(value["count"])
        if count < 1:
            raise ConfigError(f"{where}: seeds.count = {count} must be >= 1")
        return tuple(range(start, start + count))
    if isinstance(value, list) and value and all(isinstance(s, int) for s in value):
        return tuple(value)
    raise ConfigError(f"{where}: seeds must be a non-empty list of integers or {{start = 0, count = N}}")


def grid_from_dict(data: dict, where: str = "experiment") -> Grid:
    allowed = {"name", "description", "agents", "scenarios", "seeds", "converge_threshold_m", "plots"}
    unknown = set(data) - allowed
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    for key in ("agents", "scenarios", "seeds"):
        if key not in data:
            raise ConfigError(f"{where}: missing '{key}'")
    scenarios = []
    for i, s in enumerate(data["scenarios"]):
        if isinstance(s, str):
            s = {"id": s}
        if "id" not in s or set(s) - {"id", "overrides", "label"}:
            raise ConfigError(f"{where}: scenarios[{i}] needs 'id' and may have 'overrides', 'label'")
        scenarios.append(ScenarioEntry(s["id"], dict(s.get("overrides") or {}), s.get("label", "")))
    agents = _expand_agents([{"name": a} if isinstance(a, str) else a for a in data["agents"]], where)
    return Grid(
        name=str(data.get("name", Path(where).stem)),
        agents=tuple(agents),
        scenarios=tuple(scenarios),
        seeds=_seeds(data["seeds"], where),
        description=str(data.get("description", "")),
        converge_threshold_m=float(data.get("converge_threshold_m", 10.0)),
        plots=tuple(data.get("plots", ("error_vs_time",))),
    )


def available_experiments() -> list[str]:
    return sorted(p.stem for p in EXPERIMENT_DIR.glob("*.toml"))


def load_grid(name_or_path: str) -> Grid:
    """An experiment by name (aerial_loc_env/benchmark/experiments/<name>.toml) or by path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = EXPERIMENT_DIR / f"{name_or_path}.toml"
    if not path.is_file():
        raise ConfigError(f"experiment '{name_or_path}' not found (looked for {path}); "
                          f"available: {', '.join(available_experiments())}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from exc
    return grid_from_dict(data, where=str(path))
