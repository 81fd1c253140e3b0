"""Which generation of the simulator a result came from: generator versions and a scenario fingerprint.

A scenario id names a *setting*; what the env renders for it also depends on the code that generates the world
and the frames (the city generator changed four times under the same ids). Every module of ``world/`` and
``sensors/`` whose output is data (a map, an epoch, an acquisition, a camera model) declares an integer
``GENERATOR_VERSION`` (or another module-level ``<NAME>_VERSION`` integer, e.g. ``BUNDLE_VERSION``) and bumps it
whenever its output changes for the same inputs; ``generator_versions`` collects them all (a new module that
declares one joins without being listed anywhere).
``scenario_fingerprint`` hashes them with the fully resolved spec: the benchmark puts it in every trial key,
so a resumed run can never mix rows of two generations (docs/ARCHITECTURE.md, "Versions").
"""

from __future__ import annotations

import hashlib
import importlib
import json
import pkgutil
from typing import Any

#: the packages whose modules may declare GENERATOR_VERSION
GENERATOR_PACKAGES = ("aerial_loc_env.world", "aerial_loc_env.sensors")


def generator_versions() -> dict[str, int]:
    """``{"world.city": 4, "world.maps.orthomap.BUNDLE_VERSION": 1, ...}``: every integer ``*_VERSION`` defined by a
    world/sensors module (``GENERATOR_VERSION`` is keyed by the module alone; names imported from elsewhere
    are left to the module that defines them)."""
    out: dict[str, int] = {}
    for package in GENERATOR_PACKAGES:
        pkg = importlib.import_module(package)
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{package}."):
            module = importlib.import_module(info.name)
            where = f"{package.rsplit('.', 1)[1]}.{_version_name(info.name)}"
            own = _defined_here(module)
            for name, value in vars(module).items():
                if name.endswith("_VERSION") and isinstance(value, int) and name in own:
                    out[where if name == "GENERATOR_VERSION" else f"{where}.{name}"] = int(value)
    return dict(sorted(out.items()))


def _version_name(module: str) -> str:
    """A module's key among the versions: its own name (``world.maps.orthomap`` -> ``orthomap``), and for the
    ``generator`` module of a subpackage the subpackage's (``world.city.generator`` -> ``city``). Keys do not
    follow the folders, so moving a module between subpackages never invalidates users' results."""
    parent, _, leaf = module.rpartition(".")
    return parent.rpartition(".")[2] if leaf == "generator" else leaf


def _defined_here(module: Any) -> set[str]:
    """Module-level names assigned in the module's own source (not imported into it)."""
    import ast
    import inspect

    try:
        tree = ast.parse(inspect.getsource(module))
    except (OSError, TypeError):  # pragma: no cover (no source: a frozen install)
        return set(vars(module))
    names = set()
    for node in tree.body:
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] \
            if isinstance(node, ast.AnnAssign) else []
        names.update(t.id for t in targets if isinstance(t, ast.Name))
    return names


def fingerprint(spec: dict[str, Any], versions: dict[str, int] | None = None) -> str:
    """A short hash of a resolved scenario spec (its description left out) and the generator versions."""
    body = {k: v for k, v in spec.items() if k != "description"}
    blob = json.dumps({"spec": body, "generators": generator_versions() if versions is None else versions},
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def scenario_fingerprint(scenario: Any) -> str:
    """The fingerprint of a ``Scenario`` (``env.scenarios``): its resolved spec and today's generators."""
    return fingerprint(scenario.to_dict())
