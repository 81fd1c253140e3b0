"""The missions SITL flies on the vision fix: the autopilot's parameters for each feed, the flight plan over the
map, and ``fly_mission``, which checks its inputs, starts SITL, the monitor and the bridge, and flies it.
"""

from __future__ import annotations

import gc
import math
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.mavlink.cli import check_ground_amsl_m, check_sim_speedup
from aerial_loc_env.sitl.monitor import Monitor, sim_clock
from aerial_loc_env.sitl.process import SitlProcess, find_sitl
from aerial_loc_env.sitl.report import (
    horizontal_errors_m,
    read_dataflash,
    timed_horizontal_errors,
    touchdown,
)
from aerial_loc_env.world.maps.geo import offset_latlon

# the copter's flight: 10 m/s legs, 5 m/s climb/descent, RTL at the mission's height, nose first (the env's
# odometry is a unicycle's), arming in AUTO allowed; vertical speed never from the vision fix
COPTER_FLIGHT = {"AUTO_OPTIONS": 7, "WPNAV_SPEED": 1000, "WPNAV_SPEED_UP": 500, "RTL_ALT": 10000,
                 "RTL_ALT_FINAL": 0, "LAND_SPEED_HIGH": 500, "WP_YAW_BEHAVIOR": 1, "EK3_SRC1_VELZ": 0}
# GPS_INPUT (ArduPilot's MAVLink GPS): GPS1 from the bridge
COPTER_GPS_INPUT = {**COPTER_FLIGHT, "GPS1_TYPE": 14}
# ExternalNav (ArduPilot's non-GPS navigation): no GNSS, VISION_POSITION_ESTIMATE through VISO_TYPE 1 (MAVLink);
# position from ExternalNav, no velocity source (VISION_POSITION_ESTIMATE carries none; an image fix
# differentiated is too noisy for VISO_VEL_M_NSE's fixed 0.1 m/s), height from the baro, yaw from the compass
EXTERNAL_NAV_SOURCES = {"POSXY": 6, "VELXY": 0, "POSZ": 1, "VELZ": 0, "YAW": 1}
COPTER_EXTERNAL_NAV = {**COPTER_FLIGHT, "GPS1_TYPE": 0, "VISO_TYPE": 1,
                       **{f"EK3_SRC1_{k}": v for k, v in EXTERNAL_NAV_SOURCES.items()}}
# GNSS denial: SITL's own GPS (source set 1, ArduPilot's defaults) until it is switched off in flight
# (SIM_GPS1_ENABLE 0; older versions' SIM_GPS_DISABLE 1 no longer exists); source set 2 is ExternalNav,
# selected by MAV_CMD_SET_EKF_SOURCE_SET (ArduPilot's GPS / non-GPS transitions; as an RCx_OPTION 90 switch)
COPTER_GNSS_DENIAL = {**COPTER_FLIGHT, "VISO_TYPE": 1, **{f"EK3_SRC2_{k}": v for k, v in EXTERNAL_NAV_SOURCES.items()}}


@dataclass(frozen=True)
class Mission:
    """How a mission feeds the autopilot: its parameters, the bridge's message, the STATUSTEXT that says the
    EKF uses that feed, and whether SITL's GPS is switched off (and the EKF to source set 2) after take-off."""

    params: dict
    message: str
    ready_text: str
    ready_what: str
    deny_gnss: bool = False
    gps_id: int = 0                       # the GPS instance GPS_INPUT feeds (0 = GPS1, 1 = GPS2)
    deny_source_set: int | None = 2       # the EKF source set selected at the denial (None: the autopilot's GPS
    #                                       switching takes the vision GPS itself)
    deny_after_wp: int = 1                # the denial when this mission item is reached


