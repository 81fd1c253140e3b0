"""Agent specs: build agents by name from ``agents/<name>.toml``, by dotted path, or from an entry point.

A spec names one configuration::

    description = "the paper's proposal: shadow-aware information allocation"
    class = "MCLAgent"                 # a short name below, "package.module:Class", or an entry-point name
    [params]                           # validated against the class's Params dataclass
    n_particles = 700

Top-level keys other than ``class``, ``description`` and ``params`` are refused, except ``train`` (a recipe
table read by the learning module, kept in ``AgentSpec.extra``). Third-party packages expose agent classes
under the entry-point group ``aerial_loc_env.agents`` (``name = "package.module:Class"``).

``make_agent("mcl-shadow-aware", n_particles=300)`` builds a spec with overrides; ``aerial-loc agents``
lists them.
"""

from __future__ import annotations

import argparse
import importlib
import json
from collections.abc import Mapping
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from aerial_loc_env.config import read_toml
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.protocol import Agent
from aerial_loc_env.paths import spec_dir

ENTRY_POINT_GROUP = "aerial_loc_env.agents"

#: short class names usable in specs; add yours with ``register_class``
SHORT_NAMES: dict[str, str] = {
    "MCLAgent": "aerial_loc_env.estimators.mcl.agent:MCLAgent",
    "DeadReckoningAgent": "aerial_loc_env.estimators.dead_reckoning:DeadReckoningAgent",
    "TemplateMatchingAgent": "aerial_loc_env.estimators.template_matching:TemplateMatchingAgent",
    "FeatureMatchingAgent": "aerial_loc_env.estimators.feature_matching:FeatureMatchingAgent",
    "LearnedAgent": "aerial_loc_env.learning.agent:LearnedAgent",
    "SurfaceRegistrationAgent": "aerial_loc_env.learning.surface:SurfaceRegistrationAgent",
}
_SPEC_KEYS = ("class", "description", "params")
_EXTRA_SECTIONS = ("train",)


@dataclass(frozen=True)
class AgentSpec:
    """One agent configuration as read from a spec file (or built in code)."""

    name: str
    class_ref: str
    params: Mapping[str, Any] = field(default_factory=dict)
    description: str = ""
    path: Path | None = None
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def where(self) -> str:
        return str(self.path) if self.path else f"agent spec {self.name!r}"


def register_class(short_name: str, dotted: str) -> None:
    """Let specs name ``dotted`` ("package.module:Class") by ``short_name``."""
    if short_name in SHORT_NAMES and SHORT_NAMES[short_name] != dotted:
        raise ConfigError(f"agent class name {short_name!r} is already registered "
                          f"for {SHORT_NAMES[short_name]}")
    SHORT_NAMES[short_name] = dotted


