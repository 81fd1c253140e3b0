"""``aerial-loc sitl``: fly an ArduPilot SITL mission on the vision fix and write its report.

Every option is checked before SITL starts (the ranges, the output folder, the binary, the scenario), so that a
bad value costs a second, not a flight.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.mavlink.cli import GROUND_AMSL_RANGE_M, SIM_SPEEDUP_RANGE, check_ground_amsl_m, check_sim_speedup
from aerial_loc_env.sitl.missions import (
    MISSIONS,
    VISION_CUT_POINTS,
    check_scenario,
    check_vision_cut,
    check_wind,
    fly_mission,
    mission_spec,
)
from aerial_loc_env.sitl.process import DEFAULT_SITL_DIR, VEHICLES, find_sitl
from aerial_loc_env.sitl.report import check_out_dir, summary, write_outputs

DEFAULT_SCENARIOS = {"copter": "AerialLoc/Small-v3", "plane": "AerialLoc/PaperShadows-v2"}


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="aerial-loc sitl", description="fly an ArduPilot SITL mission on the vision "
                                 "fix: SITL on loopback at the map, the bridge with the camera at SITL's truth")
    ap.add_argument("--vehicle", default="copter", choices=tuple(VEHICLES))
    ap.add_argument("--scenario", default=None, help=f"default: {DEFAULT_SCENARIOS['copter']} (copter), "
                    f"{DEFAULT_SCENARIOS['plane']} (plane: 1.2 x 1.4 km at 200 m, room for a fixed wing's loop)")
    ap.add_argument("--agent", default="template-ncc")
    ap.add_argument("--mission", default="gps-input", choices=tuple(MISSIONS),
                    help="gps-input: GPS_INPUT as GPS1; external-nav (copter): VISION_POSITION_ESTIMATE, no GNSS; "
                         "gnss-denial: SITL's GPS, switched off in flight; copter: EKF to ExternalNav (source set "
                         "2); plane: the vision fix as GPS2, the autopilot switches to it (GPS_AUTO_SWITCH 4)")
    lo, hi = GROUND_AMSL_RANGE_M
    ap.add_argument("--ground-amsl-m", type=float, default=30.0,
                    help=f"SITL's home altitude = the map's ground, m AMSL in [{lo:g}, {hi:g}]")
    ap.add_argument("--sitl-bin", default=None, help=f"folder of the SITL binaries (default {DEFAULT_SITL_DIR})")
    lo, hi = SIM_SPEEDUP_RANGE
    ap.add_argument("--speedup", type=float, default=1.0, help=f"SITL's --speedup, in [{lo:g}, {hi:g}]; the camera "
                    "follows SITL's clock (frame times and odometry scaled by it): keep it where SITL and the agent "
                    "keep pace")
    ap.add_argument("--wind", default=None, metavar="SPEED,FROM_DEG[,GUST]",
                    help="SITL's wind: speed m/s, the direction it blows from, degrees, and the gusts' std m/s "
                         "(SIM_WIND_TURB), e.g. 5,270 or 8,270,1.5; default none")
    ap.add_argument("--vision-cut", default=None, metavar="AT,SECONDS",
                    help=f"withhold the vision fix from the autopilot for SECONDS (SITL's) from AT: "
                         f"{' or '.join(VISION_CUT_POINTS)} (a few seconds into the loop's first leg; the final) or "
                         "a mission item's number, e.g. loop,20; default none")
    ap.add_argument("--external-position", action="store_true",
                    help="also send MAV_CMD_EXTERNAL_POSITION_ESTIMATE at 1 Hz (SITL's), also through a vision cut")
    ap.add_argument("--out", default="sitl-run", help="a new folder (or one without a previous run's files) for "
                    "errors.csv, messages.txt, summary.json and track.png; nothing is overwritten")
    return ap


def parse_wind(text: str | None) -> tuple[float, ...] | None:
    """``--wind SPEED,FROM_DEG[,GUST]`` as a checked tuple, None without the option."""
    if text is None:
        return None
    try:
        wind = tuple(float(v) for v in text.split(","))
    except ValueError:
        wind = ()
    try:
        return check_wind(wind)
    except ConfigError:
        raise ConfigError(f"--wind {text!r}: give SPEED,FROM_DEG[,GUST] with the speed in 0..30 m/s, the direction "
                          f"the wind blows from in degrees and the gusts' std in 0..10 m/s, e.g. 5,270 or 8,270,1.5"
                          ) from None


def parse_vision_cut(text: str | None) -> tuple[str | int, float] | None:
    """``--vision-cut AT,SECONDS`` as a checked pair, None without the option."""
    if text is None:
        return None
    parts = text.split(",")
    try:
        cut = (parts[0].strip(), float(parts[1])) if len(parts) == 2 else None
    except ValueError:
        cut = None
    if cut is None:
        raise ConfigError(f"--vision-cut {text!r}: give AT,SECONDS with AT one of {', '.join(VISION_CUT_POINTS)} "
                          "or a mission item's number, e.g. loop,20")
    return check_vision_cut(cut)


def check_options(args: argparse.Namespace) -> str:
    """Every option checked before anything long starts; returns the scenario id to fly."""
    mission_spec(args.vehicle, args.mission)
    check_sim_speedup(args.speedup, "--speedup")
    check_ground_amsl_m(args.ground_amsl_m)
    parse_wind(args.wind)
    parse_vision_cut(args.vision_cut)
    check_out_dir(Path(args.out))
    find_sitl(args.vehicle, args.sitl_bin)
    return check_scenario(args.scenario or DEFAULT_SCENARIOS[args.vehicle])


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    scenario = check_options(args)
    record = fly_mission(scenario, args.agent, ground_amsl_m=args.ground_amsl_m, vehicle=args.vehicle,
                         mission=args.mission, speedup=args.speedup, sitl_dir=args.sitl_bin, log=sys.stdout,
                         wind=parse_wind(args.wind), vision_cut=parse_vision_cut(args.vision_cut),
                         external_position=args.external_position)
    paths = write_outputs(record, Path(args.out))
    print(json.dumps(summary(record), indent=1))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def run_as_script(argv: list[str] | None = None) -> int:
    """``python -m aerial_loc_env.sitl``: as ``aerial-loc sitl``, errors as one line and exit status 2."""
    try:
        return main(argv)
    except AerialLocError as exc:
        print(f"aerial-loc sitl: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("aerial-loc sitl: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(run_as_script())