MISSIONS = {
    "gps-input": Mission(COPTER_GPS_INPUT, "gps_input", "is using GPS", "the EKF to use the vision fix (GPS_INPUT)"),
    "external-nav": Mission(COPTER_EXTERNAL_NAV, "vision_position_estimate", "is using external nav",
                            "the EKF to use the vision fix (ExternalNav)"),
    "gnss-denial": Mission(COPTER_GNSS_DENIAL, "vision_position_estimate", "is using GPS",
                           "the EKF to use SITL's GPS before the denial", deny_gnss=True),
}
# ArduPlane, plane.parm's airframe (cruise 22 m/s, at most 30: the paper's 41.7 m/s is beyond this model); the
# mission ends in a landing sequence (DO_LAND_START, NAV_LAND), which an RTL also flies (RTL_AUTOLAND 2); disarm
# 5 s after touchdown. EK3_GPS_CHECK 0: EKF3 must take the fix again in flight, after the climb with none, and its
# GPS quality checks (speed accuracy <= 1 m/s, horizontal <= 5 m, hdop) reject an image fix's first frames and its
# differentiated speed (about 3 m/s accuracy at 22 m/s): with them on, EKF3 often never took the fix again
# (XKF4.GPS 131, EKF_STATUS_REPORT without an absolute position) and the AHRS flew the loop on DCM
# EK3_WIND_P_NSE 1 (ArduPilot's most; default 0.2): the wind weakens towards the ground, and on the final EKF3's
# wind must follow it down while the fix lasts, for the dead reckoning below the camera's range starts from the
# wind it learned last (docs/mavlink.md, the crosswind touchdown)
PLANE_FLIGHT = {"EK3_SRC1_VELZ": 0, "RTL_ALTITUDE": 200, "RTL_AUTOLAND": 2, "EK3_GPS_CHECK": 0,
                "LAND_DISARMDELAY": 5, "SCR_ENABLE": 1, "EK3_WIND_P_NSE": 1.0}
# ArduPlane's own failsafes do not act on a lost fix in fixed-wing flight (its EKF failsafe only in VTOL modes;
# AFS_WP_GPS_LOSS would also fire below the camera's range on every final): the plane runs this Lua script
# (SCR_ENABLE 1), which loiters where the fix was lost and resumes the mission when it is back
PLANE_SCRIPTS = (Path(__file__).resolve().parent / "scripts" / "vision_failsafe.lua",)
# GPS_INPUT as GPS1
PLANE_GPS_INPUT = {**PLANE_FLIGHT, "GPS1_TYPE": 14}
# GNSS denial: SITL's GPS as GPS1 (the primary), the vision fix as GPS2 (GPS_INPUT, gps_id 1); GPS_AUTO_SWITCH 4
# (use the primary while it has a 3D fix, else the best): when SITL's GPS goes (SIM_GPS1_ENABLE 0) the autopilot
# itself switches to GPS2, EKF3's source stays "GPS" (no source-set command)
PLANE_GNSS_DENIAL = {**PLANE_FLIGHT, "GPS2_TYPE": 14, "GPS_AUTO_SWITCH": 4, "GPS_PRIMARY": 0}
PLANE_MISSIONS = {
    "gps-input": Mission(PLANE_GPS_INPUT, "gps_input", "is using GPS", "the EKF to use the vision fix (GPS_INPUT)"),
    "gnss-denial": Mission(PLANE_GNSS_DENIAL, "gps_input", "is using GPS", "the EKF to use SITL's GPS before the "
                           "denial", deny_gnss=True, gps_id=1, deny_source_set=None, deny_after_wp=2),
}



def mission_spec(vehicle: str, mission: str) -> Mission:
    """The ``Mission`` named ``mission`` for ``vehicle``, or a clear error naming the ones it has."""
    if vehicle not in ("copter", "plane"):
        raise ConfigError(f"--vehicle {vehicle!r}: use copter or plane")
    missions = MISSIONS if vehicle == "copter" else PLANE_MISSIONS
    if mission not in missions:
        raise ConfigError(f"--mission {mission!r} for --vehicle {vehicle}: use one of {', '.join(missions)}")
    return missions[mission]


#: the plane's final: from this height above home, this far north of it (a 5.7 deg glide), south to touchdown
PLANE_APPROACH_ALT_M = 100.0
PLANE_GLIDE_M = 1000.0
#: the plane's home (its runway) this far north of the map's south edge, mid-width; its loop's corners this far
#: inside the map's edges (the camera footprint and the turns stay on the map), its legs at least this long
PLANE_HOME_Y_M = 250.0
PLANE_LOOP_INSET_M = 300.0
PLANE_MIN_LEG_M = 400.0
#: the map beyond the farthest point of a flight plan (the camera's footprint around it)
EDGE_M = 100.0


#: the camera's rate in the missions: each frame's fix reaches the autopilot stamped at its capture time, and
#: ArduPilot calls a GPS unhealthy after two updates in a row further apart than ``report.GPS_MAX_DELTA_MS`` (or a
#: running mean over ``report.GPS_AVG_MAX_MS``): a 4 Hz camera's interval sits on that line, where a scheduling
#: hiccup crosses it; 5 Hz leaves a margin
MISSION_CAMERA_HZ = 5.0


