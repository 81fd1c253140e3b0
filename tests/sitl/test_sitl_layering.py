"""SITL sits on top of the MAVLink bridge: ``aerial_loc_env.sitl`` may import ``aerial_loc_env.mavlink``, never the
other way round (the bridge works with any autopilot, simulated or not)."""

from __future__ import annotations

import ast
from pathlib import Path

MAVLINK = Path(__file__).resolve().parents[2] / "aerial_loc_env" / "mavlink"


def test_mavlink_never_imports_sitl():
    found = []
    for path in sorted(MAVLINK.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            found += [f"{path.name}: {n}" for n in names if n.startswith("aerial_loc_env.sitl")]
    assert not found, found
    assert sorted(p.name for p in MAVLINK.glob("*.py")) and not (MAVLINK / "sitl.py").exists()
