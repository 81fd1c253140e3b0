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
PLANE_FLIGHT = {"EK3_SRC1_VELZ": 0, "RTL_ALTITUDE": 200, "RTL_AUTOLAND": 2, "EK3_GPS_CHECK": 0,
                "LAND_DISARMDELAY": 5}
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


def check_scenario(scenario: str) -> str:
    """The registered id of ``scenario`` (id, short name or spec stem) if ``aerial-loc sitl`` can fly it, else
    a clear error: an old version names the current id, a map-file scenario says which ids can be flown."""
    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.env.scenarios import resolve, specs

    try:
        _path, raw = resolve(scenario)
    except ConfigError as exc:
        raise ConfigError(f"--scenario: {exc}") from exc
    sid = raw["id"]
    if _map_kind(raw) == "file":
        city = [s for s, (_p, r) in specs().items() if _map_kind(r) != "file"]
        raise ConfigError(f"--scenario {sid}: flies over a map file given to gym.make (path=...), and "
                          f"`aerial-loc sitl` takes no map file; it flies the procedural-city scenarios: "
                          f"{', '.join(city)}")
    return sid


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


def check_wind(wind: tuple[float, float] | None) -> tuple[float, float] | None:
    """SITL's wind (speed m/s in [0, 30], the direction it blows from, degrees), or a clear error."""
    if wind is None:
        return None
    if len(wind) != 2 or not 0 <= wind[0] <= 30 or not math.isfinite(wind[1]):
        raise ConfigError(f"--wind {wind!r}: give SPEED,FROM_DEG with the speed in 0..30 m/s and the direction the "
                          f"wind blows from in degrees, e.g. 5,270")
    return float(wind[0]), float(wind[1])


def sitl_home(orthomap: Any, ground_amsl_m: float, heading_deg: float = 0.0,
              xy_m: tuple[float, float] | None = None) -> str:
    """SITL's ``--home`` (LAT,LON,ALT,HEADING) at the map's centre (or at ``xy_m``, world metres): start the
    autopilot where the map is."""
    x, y = xy_m if xy_m is not None else (orthomap.width_m / 2.0, orthomap.height_m / 2.0)
    lat, lon = (float(np.ravel(v)[0]) for v in orthomap.world_to_latlon(x, y))
    return f"{lat:.8f},{lon:.8f},{ground_amsl_m:.2f},{heading_deg:.0f}"


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
                wind: tuple[float, float] | None = None) -> dict:
    """ArduPilot SITL on the vision fix, the camera following SITL's truth. Copter (``MISSIONS``: GPS_INPUT,
    ExternalNav, or SITL's GPS then denied): arm in AUTO on the pad fix, take off, a leg east and back, RTL and
    land. Plane (``PLANE_MISSIONS``: GPS_INPUT, or SITL's GPS then denied): arm in AUTO (on the pad fix, or on
    SITL's GPS), take off (no camera fix from leaving the pad until the camera is in range), a loop over the map
    at the scenario's altitude, the landing sequence (the camera fix down to the agent's lowest altitude, then
    dead reckoning), touchdown and disarm. Returns the record, every time on SITL's clock (seconds since its
    boot): truth and EKF from SITL's dataflash log, the monitor's events, the bridge's steps (the estimator's
    own error, pad/camera/lost), ArduPilot's GPS update intervals, and for the plane the touchdown. ``wind``:
    SITL's wind (speed m/s, direction it blows from, degrees; SIM_WIND_SPD / SIM_WIND_DIR), none by default.

    Every input is checked before SITL starts; a death of SITL or of the bridge during the flight is an error
    at once, naming it."""
    import gymnasium as gym

    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.mavlink import cli as mav_cli

    spec = mission_spec(vehicle, mission)
    speedup = check_sim_speedup(speedup, "--speedup")
    ground_amsl_m = check_ground_amsl_m(ground_amsl_m)
    wind = check_wind(wind)
    find_sitl(vehicle, sitl_dir)
    scenario = check_scenario(scenario)
    env = gym.make(scenario)
    env.reset(seed=seed)
    database = env.unwrapped.database
    scenario_alt_m = float(env.unwrapped.scenario.flight.altitude_m)
    altitude_m = scenario_alt_m if altitude_m is None else altitude_m
    # the camera gives the agent frames within its own altitude range (follow mode), e.g. template-ncc down to 40 m
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
    stop = threading.Event()
    result: dict = {}
    steps: list = []      # (monotonic time -> SITL's, source, estimator error m, estimate x, y in the map's frame)
    t_denied, denial = None, None

    def on_step(step) -> None:
        src = step.source if step.estimate.status != "lost" else "lost"
        steps.append((time.monotonic(), src, step.error_m, float(step.estimate.x_m), float(step.estimate.y_m),
                      float(step.altitude_m)))

    # LOG_DISARMED 1: the dataflash log (SITL's own clock: truth, EKF, GPS update intervals) from boot on
    sim_wind = {} if wind is None else {"SIM_WIND_SPD": float(wind[0]), "SIM_WIND_DIR": float(wind[1])}
    with SitlProcess(vehicle, home, {**spec.params, **sim_wind, "LOG_DISARMED": 1}, speedup=speedup,
                     sitl_dir=sitl_dir) as sitl:
        args = mav_cli.build_parser().parse_args([
            "--scenario", scenario, "--agent", agent, "--follow", "--seed", str(seed),
            "--ground-amsl-m", str(ground_amsl_m), "--connect", f"udpin:127.0.0.1:{sitl.bridge_port}",
            "--message", spec.message, "--rate-hz", str(10.0 * speedup), "--sim-speedup", str(speedup),
            "--gps-id", str(spec.gps_id),
            *(["--pad-radius-m", "5"] if vehicle == "plane" else []),
            *([] if log is not None else ["--quiet"])])

        def run_bridge() -> None:
            with open(os.devnull, "w") as devnull:
                try:
                    result["rc"] = mav_cli.run(args, out=log or devnull, should_stop=stop.is_set, on_step=on_step)
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
            if vehicle == "copter":
                monitor.wait(lambda t: loop_end - 1 in t.reached, timeout_s / speedup, "the mission's last waypoint")
                monitor.wait(lambda t: not t.armed, timeout_s / speedup, "landing and disarming after RTL")
            else:         # the loop, the landing sequence, touchdown, disarm 5 s later (LAND_DISARMDELAY)
                monitor.wait(lambda t: not t.armed, 2 * timeout_s / speedup, "the landing and disarming")
            t_end = time.monotonic()
        finally:
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
    loop_start = 2 if vehicle == "copter" else 3
    record["loop_start"] = loop_start
    starts = {k: next((t for t, x in record["texts"] if x.startswith(f"Mission: {k}")), None)
              for k in (loop_start, loop_end)}
    if starts[loop_start] is not None and starts[loop_end] is not None:
        legs = lambda rows: [r for r in rows if starts[loop_start] <= r[0] <= starts[loop_end]]   # noqa: E731
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