#: the map kinds that fly over files the user gives gym.make, which `aerial-loc sitl` has no option for
USER_MAP_KINDS = {"file": "a map file given to gym.make (path=...)",
                  "pair": "two image files given to gym.make (path_a=..., path_b=...)"}


def check_scenario(scenario: str) -> str:
    """The registered id of ``scenario`` (id, short name or spec stem) if ``aerial-loc sitl`` can fly it, else
    a clear error: an old version names the current id; a scenario over the user's files (an old version's too)
    says which ids can be flown."""
    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.env.scenarios import registered_version, resolve, specs

    try:
        _path, raw = resolve(scenario)
        named = raw["id"]
    except ConfigError as exc:
        current = registered_version(scenario)      # an old version: its current id is no use if sitl cannot fly it
        if current is None or _map_kind(specs()[current][1]) not in USER_MAP_KINDS:
            raise ConfigError(f"--scenario: {exc}") from exc
        raw, named = specs()[current][1], f"{scenario} (now {current})"
    if _map_kind(raw) in USER_MAP_KINDS:
        city = [s for s, (_p, r) in specs().items() if _map_kind(r) not in USER_MAP_KINDS]
        raise ConfigError(f"--scenario {named}: flies over {USER_MAP_KINDS[_map_kind(raw)]}, and `aerial-loc sitl` "
                          f"takes no map file; it flies the procedural-city scenarios: {', '.join(city)}")
    return raw["id"]


def _map_kind(raw: dict) -> str:
    section = raw.get("map")
    return section.get("kind", "city") if isinstance(section, dict) else "city"


def check_map_fits(scenario: str, vehicle: str, database: Any, leg_m: float) -> None:
    """Refuse a map too small for the vehicle's flight plan (``mission_items``) before SITL starts: the copter's
    leg east of the map's centre, the plane's loop inset in the map and its final north of home."""
    if vehicle == "copter":
        need_w_m = need_h_m = 2.0 * (leg_m + EDGE_M)
        plan = f"a {leg_m:g} m leg east of the map's centre"
    else:
        need_w_m = 2.0 * PLANE_LOOP_INSET_M + PLANE_MIN_LEG_M
        need_h_m = max(need_w_m, PLANE_HOME_Y_M + PLANE_GLIDE_M + EDGE_M)
        plan = (f"a loop {PLANE_LOOP_INSET_M:g} m inside the edges with legs of {PLANE_MIN_LEG_M:g} m or more, and "
                f"a {PLANE_GLIDE_M:g} m final north of home")
    w_m, h_m = float(database.width_m), float(database.height_m)
    if w_m < need_w_m or h_m < need_h_m:
        raise ConfigError(f"--scenario {scenario}: its map is {w_m:.0f} x {h_m:.0f} m, and the {vehicle}'s flight "
                          f"({plan}) needs at least {need_w_m:.0f} x {need_h_m:.0f} m; choose a larger scenario, "
                          f"e.g. AerialLoc/PaperShadows-v2 (1200 x 1400 m)")


def check_wind(wind: tuple[float, ...] | None) -> tuple[float, ...] | None:
    """SITL's wind: (speed m/s in [0, 30], the direction it blows from, degrees[, gust std m/s in [0, 10]]: SITL's
    turbulence, SIM_WIND_TURB), or a clear error."""
    if wind is None:
        return None
    ok = len(wind) in (2, 3) and all(math.isfinite(v) for v in wind) and 0 <= wind[0] <= 30 \
        and (len(wind) == 2 or 0 <= wind[2] <= 10)
    if not ok:
        raise ConfigError(f"--wind {wind!r}: give SPEED,FROM_DEG[,GUST] with the speed in 0..30 m/s, the direction "
                          f"the wind blows from in degrees and the gusts' std in 0..10 m/s, e.g. 5,270 or 8,270,1.5")
    return tuple(float(v) for v in wind)


#: the bridge's least capture-to-send time (real seconds: rendering and the agent at their fastest; the figure
#: is in docs/mavlink.md, Latency). ArduPilot dates a GPS_INPUT fix at its stamp (the frame's capture) plus
#: the least transport delay its jitter correction has seen, then GPSn_DELAY_MS earlier: set to this, the EKF
#: fuses each fix at its capture time (its default for a MAVLink GPS, a fifth of a second, fused them too early)
BRIDGE_MIN_LATENCY_S = 0.006


