"""The public API at the package root: every name of ``__all__`` one import deep, the layers above the env
loaded only when one of their names is used, and the scenario ids registered by ``import aerial_loc_env`` and by
Gymnasium's ``module:id`` form."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import pytest

import aerial_loc_env as ale

ROOT_INIT = Path(ale.__file__)


def _fresh_python(code: str) -> str:
    """Run ``code`` in a new interpreter (nothing of the package imported yet); its stdout."""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout


@pytest.mark.parametrize("name", ale.__all__)
def test_every_public_name_is_one_import_deep(name):
    assert getattr(ale, name) is not None
    assert name in dir(ale)


def test_the_lazy_names_are_the_objects_of_their_modules():
    for name, module in ale._LAZY.items():
        assert getattr(ale, name) is getattr(importlib.import_module(module), name), name
    assert set(ale._LAZY) <= set(ale.__all__)


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="has no attribute 'make_agnet'"):
        ale.make_agnet  # noqa: B018


def test_the_lazy_names_are_imports_the_layer_test_sees():
    """Each lazy name is also imported under TYPE_CHECKING from the same module: tests/test_architecture.py
    reads that import as the root's edge to the layer above, so a lazy name cannot hide an arrow."""
    seen: dict[str, str] = {}
    for node in ast.walk(ast.parse(ROOT_INIT.read_text(encoding="utf-8"))):
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            for imp in node.body:
                assert isinstance(imp, ast.ImportFrom), ast.dump(imp)
                seen.update({alias.name: imp.module for alias in imp.names})
    assert seen == ale._LAZY


def test_importing_a_lower_layer_does_not_load_the_layers_above():
    out = _fresh_python(
        "import sys, aerial_loc_env.world.maps\n"
        "print(sorted(m for m in sys.modules if m.startswith(('aerial_loc_env.estimators', "
        "'aerial_loc_env.benchmark', 'aerial_loc_env.learning'))))")
    assert out.strip() == "[]"


def test_import_registers_the_ids_and_a_lazy_name_loads_its_layer():
    out = _fresh_python(
        "import sys, gymnasium as gym, aerial_loc_env as ale\n"
        "print('AerialLoc/Small-v3' in gym.registry, 'aerial_loc_env.estimators.registry' in sys.modules)\n"
        "ale.make_agent\n"
        "print('aerial_loc_env.estimators.registry' in sys.modules)")
    assert out.split() == ["True", "False", "True"]


def test_gym_make_with_the_module_prefix_in_a_fresh_interpreter():
    out = _fresh_python(
        "import gymnasium as gym\n"
        "env = gym.make('aerial_loc_env:AerialLoc/Small-v3')\n"
        "obs, info = env.reset(seed=0)\n"
        "print(env.spec.id, obs['image'].shape)")
    assert out.split(maxsplit=1)[0] == "AerialLoc/Small-v3"
