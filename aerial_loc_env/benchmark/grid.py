"""Experiment grids: agents x scenarios x seeds, from spec files (``experiments/<name>.toml``) or from Python.

An experiment spec::

    name = "table5"
    description = "..."
    seeds = {start = 0, count = 100}          # or a list of integers
    paper = ["table5"]                        # report sections beside the paper's (report.PAPER_SECTIONS)
    plots = ["error_vs_time", "rmse_vs_n_pairs"]
    converge_threshold_m = "auto"             # the default: min(footprint width / 15, prior sigma) per
                                              # scenario (the paper's 10 m); diverge_threshold_m: 5x that
    detector_quality = false                  # true: score the image shadow detector against the true masks

    [[agents]]
    name = "mcl-conventional"                 # agents/<name>.toml
    label = "conventional"
    params = {n_particles = 700}              # overrides of the spec's [params]
    sweep = {"measurement_params.n_pairs" = [10, 30, 50, 70]}   # one agent entry per value (product of keys)

    [[scenarios]]
    id = "AerialLoc/PaperShadows-v2"
    overrides = {"flight.duration_s" = 30}   # gym.make overrides

    [[scenarios]]
    pairs = "../shared/data/pairs/levir-cd"  # a folder of real two-epoch pairs (A/, B/): one AerialLoc/RealPair-v2
    gsd_m = 0.5                              # scenario per pair, its flight fitted to it (pair_scenarios.py)

Parameter keys may be dotted (``measurement_params.n_pairs``): they address nested tables of the spec and are
stored nested, so the dotted and the nested spelling name the same trial.

A relative ``map.path`` in scenario overrides is read from the spec file's folder, except in the experiments
shipped in the package (``experiments/``, installed wherever the package is): those name data beside the project
(``../shared/data``) and are read from the working directory, i.e. run from the repository root.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from aerial_loc_env.config import is_number, read_toml
from aerial_loc_env.errors import ConfigError

EXPERIMENT_DIR = Path(__file__).resolve().parent / "experiments"
PLOTS = ("error_vs_time", "track", "likelihood", "shadow_pairs")  # plus "rmse_vs_<param>"
#: the report sections an experiment may ask for (``paper = [...]``): the paper's tables, "comparison" (every
#: agent on every scenario side by side) and "intervals" (every figure with its bootstrap interval, per scenario
#: group); report.PAPER_SECTIONS builds each
PAPER_SECTION_NAMES = ("table5", "table9", "sweeps", "global", "comparison", "intervals")


def nest_params(params: Mapping[str, Any]) -> dict[str, Any]:
    """``{"a.b": 1, "c": 2}`` -> ``{"a": {"b": 1}, "c": 2}`` (nested tables merged key by key)."""
    out: dict[str, Any] = {}
    for key, value in params.items():
        if isinstance(value, Mapping):
            value = nest_params(value)
        parts = str(key).split(".")
        node = out
        for part in parts[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"parameter '{key}': '{part}' is both a value and a table")
        leaf = parts[-1]
        if isinstance(value, dict) and isinstance(node.get(leaf), dict):
            node[leaf] = {**node[leaf], **value}
        else:
            node[leaf] = value
    return _sorted(out)


def _sorted(d: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _sorted(v) if isinstance(v, Mapping) else v for k, v in sorted(d.items())}


def param_value(params: Mapping[str, Any], name: str, default: Any = None) -> Any:
    """A parameter by dotted path, or by leaf name anywhere in the nested tables (first match, depth first).

    ``param_value(p, "n_pairs")`` finds ``p["measurement_params"]["n_pairs"]``: reports and plots use it to
    group trials by K or N without knowing which table a model keeps them in.
    """
    node: Any = params
    for part in name.split("."):
        if isinstance(node, Mapping) and part in node:
            node = node[part]
        else:
            break
    else:
        return node
    if "." in name:
        return default
    for value in params.values():
        if isinstance(value, Mapping):
            found = param_value(value, name, None)
            if found is not None:
                return found
    return default


@dataclass(frozen=True)
class AgentEntry:
    """One agent configuration of a grid: a spec name (agents/<name>.toml) plus nested parameter overrides."""

    name: str
    params: dict[str, Any] = field(default_factory=dict)
    label: str = ""

    @property
    def display(self) -> str:
        return self.label or self.name

    def spec(self) -> dict[str, Any]:
        """What identifies the agent of a trial (the label is for display only, not part of the identity)."""
        return {"name": self.name, "params": _sorted(self.params)}


@dataclass(frozen=True)
class ScenarioEntry:
    """One scenario of a grid: a registered id plus gym.make overrides."""

    id: str
    overrides: dict[str, Any] = field(default_factory=dict)
    label: str = ""

    @property
    def display(self) -> str:
        return self.label or self.id.split("/")[-1]

    def spec(self) -> dict[str, Any]:
        return {"id": self.id, "overrides": _sorted(self.overrides)}


@dataclass(frozen=True)
class Grid:
    """An experiment: every agent runs on every (scenario, seed) episode."""

    name: str
    agents: tuple[AgentEntry, ...]
    scenarios: tuple[ScenarioEntry, ...]
    seeds: tuple[int, ...]
    description: str = ""
    converge_threshold_m: float | None = None   # None: scaled per scenario (metrics.MetricConfig.for_scenario)
    diverge_threshold_m: float | None = None
    plots: tuple[str, ...] = ("error_vs_time",)
    paper: tuple[str, ...] = ()
    #: score the image shadow detector against the simulator's masks (report section, row columns); trials
    #: stored without it keep their rows (the option is not part of a trial's identity)
    detector_quality: bool = False

    def trials(self) -> int:
        return len(self.agents) * len(self.scenarios) * len(self.seeds)

    def episodes(self) -> int:
        return len(self.scenarios) * len(self.seeds)


def _leaf(key: str) -> str:
    return key.split(".")[-1]


def _expand_agents(items: Sequence[Any], where: str) -> list[AgentEntry]:
    out = []
    for i, item in enumerate(items):
        item = {"name": item} if isinstance(item, str) else dict(item)
        unknown = set(item) - {"name", "params", "label", "sweep"}
        if unknown or not isinstance(item.get("name"), str):
            raise ConfigError(f"{where}: agents[{i}] needs 'name' (an agent spec) and may have 'params', "
                              f"'label', 'sweep' (got {sorted(item)})")
        sweep = item.get("sweep") or {}
        if not isinstance(sweep, Mapping) or any(not isinstance(v, list) or not v for v in sweep.values()):
            raise ConfigError(f"{where}: agents[{i}].sweep must map parameter names to non-empty lists")
        keys = list(sweep)
        for values in itertools.product(*(sweep[k] for k in keys)):
            params = dict(item.get("params") or {})
            params.update(dict(zip(keys, values, strict=True)))
            label = item.get("label") or item["name"]
            if keys:
                label += " " + " ".join(f"{_leaf(k)}={v}" for k, v in zip(keys, values, strict=True))
            out.append(AgentEntry(item["name"], nest_params(params), label))
    displays = [a.display for a in out]
    dup = sorted({d for d in displays if displays.count(d) > 1})
    if dup:
        raise ConfigError(f"{where}: agent labels {dup} appear twice; give each entry its own 'label'")
    return out


def _entries(value: Any, key: str, where: str, single: tuple[type, ...] = (str,)) -> list[Any]:
    """A list of entries; a single one (a name, or a table where ``single`` allows) is a list of one, never
    split into its letters or keys."""
    if isinstance(value, single):
        return [value]
    if isinstance(value, Iterable) and not isinstance(value, (str, bytes, Mapping)):
        return list(value)
    raise ConfigError(f"{where}: {key} = {value!r} must be a list (e.g. {key} = [\"...\", \"...\"]) or a "
                      "single name")


def _integer(value: Any, field: str, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ConfigError(f"{where}: {field} = {value!r} must be an integer")
    return value


def _seeds(value: Any, where: str) -> tuple[int, ...]:
    if isinstance(value, Mapping):
        if set(value) - {"start", "count"} or "count" not in value:
            raise ConfigError(f"{where}: seeds must be a list of integers or {{start = 0, count = N}}")
        start = _integer(value.get("start", 0), "seeds.start", where)
        count = _integer(value["count"], "seeds.count", where)
        if count < 1:
            raise ConfigError(f"{where}: seeds.count = {count} must be >= 1")
        return tuple(range(start, start + count))
    if isinstance(value, int) and not isinstance(value, bool) and value >= 1:
        return tuple(range(value))
    if isinstance(value, (list, tuple)) and value and \
            all(isinstance(s, int) and not isinstance(s, bool) for s in value):
        if len(set(value)) != len(value):
            raise ConfigError(f"{where}: seeds {list(value)} has duplicates")
        return tuple(value)
    raise ConfigError(f"{where}: seeds = {value!r}: seeds must be a count >= 1, a non-empty list of integers "
                      "or {start = 0, count = N}")


def _flag(data: Mapping[str, Any], key: str, where: str) -> bool:
    value = data.get(key, False)
    if not isinstance(value, bool):
        raise ConfigError(f"{where}: {key} = {value!r} must be true or false")
    return value


def _threshold(data: Mapping[str, Any], key: str, where: str) -> float | None:
    """A fixed threshold in metres, or None (absent or "auto"): scaled with each scenario."""
    value = data.get(key, "auto")
    if value == "auto":
        return None
    if not is_number(value) or not math.isfinite(value):
        raise ConfigError(f"{where}: {key} = {value!r} must be a finite number of metres, or \"auto\" (the "
                          "default: scaled with each scenario's footprint and prior)")
    return float(value)


def _resolve_map_paths(overrides: Mapping[str, Any], base: Path) -> dict[str, Any]:
    """Overrides with a relative ``map.path`` made absolute against ``base`` (the experiment file's folder)."""
    out = dict(overrides)
    for key, value in overrides.items():
        if key in ("map.path", "path") and isinstance(value, str):
            out[key] = str(base / value) if not Path(value).expanduser().is_absolute() else value
        elif key == "map" and isinstance(value, Mapping) and isinstance(value.get("path"), str):
            p = value["path"]
            out[key] = {**value, "path": p if Path(p).expanduser().is_absolute() else str(base / p)}
    return out


def grid_from_dict(data: Mapping[str, Any], where: str = "experiment", base_dir: Path | None = None) -> Grid:
    """A grid from a mapping laid out like an experiment spec (see the module docstring); a relative
    ``map.path`` in scenario overrides is relative to ``base_dir`` (the experiment file's folder) when given."""
    allowed = {"name", "description", "agents", "scenarios", "seeds", "converge_threshold_m",
               "diverge_threshold_m", "plots", "paper", "detector_quality"}
    unknown = set(data) - allowed
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(allowed)}")
    for key in ("agents", "scenarios", "seeds"):
        if key not in data:
            raise ConfigError(f"{where}: missing '{key}'")
    agents = _entries(data["agents"], "agents", where, (str, Mapping))
    scenario_items = _entries(data["scenarios"], "scenarios", where, (str, Mapping))
    if not agents or not scenario_items:
        raise ConfigError(f"{where}: 'agents' and 'scenarios' must each list at least one entry")
    scenarios = []
    for i, s in enumerate(scenario_items):
        s = {"id": s} if isinstance(s, str) else dict(s)
        if "pairs" in s:      # a folder of real two-epoch pairs: one RealPair scenario per pair
            from aerial_loc_env.benchmark.pair_scenarios import expand_pairs_entry

            scenarios += [ScenarioEntry(**e) for e in expand_pairs_entry(s, f"{where}: scenarios[{i}]", base_dir)]
            continue
        if not isinstance(s.get("id"), str) or set(s) - {"id", "overrides", "label"}:
            raise ConfigError(f"{where}: scenarios[{i}] needs 'id' and may have 'overrides', 'label'")
        overrides = s.get("overrides") or {}
        if not isinstance(overrides, Mapping):
            raise ConfigError(f"{where}: scenarios[{i}].overrides must be a table, got {overrides!r}")
        if base_dir is not None:
            overrides = _resolve_map_paths(overrides, base_dir)
        scenarios.append(ScenarioEntry(s["id"], dict(overrides), s.get("label", "")))
    plots = tuple(_entries(data.get("plots", ["error_vs_time"]), "plots", where))
    bad = [p for p in plots if p not in PLOTS and not p.startswith("rmse_vs_")]
    if bad:
        raise ConfigError(f"{where}: unknown plot(s) {bad}; use {', '.join(PLOTS)} or rmse_vs_<parameter>")
    paper = tuple(_entries(data.get("paper", []), "paper", where))
    bad = [p for p in paper if p not in PAPER_SECTION_NAMES]
    if bad:
        raise ConfigError(f"{where}: unknown paper section(s) {bad}; use {', '.join(PAPER_SECTION_NAMES)}")
    converge = _threshold(data, "converge_threshold_m", where)
    diverge = _threshold(data, "diverge_threshold_m", where)
    low = [v for v in (converge, diverge) if v is not None and v <= 0.0]
    if low or (converge is not None and diverge is not None and converge > diverge):
        raise ConfigError(f"{where}: need 0 < converge_threshold_m ({converge}) <= "
                          f"diverge_threshold_m ({diverge})")
    return Grid(
        name=str(data.get("name", Path(where).stem)),
        agents=tuple(_expand_agents(agents, where)),
        scenarios=tuple(scenarios),
        seeds=_seeds(data["seeds"], where),
        description=str(data.get("description", "")),
        converge_threshold_m=converge,
        diverge_threshold_m=diverge,
        plots=plots,
        paper=paper,
        detector_quality=_flag(data, "detector_quality", where),
    )


