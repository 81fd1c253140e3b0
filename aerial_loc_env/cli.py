"""The ``aerial-loc`` command: each subcommand lives in its own module and parses its own arguments."""

from __future__ import annotations

import importlib
import sys

from aerial_loc_env.errors import AerialLocError

# name -> (module with main(argv) -> int, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "bench": ("aerial_loc_env.benchmark.cli", "run an experiment grid (default: compare the main agents)"),
    "gap": ("aerial_loc_env.benchmark.gap", "appearance-gap statistics: scenarios and real image pairs"),
    "fidelity": ("aerial_loc_env.benchmark.fidelity", "do simulated presets rank agents as real image pairs do?"),
    "pictures": ("aerial_loc_env.pictures", "write a map overview and camera frames with/without shadows"),
    "train": ("aerial_loc_env.learning.cli", "train a learned policy from a recipe in agents/"),
    "dataset": ("aerial_loc_env.learning.minari_export", "export recorded episodes as a Minari dataset"),
    "mavlink": ("aerial_loc_env.mavlink.cli", "stream an agent's estimates to a flight controller"),
    "sitl": ("aerial_loc_env.sitl.cli", "fly an ArduPilot SITL mission on the vision fix"),
    "perf": ("aerial_loc_env.perf.__main__", "speed benchmarks on one core"),
    "cog": ("aerial_loc_env.world.maps.cog", "write a map as a COG (tiled, overviews), which envs read by window"),
    "scenarios": ("aerial_loc_env.env.scenarios", "list the registered scenarios"),
    "agents": ("aerial_loc_env.estimators.registry", "list the agent specs"),
}


def _usage() -> str:
    lines = ["usage: aerial-loc <command> [options]", "", "commands:"]
    lines += [f"  {name:10s} {help_}" for name, (_, help_) in COMMANDS.items()]
    lines += ["", "aerial-loc <command> --help for a command's options"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"aerial-loc: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    try:
        module = importlib.import_module(COMMANDS[name][0])
        return int(module.main(rest) or 0)
    except AerialLocError as exc:
        print(f"aerial-loc {name}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"aerial-loc {name}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