def gps_delay_params(gps_id: int, speedup: float) -> dict[str, int]:
    """GPSn_DELAY_MS for the vision GPS (instance ``gps_id``) at SITL's ``speedup``: the bridge's least latency
    on SITL's clock, at least one millisecond (0 would select ArduPilot's default)."""
    return {f"GPS{gps_id + 1}_DELAY_MS": max(1, round(1000.0 * BRIDGE_MIN_LATENCY_S * speedup))}


#: where a vision cut can start: a named point of the flight, or a mission item's number (when it starts)
VISION_CUT_POINTS = ("loop", "approach")
#: the loop's cut starts this long (SITL seconds) after its item started: past the corner's turn, on a leg
CUT_LEG_DELAY_S = {"copter": 2.0, "plane": 5.0}
#: after a cut, the EKF's return to the fix (its reset to the first fixes back) is counted as the failsafe's
CUT_RECOVERY_S = 10.0


def check_vision_cut(cut: tuple[str | int, float] | None) -> tuple[str | int, float] | None:
    """A vision cut (where, seconds): where is 'loop', 'approach' or a mission item's number >= 1, the duration
    in (0, 120] SITL seconds; or a clear error."""
    if cut is None:
        return None
    where, seconds = cut
    item = int(where) if isinstance(where, int) or str(where).isdigit() else None
    if (item is None and where not in VISION_CUT_POINTS) or (item is not None and item < 1) \
            or not (math.isfinite(float(seconds)) and 0 < float(seconds) <= 120):
        raise ConfigError(f"--vision-cut {where},{seconds}: give AT,SECONDS with AT one of "
                          f"{', '.join(VISION_CUT_POINTS)} or a mission item's number (1 or more) and SECONDS in "
                          f"(0, 120], e.g. loop,20")
    return (item if item is not None else str(where)), float(seconds)


def cut_start(vehicle: str, where: str | int, loop_start: int, final_item: int) -> tuple[int, float]:
    """(mission item whose start begins the cut, SITL seconds after it): 'loop' a few seconds into the loop's
    first leg (plane: from its first corner, copter: the leg east), 'approach' the final (plane: NAV_LAND from
    the approach point; copter: RTL), a number that item."""
    if where == "loop":
        return loop_start, CUT_LEG_DELAY_S[vehicle]
    if where == "approach":
        return final_item, 0.0
    return int(where), 0.0


def sitl_home(orthomap: Any, ground_amsl_m: float, heading_deg: float = 0.0,
              xy_m: tuple[float, float] | None = None) -> str:
    """SITL's ``--home`` (LAT,LON,ALT,HEADING) at the map's centre (or at ``xy_m``, world metres): start the
    autopilot where the map is."""
    x, y = xy_m if xy_m is not None else (orthomap.width_m / 2.0, orthomap.height_m / 2.0)
    lat, lon = (float(np.ravel(v)[0]) for v in orthomap.world_to_latlon(x, y))
    return f"{lat:.8f},{lon:.8f},{ground_amsl_m:.2f},{heading_deg:.0f}"


def _wait_sim(monitor: Monitor, seconds: float, speedup: float) -> None:
    """Wait ``seconds`` of SITL's clock (GLOBAL_POSITION_INT.time_boot_ms as the monitor receives it)."""
    with monitor.lock:
        start = monitor.track.clock[-1][1] if monitor.track.clock else None
    if start is None:
        time.sleep(seconds / speedup)
        return
    monitor.wait(lambda t: t.clock[-1][1] >= start + seconds, 2.0 * seconds / speedup + 30.0,
                 f"{seconds:g} s of SITL's clock")