def check_scenarios(grid: Grid) -> None:
    """Build each scenario's env once (spec, overrides, map file, flyable area) so that a bad map is one clear
    error before any trial starts, not one failure per trial and an empty table."""
    import gymnasium as gym

    from aerial_loc_env.env import register_all
    from aerial_loc_env.errors import AerialLocError

    register_all()
    for entry in grid.scenarios:
        try:
            gym.make(entry.id, **entry.overrides).close()
        except (AerialLocError, gym.error.Error) as exc:
            raise ConfigError(f"experiment '{grid.name}': scenario '{entry.display}' ({entry.id}, overrides "
                              f"{entry.overrides}) cannot run: {exc}. Fix it first; no trial was started") from None


def make_grid(name: str, agents: Sequence[Any], scenarios: Sequence[Any], seeds: Any, **options: Any) -> Grid:
    """A grid from Python: ``make_grid("mine", ["mcl-shadow-aware"], ["AerialLoc/Small-v3"], seeds=5)``."""
    where = f"grid '{name}'"
    return grid_from_dict({"name": name, "agents": _entries(agents, "agents", where, (str, Mapping)),
                           "scenarios": _entries(scenarios, "scenarios", where, (str, Mapping)), "seeds": seeds,
                           **options}, where=where)


def available_experiments() -> list[str]:
    return sorted(p.stem for p in EXPERIMENT_DIR.glob("*.toml"))


def load_grid(name_or_path: str | Path) -> Grid:
    """An experiment by name (aerial_loc_env/benchmark/experiments/<name>.toml) or by path."""
    path = Path(name_or_path)
    if not path.suffix:
        path = EXPERIMENT_DIR / f"{name_or_path}.toml"
    if not path.is_file():
        raise ConfigError(f"experiment '{name_or_path}' not found (looked for {path}); "
                          f"available: {', '.join(available_experiments())}")
    folder = path.resolve().parent
    # a shipped experiment's relative map paths from the working directory: its own folder is inside the package
    base = Path.cwd() if folder == EXPERIMENT_DIR else folder
    return grid_from_dict(read_toml(path, "experiment"), where=str(path), base_dir=base)
