"""The layer rule and the no-circle rule of docs/ARCHITECTURE.md, checked over every import of the package.

Imports are read with ``ast`` (module level, inside functions and under ``TYPE_CHECKING`` alike), so a lazy
import that closes a circle or climbs a layer is caught as surely as a top-level one.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "aerial_loc_env"
ARCHITECTURE = REPO / "docs" / "ARCHITECTURE.md"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the package's modules it imports (``from pkg import sub`` counts as importing ``pkg.sub``)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        is_pkg = path.name == "__init__.py"
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                found = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = name.split(".") if is_pkg else name.split(".")[:-1]
                    base = base[: len(base) - node.level + 1]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                found = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in modules else mod for a in node.names]
            else:
                continue
            for target in found:
                while target and target not in modules:
                    target = target.rpartition(".")[0]
                if target and target != name:
                    targets.add(target)
        graph[name] = targets
    return graph


def layer_table() -> dict[str, int]:
    """Path prefix (``aerial_loc_env/world/``, ``aerial_loc_env/cli.py``) -> layer, from ARCHITECTURE.md."""
    text = ARCHITECTURE.read_text(encoding="utf-8")
    section = text.split("## Layers", 1)[1].split("\n## ", 1)[0]
    table: dict[str, int] = {}
    for line in section.splitlines():
        m = re.match(r"\|\s*(\d+)\s+\w+\s*\|([^|]*)\|", line)
        if m:
            for prefix in re.findall(r"`(aerial_loc_env/[^`]*)`", m.group(2)):
                table[prefix] = int(m.group(1))
    return table


def layer_of(module: str, modules: dict[str, Path], table: dict[str, int]) -> int | None:
    rel = modules[module].relative_to(REPO).as_posix()
    matches = [(len(prefix), layer) for prefix, layer in table.items()
               if rel == prefix or (prefix.endswith("/") and rel.startswith(prefix))]
    return max(matches)[1] if matches else None


def find_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_every_module_has_a_layer():
    modules, table = _modules(), layer_table()
    assert len(set(table.values())) >= 6, f"could not read the layer table of {ARCHITECTURE}: {table}"
    missing = [m for m in modules if layer_of(m, modules, table) is None]
    assert not missing, f"modules in no row of the layer table of {ARCHITECTURE}: {missing}"


def test_no_import_climbs_a_layer():
    modules, table = _modules(), layer_table()
    graph = import_graph(modules)
    layer = {m: layer_of(m, modules, table) for m in modules}   # None: caught by the test above
    upward = [f"{a} (layer {layer[a]}) imports {b} (layer {layer[b]})"
              for a, targets in graph.items() for b in sorted(targets)
              if layer[a] is not None and layer[b] is not None and layer[b] > layer[a]]
    assert not upward, "imports up a layer:\n" + "\n".join(upward)


def test_no_import_circle():
    graph = import_graph(_modules())
    assert sum(len(t) for t in graph.values()) > 100, "the import graph looks empty: the parser is broken"
    cycles = find_cycles(graph)
    assert not cycles, f"import circles: {cycles}"


@pytest.mark.parametrize("source, expected", [
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}, [["a", "b", "c"]]),
    ({"a": {"b"}, "b": set(), "c": {"b"}}, []),
])
def test_the_cycle_finder_finds_cycles(source, expected):
    assert find_cycles(source) == expected


def test_the_parser_sees_lazy_and_relative_imports(tmp_path):
    """A function-level relative import is an edge (the circles of issue 13 were lazy imports)."""
    runner = _modules()["aerial_loc_env.benchmark.runner"]
    graph = import_graph({"aerial_loc_env.benchmark.runner": runner,
                          "aerial_loc_env.benchmark.executors": runner.with_name("executors.py"),
                          "aerial_loc_env.benchmark.episodes": runner.with_name("episodes.py"),
                          "aerial_loc_env.estimators.registry": PACKAGE / "estimators" / "registry.py"})
    assert "aerial_loc_env.benchmark.executors" in graph["aerial_loc_env.benchmark.runner"]
    # episodes.run_episode imports the registry inside the function
    assert "aerial_loc_env.estimators.registry" in graph["aerial_loc_env.benchmark.episodes"]