def mission_items(vehicle: str, database: Any, lat0: float, lon0: float, leg_m: float, altitude_m: float,
          camera_min_alt_m: float = 40.0) -> list:
    """Mission items (command, lat, lon, alt above home, param1). Copter: take off at home, a leg east and back,
    RTL (lands). Plane: take off north (home in the map's south) to half the loop's altitude (at least 1.5 x the
    camera's lowest: the agent's first fixes, from the scenario's prior, come during the climb), a rectangular
    loop ``PLANE_LOOP_INSET_M`` inside the map's edges at ``altitude_m``, then a
    landing sequence: DO_LAND_START, an approach point north over the map at ``PLANE_APPROACH_ALT_M``
    and NAV_LAND at home heading south (``PLANE_GLIDE_M`` of final: the vision fix down to ``camera_min_alt_m``,
    dead reckoning below)."""
    mav = mavutil.mavlink
    if vehicle == "copter":
        def east(metres: float) -> tuple[float, float]:
            return tuple(float(v) for v in offset_latlon(lat0, lon0, metres, 0.0))

        return [(mav.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, altitude_m, 0.0),
                (mav.MAV_CMD_NAV_WAYPOINT, *east(leg_m), altitude_m, 0.0),
                (mav.MAV_CMD_NAV_WAYPOINT, *east(5.0), altitude_m, 0.0),
                (mav.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0, 0.0, 0.0, 0.0)]
    w, h, m = database.width_m, database.height_m, PLANE_LOOP_INSET_M

    def at(x: float, y: float) -> tuple[float, float]:
        return tuple(float(np.ravel(v)[0]) for v in database.world_to_latlon(x, y))

    corners = [(w - m, h - m), (w - m, m), (m, m), (m, h - m)]
    hx, hy = (float(np.ravel(v)[0]) for v in database.latlon_to_world(lat0, lon0))
    climb_m = max(1.5 * camera_min_alt_m, 0.5 * altitude_m)
    return ([(mav.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, climb_m, 15.0)]          # 15 deg climb through the camera's range
            + [(mav.MAV_CMD_NAV_WAYPOINT, *at(x, y), altitude_m, 0.0) for x, y in corners]
            + [(mav.MAV_CMD_DO_LAND_START, 0.0, 0.0, 0.0, 0.0),
               (mav.MAV_CMD_NAV_WAYPOINT, *at(hx, hy + PLANE_GLIDE_M), PLANE_APPROACH_ALT_M, 0.0),
               (mav.MAV_CMD_NAV_LAND, lat0, lon0, 0.0, 0.0)])