def resolve_dotted(ref: str, *, where: str = "agent spec") -> Any:
    """Import ``package.module:Attr`` (or ``package.module.Attr``) with a clear error."""
    if ":" in ref:
        module_name, _, attr = ref.partition(":")
    else:
        module_name, _, attr = ref.rpartition(".")
    if not module_name or not attr:
        raise ConfigError(f"{where}: class {ref!r} is not a dotted path; use 'package.module:Class'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"{where}: cannot import module {module_name!r} for class {ref!r}: {exc}") from exc
    obj: Any = module
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ConfigError(f"{where}: module {module_name!r} has no attribute {attr!r}")
        obj = getattr(obj, part)
    return obj


def resolve_class(ref: str, *, where: str = "agent spec") -> type[Agent]:
    """An Agent subclass from a short name, an entry-point name, or a dotted path."""
    if ref in SHORT_NAMES:
        obj = resolve_dotted(SHORT_NAMES[ref], where=where)
    elif ":" in ref or "." in ref:
        obj = resolve_dotted(ref, where=where)
    else:
        eps = [ep for ep in entry_points(group=ENTRY_POINT_GROUP) if ep.name == ref]
        if not eps:
            known = sorted(SHORT_NAMES) + sorted(ep.name for ep in entry_points(group=ENTRY_POINT_GROUP))
            raise ConfigError(f"{where}: unknown agent class {ref!r}; use one of {', '.join(known)}, "
                              "or a dotted path 'package.module:Class'")
        try:
            obj = eps[0].load()
        except Exception as exc:  # a broken third-party package: say which
            raise ConfigError(f"{where}: entry point {ref!r} ({eps[0].value}) failed to load: {exc}") from exc
    if not (isinstance(obj, type) and issubclass(obj, Agent)):
        raise ConfigError(f"{where}: {ref!r} is not an Agent subclass "
                          "(aerial_loc_env.estimators.protocol.Agent)")
    return obj


def parse_spec(data: Mapping[str, Any], *, name: str, path: Path | None = None) -> AgentSpec:
    """Check the top-level layout of a spec mapping and return an ``AgentSpec``."""
    where = str(path) if path else f"agent spec {name!r}"
    unknown = sorted(set(data) - set(_SPEC_KEYS) - set(_EXTRA_SECTIONS))
    if unknown:
        raise ConfigError(f"{where}: unknown top-level key(s) {unknown}; allowed: "
                          f"{', '.join(_SPEC_KEYS + _EXTRA_SECTIONS)}")
    if not isinstance(data.get("class"), str):
        raise ConfigError(f"{where}: missing 'class' (a short name, or 'package.module:Class')")
    params = data.get("params", {})
    if not isinstance(params, Mapping):
        raise ConfigError(f"{where}: [params] must be a table")
    description = data.get("description", "")
    if not isinstance(description, str):
        raise ConfigError(f"{where}: 'description' must be a string")
    extra = {k: data[k] for k in _EXTRA_SECTIONS if k in data}
    return AgentSpec(name, data["class"], dict(params), description, path, extra)


def load_spec(name_or_path: str | Path) -> AgentSpec:
    """The spec ``agents/<name>.toml``, or a TOML file given by path."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        path = p
    else:
        path = spec_dir("agents") / f"{name_or_path}.toml"
        if not path.is_file():
            raise ConfigError(f"unknown agent spec {str(name_or_path)!r}; known: {', '.join(spec_names())}")
    data = read_toml(path, "agent spec")
    return parse_spec(data, name=path.stem, path=path)


def spec_names() -> list[str]:
    """Names of the spec files in agents/."""
    return sorted(p.stem for p in spec_dir("agents").glob("*.toml"))


def list_specs() -> list[AgentSpec]:
    return [load_spec(n) for n in spec_names()]


def build_agent(spec: AgentSpec, **overrides: Any) -> Agent:
    """Instantiate ``spec`` with ``overrides`` on top of its [params] (validated by the class's Params)."""
    cls = resolve_class(spec.class_ref, where=spec.where)
    where = spec.where + (f" + overrides {sorted(overrides)}" if overrides else "")
    agent = cls.from_params(merge_params(spec.params, overrides), where=where)
    agent.name = spec.name
    return agent


def merge_params(base: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """``overrides`` on top of ``base``; nested tables (e.g. ``measurement_params``) are merged key by key."""
    out = dict(base)
    for k, v in overrides.items():
        out[k] = merge_params(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def make_agent(name: str | Path | type[Agent], **overrides: Any) -> Agent:
    """Build an agent from a spec name/path, a dotted class path, or an Agent subclass, with overrides."""
    if isinstance(name, type):
        spec = AgentSpec(name.__name__, f"{name.__module__}:{name.__qualname__}")
    elif isinstance(name, str) and (":" in name or name in SHORT_NAMES) and not name.endswith(".toml"):
        spec = AgentSpec(name, name)
    elif isinstance(name, str) and "/" not in name and not name.endswith(".toml") \
            and name not in spec_names() and _is_entry_point(name):
        spec = AgentSpec(name, name)
    else:
        spec = load_spec(name)
    return build_agent(spec, **overrides)


def _is_entry_point(name: str) -> bool:
    return any(ep.name == name for ep in entry_points(group=ENTRY_POINT_GROUP))


def main(argv: list[str] | None = None) -> int:
    """``aerial-loc agents``: list the agent specs (or show one with its parameters)."""
    parser = argparse.ArgumentParser(prog="aerial-loc agents", description="List the agent specs in agents/.")
    parser.add_argument("name", nargs="?", help="show this spec's class and parameters (validated)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    args = parser.parse_args(argv)
    if args.name:
        spec = load_spec(args.name)
        agent = build_agent(spec)  # validates the parameters
        params = getattr(agent, "params", None)
        from aerial_loc_env.config import config_to_dict

        full = config_to_dict(params) if params is not None and hasattr(params, "__dataclass_fields__") \
            else dict(spec.params)
        out = {"name": spec.name, "class": spec.class_ref, "description": spec.description, "params": full}
        print(json.dumps(out, indent=2, default=str) if args.json else
              "\n".join([f"{spec.name}: {spec.description}", f"  class = {spec.class_ref}"]
                        + [f"  {k} = {v!r}" for k, v in full.items()]))
        return 0
    specs = list_specs()
    if args.json:
        print(json.dumps([{"name": s.name, "class": s.class_ref, "description": s.description,
                           "params": dict(s.params)} for s in specs], indent=2, default=str))
        return 0
    width = max((len(s.name) for s in specs), default=4)
    for s in specs:
        print(f"{s.name:{width}s}  {s.description}")
    return 0