def fly_mission(scenario: str, agent: str, *, ground_amsl_m: float, vehicle: str = "copter",
                mission: str = "gps-input", leg_m: float = 80.0, altitude_m: float | None = None,
                speedup: float = 1.0, sitl_dir=None, seed: int = 0, timeout_s: float = 300.0, log=None,
                wind: tuple[float, ...] | None = None, vision_cut: tuple[str | int, float] | None = None,
                external_position: bool = False) -> dict:
    """ArduPilot SITL on the vision fix, the camera following SITL's truth. Copter (``MISSIONS``: GPS_INPUT,
    ExternalNav, or SITL's GPS then denied): arm in AUTO on the pad fix, take off, a leg east and back, RTL and
    land. Plane (``PLANE_MISSIONS``: GPS_INPUT, or SITL's GPS then denied): arm in AUTO (on the pad fix, or on
    SITL's GPS), take off (no camera fix from leaving the pad until the camera is in range), a loop over the map
    at the scenario's altitude, the landing sequence (the camera fix down to the agent's lowest altitude, then
    dead reckoning), touchdown and disarm. Returns the record, every time on SITL's clock (seconds since its
    boot): truth and EKF from SITL's dataflash log, the monitor's events, the bridge's steps (the estimator's
    own error, pad/camera/lost), ArduPilot's GPS update intervals, and for the plane the touchdown. ``wind``:
    SITL's wind (speed m/s, direction it blows from, degrees[, gusts' std m/s]; SIM_WIND_SPD / SIM_WIND_DIR /
    SIM_WIND_TURB), none by default.
    ``vision_cut`` (where, seconds; ``check_vision_cut``): the fix is withheld from the autopilot for that long
    from that point (the agent keeps its frames), and the record holds the autopilot's reaction from its log.
    ``external_position``: the bridge also sends MAV_CMD_EXTERNAL_POSITION_ESTIMATE at 1 Hz (SITL's), through a
    cut too (the low-rate global fix for an autopilot dead reckoning); the record holds the autopilot's answers.

    Every input is checked before SITL starts; a death of SITL or of the bridge during the flight is an error
    at once, naming it."""
    import gymnasium as gym

    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.mavlink import cli as mav_cli

    spec = mission_spec(vehicle, mission)
    speedup = check_sim_speedup(speedup, "--speedup")
    ground_amsl_m = check_ground_amsl_m(ground_amsl_m)
    wind = check_wind(wind)
    vision_cut = check_vision_cut(vision_cut)
    find_sitl(vehicle, sitl_dir)
    scenario = check_scenario(scenario)
    env = gym.make(scenario)
    env.reset(seed=seed)
    database = env.unwrapped.database
    scenario_alt_m = float(env.unwrapped.scenario.flight.altitude_m)
    altitude_m = scenario_alt_m if altitude_m is None else altitude_m
    # the camera gives the agent frames within its own altitude range (follow mode), e.g. template-ncc down to 10 m
    # on PaperShadows (its fine level)
    camera_min_alt_m = float(make_agent(agent).altitude_range_m(env.unwrapped.briefing)[0])
    check_map_fits(scenario, vehicle, database, leg_m)
    home_xy = None if vehicle == "copter" else (database.width_m / 2.0, PLANE_HOME_Y_M)
    home = sitl_home(database, ground_amsl_m, 0.0, home_xy)
    env.close()
    lat0, lon0 = (float(v) for v in home.split(",")[:2])
    items = mission_items(vehicle, database, lat0, lon0, leg_m, altitude_m, camera_min_alt_m)
    # the last item (item 0 is home): RTL (copter, lands) or NAV_LAND (plane); the loop's end: the item after the
    # last waypoint (RTL, or DO_LAND_START)
    last_wp = len(items) if vehicle == "plane" else len(items) - 1
    loop_end = next(i for i, it in enumerate(items, 1) if it[0] in (mavutil.mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH,
                                                                    mavutil.mavlink.MAV_CMD_DO_LAND_START))
    loop_start = 2 if vehicle == "copter" else 3
    final_item = len(items)          # the plane's NAV_LAND (the final), the copter's RTL
    if vision_cut is not None and not 1 <= cut_start(vehicle, vision_cut[0], loop_start, final_item)[0] <= len(items):
        raise ConfigError(f"--vision-cut {vision_cut[0]}: the {vehicle}'s mission has items 1 to {len(items)}")
    stop = threading.Event()
    cut = threading.Event()
    t_cut = t_back = None
    result: dict = {}
    steps: list = []      # (monotonic time -> SITL's, source, estimator error m, estimate x, y in the map's frame)
    t_denied, denial = None, None

    def on_step(step) -> None:
        src = step.source if step.estimate.status != "lost" else "lost"
        steps.append((time.monotonic(), src, step.error_m, float(step.estimate.x_m), float(step.estimate.y_m),
                      float(step.altitude_m)))

    # LOG_DISARMED 1: the dataflash log (SITL's own clock: truth, EKF, GPS update intervals) from boot on
    sim_wind = {} if wind is None else {"SIM_WIND_SPD": wind[0], "SIM_WIND_DIR": wind[1],
                                        "SIM_WIND_TURB": wind[2] if len(wind) > 2 else 0.0}
    delay = gps_delay_params(spec.gps_id, speedup) if spec.message == "gps_input" else {}
    with SitlProcess(vehicle, home, {**spec.params, **delay, **sim_wind, "LOG_DISARMED": 1}, speedup=speedup,
                     sitl_dir=sitl_dir, scripts=PLANE_SCRIPTS if vehicle == "plane" else ()) as sitl:
        args = mav_cli.build_parser().parse_args([
            "--scenario", scenario, "--agent", agent, "--follow", "--seed", str(seed),
            "--ground-amsl-m", str(ground_amsl_m), "--connect", f"udpin:127.0.0.1:{sitl.bridge_port}",
            "--message", spec.message + (",external_position" if external_position else ""),
            "--external-position-hz", str(speedup), "--rate-hz", str(10.0 * speedup), "--sim-speedup", str(speedup),
            "--gps-id", str(spec.gps_id), "--set", f"flight.rate_hz={MISSION_CAMERA_HZ:g}",
            *(["--pad-radius-m", "5"] if vehicle == "plane" else []),
            *([] if log is not None else ["--quiet"])])

        def run_bridge() -> None:
            with open(os.devnull, "w") as devnull:
                try:
                    result["rc"] = mav_cli.run(args, out=log or devnull, should_stop=stop.is_set, on_step=on_step,
                                               vision_cut=cut.is_set,
                                               on_sender=lambda s: result.__setitem__("sender", s))
                except Exception as exc:    # noqa: BLE001  (the watchdog reports it in the flight's thread)
                    result["error"] = exc

        def watchdog() -> None:
            """SITL and the bridge must run until the flight ends: a death of either is reported at once."""
            sitl.check_alive()
            if "error" in result:
                raise AerialLocError(f"the bridge stopped: {result['error']}") from result["error"]
            if not bridge.is_alive() and not stop.is_set():
                raise AerialLocError(f"the bridge ended before the flight did (exit code {result.get('rc')})")

        bridge = threading.Thread(target=run_bridge, name="sitl-bridge", daemon=True)
        # The fix must reach the autopilot every period (ArduPilot calls a GPS silent for 0.245 s unhealthy): the
        # objects the process made before the flight are frozen out of the collector's full passes, which would
        # otherwise walk them all while holding the GIL and stall the bridge (a long-lived process, such as a
        # test run or a notebook, can hold millions)
        gc.collect()
        gc.freeze()
        bridge.start()
        monitor = Monitor(sitl.monitor_port, watchdog)
        try:
            monitor.start()
            monitor.wait(lambda t: any(spec.ready_text in x for _, x in t.texts), 120 / speedup, spec.ready_what)
            t_fix = time.monotonic()
            monitor.upload_mission(items)
            end_arm = time.monotonic() + 60 / speedup
            while not monitor.track.armed:
                watchdog()
                if time.monotonic() > end_arm:
                    raise AerialLocError(f"SITL: could not arm in 60 s; last messages: "
                                         f"{[x for _, x in monitor.track.texts[-8:]]}")
                monitor.set_mode("AUTO")
                monitor.arm()
                time.sleep(1.0)
            t_armed = time.monotonic()
            if spec.deny_gnss:    # over the map with the camera in range (copter: top of the climb): GNSS gone
                monitor.wait(lambda t: spec.deny_after_wp in t.reached, timeout_s / speedup,
                             f"mission item {spec.deny_after_wp} before the denial")
                monitor.set_param("SIM_GPS1_ENABLE", 0)
                if spec.deny_source_set is not None:
                    monitor.set_source_set(spec.deny_source_set)
                denial = "SIM_GPS1_ENABLE 0" + ("" if spec.deny_source_set is None
                                                else f", EKF source set {spec.deny_source_set}")
                t_denied = time.monotonic()
            if vision_cut is not None:      # the fix withheld from the autopilot, on SITL's clock
                item, delay = cut_start(vehicle, vision_cut[0], loop_start, final_item)
                monitor.wait(lambda t: any(x.startswith(f"Mission: {item} ") for _, x in t.texts),
                             timeout_s / speedup, f"mission item {item} before the vision cut")
                _wait_sim(monitor, delay, speedup)
                cut.set()
                t_cut = time.monotonic()
                _wait_sim(monitor, vision_cut[1], speedup)
                cut.clear()
                t_back = time.monotonic()
            if vehicle == "copter" and vision_cut is not None:     # its EKF failsafe lands it where it is
                monitor.wait(lambda t: not t.armed, timeout_s / speedup, "the landing and disarming")
            elif vehicle == "copter":
                monitor.wait(lambda t: loop_end - 1 in t.reached, timeout_s / speedup, "the mission's last waypoint")
                monitor.wait(lambda t: not t.armed, timeout_s / speedup, "landing and disarming after RTL")
            else:         # the loop, the landing sequence, touchdown, disarm 5 s later (LAND_DISARMDELAY)
                monitor.wait(lambda t: not t.armed, 2 * timeout_s / speedup, "the landing and disarming")
            t_end = time.monotonic()
        finally:
            cut.clear()
            stop.set()
            bridge.join(10)
            monitor.stop()
            sitl.stop()
            gc.unfreeze()
        if sitl.dataflash_log is None:
            raise AerialLocError(f"SITL wrote no dataflash log (LOG_DISARMED 1); its output: "
                                 f"{(sitl.workdir / 'sitl.log').read_text(errors='replace')[-800:]}")
        flog = read_dataflash(sitl.dataflash_log, spec.gps_id)
    # every time in the record on SITL's clock (seconds since its boot): the log's own stamps, the monitor's
    # arrivals through SITL's clock as GLOBAL_POSITION_INT.time_boot_ms reported it
    tr = monitor.track
    to_sim = sim_clock(tr.clock)
    mono = {"fix": t_fix, "armed": t_armed, "end": t_end}
    t_fix, t_armed, t_end = (to_sim(mono[k]) for k in ("fix", "armed", "end"))
    t_denied = None if t_denied is None else to_sim(t_denied)
    t_cut, t_back = (None if t is None else to_sim(t) for t in (t_cut, t_back))
    mapped = lambda rows: [(to_sim(r[0]), *r[1:]) for r in rows]                      # noqa: E731
    flight = lambda rows: [r for r in rows if t_armed <= r[0] <= t_end]               # noqa: E731
    gps = flog["gps_delta_ms"]
    record = {"vehicle": vehicle, "mission": mission, "last_wp": last_wp, "loop_end": loop_end, "wind": wind,
              "truth": flight(flog["truth"]), "ekf": flight(flog["ekf"]), "texts": mapped(tr.texts),
              "ekf_flags": flight(mapped(tr.ekf_flags)),
              # ArduPilot's own interval between GPS updates, from the EKF taking the fix on (a stall while the
              # bridge starts up is harmless; it is reported apart)
              "gps_gaps_ms": [d for t, d in gps if t_fix <= t <= t_end],
              "gps_gap_max_before_fix_ms": max((d for t, d in gps if t < t_fix), default=0),
              "reached": list(tr.reached), "acks": mapped(tr.acks), "gps_fix": flight(mapped(tr.gps_fix)),
              "fix_to_arm_s": t_armed - t_fix, "flight_s": t_end - t_armed, "bridge_rc": result.get("rc"),
              "t_armed": t_armed, "t_end": t_end, "t_denied": t_denied, "denial": denial,
              "vision_cut": vision_cut, "t_cut": t_cut, "t_back": t_back,
              "modes": flog["modes"], "log_messages": flog["messages"], "gps_status": flog["gps_status"],
              "ekf_status": flog["ekf_status"], "ekf_var_m2": flog["ekf_var_m2"],
              # ArduPilot's health rule replayed from arming: its pre-arm check refuses to arm on the same rule
              # (a slow bridge start-up lifts the running average until it decays; arming waits for it)
              "gps_deltas_ms": [(t, d) for t, d in gps if t <= t_end], "gps_deltas_since_s": t_armed,
              # the fixes' capture-to-send latency (each fix's first send), SITL seconds
              "fix_latency_s": list(result["sender"].latencies_s()) if "sender" in result else [],
              # MAV_CMD_EXTERNAL_POSITION_ESTIMATE: how many sent, and the autopilot's COMMAND_ACK results
              "external_position": ({"sent": result["sender"].stats().sent.get("external_position", 0),
                                     "acks": result["sender"].acks()} if external_position and "sender" in result
                                    else None),
              "steps": flight(mapped(steps)),
              "ground_amsl_m": ground_amsl_m, "camera_min_alt_m": camera_min_alt_m, "speedup": speedup,
              # SITL seconds per real second from the fix to the end: SITL keeps its --speedup or falls behind
              "speedup_achieved": (t_end - t_fix) / max(1e-9, mono["end"] - mono["fix"])}
    record["estimates"] = [(s[0], *(float(np.ravel(v)[0]) for v in database.world_to_latlon(s[3], s[4])))
                           for s in record["steps"] if s[1] == "camera"]
    record["timed_errors"] = timed_horizontal_errors(record["truth"], record["ekf"])
    record["horizontal_errors_m"] = [e for _, e in record["timed_errors"]]
    # the AUTO legs on the vision fix: from the first waypoint (plane: from the loop's first corner, at its
    # altitude; the climb-out to it is the agent's acquisition, from its prior) to the start of RTL / the landing
    record["loop_start"] = loop_start
    starts = {k: next((t for t, x in record["texts"] if x.startswith(f"Mission: {k}")), None)
              for k in (loop_start, loop_end)}
    # a vision cut: from the first fix withheld to CUT_RECOVERY_S after the first fix back is the failsafe's
    # (its own figures: report.failsafe_timeline), not the loop's tracking
    cut_steps = [st[0] for st in record["steps"] if st[1] == "cut"]
    window = (math.inf, -math.inf)
    if cut_steps:
        back = next((st[0] for st in record["steps"] if st[1] == "camera" and st[0] > cut_steps[-1]), cut_steps[-1])
        window = (cut_steps[0], back + CUT_RECOVERY_S)
    record["cut_window"] = window if cut_steps else None
    if starts[loop_start] is not None and starts[loop_end] is not None:
        legs = lambda rows: [r for r in rows if starts[loop_start] <= r[0] <= starts[loop_end]     # noqa: E731
                             and not window[0] <= r[0] <= window[1]]
        record["leg_errors_m"] = horizontal_errors_m(legs(record["truth"]), legs(record["ekf"]))
        record["leg_flags"] = legs(record["ekf_flags"])
    else:
        record["leg_errors_m"], record["leg_flags"] = [], []
    if vehicle == "plane" and starts[loop_start] is not None:    # take-off and climb-out: the acquisition
        record["acquisition_errors_m"] = [e for t, e in record["timed_errors"] if t < starts[loop_start]]
    if vehicle == "plane":
        record["touchdown"] = touchdown(flog["truth"], record["ekf"], record["steps"], (lat0, lon0),
                                        starts[loop_end], flog["ekf_var_m2"])
    return record
