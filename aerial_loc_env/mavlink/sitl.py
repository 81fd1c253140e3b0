"""ArduPilot SITL on loopback: start it at the map, watch it, fly a mission with the bridge in the loop.

Why here: the bridge's claims (rates, frames, accuracies, follow mode) only mean something against a real
autopilot. ``SitlProcess`` starts an ArduPilot SITL binary (``../shared/sitl/`` by default) with its home at the
map's centre (``sitl_home``), SERIAL0 to a ``Monitor`` (commands, truth, EKF, STATUSTEXT) and SERIAL1 to the
bridge, both UDP on 127.0.0.1 only; the process is always killed on exit.
"""

from __future__ import annotations

import math
import os
import random
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink import mavutil

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.mavlink.cli import EARTH_RADIUS_M
from aerial_loc_env.mavlink.selfcheck import free_udp_port

VEHICLES = {"copter": ("arducopter", "+", "copter.parm"), "plane": ("arduplane", "plane", "plane.parm")}
DEFAULT_SITL_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "sitl"

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
# differentiated speed (about 3 m/s accuracy at 22 m/s): with them on, in 4 of 6 runs EKF3 never took the fix
# again (XKF4.GPS 131, EKF_STATUS_REPORT without an absolute position) and the AHRS flew the loop on DCM
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
MAV_CMD_SET_EKF_SOURCE_SET = 42007     # ardupilotmega: param1 = source set 1..3


def find_sitl(vehicle: str, sitl_dir: str | os.PathLike | None = None) -> tuple[Path, Path, str]:
    """(binary, default parameter file, model) of ``vehicle`` in ``sitl_dir`` (default ../shared/sitl/)."""
    if vehicle not in VEHICLES:
        raise ConfigError(f"--vehicle {vehicle!r}: use one of {', '.join(VEHICLES)}")
    exe, model, parm = VEHICLES[vehicle]
    folder = Path(sitl_dir) if sitl_dir is not None else DEFAULT_SITL_DIR
    binary, defaults = folder / exe, folder / parm
    if not (binary.is_file() and os.access(binary, os.X_OK)):
        raise ConfigError(f"--sitl-bin {folder}: no executable '{exe}' there; build ArduPilot SITL "
                          f"(./waf configure --board sitl && ./waf {vehicle}) and give its folder")
    if not defaults.is_file():
        raise ConfigError(f"--sitl-bin {folder}: no '{parm}' (ArduPilot's default parameters for {vehicle})")
    return binary, defaults, model


def sitl_home(orthomap: Any, ground_amsl_m: float, heading_deg: float = 0.0,
              xy_m: tuple[float, float] | None = None) -> str:
    """SITL's ``--home`` (LAT,LON,ALT,HEADING) at the map's centre (or at ``xy_m``, world metres): start the
    autopilot where the map is."""
    x, y = xy_m if xy_m is not None else (orthomap.width_m / 2.0, orthomap.height_m / 2.0)
    lat, lon = (float(np.ravel(v)[0]) for v in orthomap.world_to_latlon(x, y))
    return f"{lat:.8f},{lon:.8f},{ground_amsl_m:.2f},{heading_deg:.0f}"


def _die_with_parent() -> None:
    """In the child before exec: SIGKILL when the parent dies (Linux), so no SITL outlives a killed run."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)    # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class SitlProcess:
    """One SITL instance on loopback (context manager; killed, with its process group, on exit)."""

    def __init__(self, vehicle: str, home: str, params: dict[str, float], *, speedup: float = 1.0,
                 sitl_dir: str | os.PathLike | None = None) -> None:
        self.binary, self.defaults, self.model = find_sitl(vehicle, sitl_dir)
        self.home, self.params, self.speedup = home, dict(params), speedup
        self.monitor_port, self.bridge_port = free_udp_port(), free_udp_port()
        self.instance = random.randint(20, 90)      # its other ports (RC in, sim) away from other instances
        self.workdir: Path | None = None
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> SitlProcess:
        self.workdir = Path(tempfile.mkdtemp(prefix="aerial_loc_sitl_"))
        extra = self.workdir / "extra.parm"
        extra.write_text("".join(f"{k} {v}\n" for k, v in self.params.items()))
        self.log = open(self.workdir / "sitl.log", "wb")   # noqa: SIM115 (closed in __exit__)
        # SITL binds ports of its own from its instance number (TCP 5760 + 10 I for the serial ports it serves,
        # UDP 5501 + 10 I for RC input) and exits at once when one is taken, e.g. by another SITL that drew the
        # same instance (seen: "SITL did not speak within 60 s"): draw again while it exits that way
        for attempt in range(6):
            start = (self.workdir / "sitl.log").stat().st_size
            cmd = [str(self.binary), "--model", self.model, "--speedup", f"{self.speedup:g}", "--home", self.home,
                   "--defaults", f"{self.defaults},{extra}", "--wipe", "-I", str(self.instance),
                   "--serial0", f"udpclient:127.0.0.1:{self.monitor_port}",
                   "--serial1", f"udpclient:127.0.0.1:{self.bridge_port}"]
            self.proc = subprocess.Popen(cmd, cwd=self.workdir, stdout=self.log, stderr=subprocess.STDOUT,
                                         start_new_session=True, preexec_fn=_die_with_parent)
            try:
                self.proc.wait(1.0)          # a bind failure ends it within milliseconds
            except subprocess.TimeoutExpired:
                return self
            out = (self.workdir / "sitl.log").read_bytes()[start:].decode(errors="replace")    # this start's
            if "bind failed" not in out or attempt == 5:
                self.__exit__()
                raise AerialLocError(f"SITL ({self.binary.name}) exited at start (code {self.proc.returncode}): "
                                     f"{out[-600:]}")
            self.instance = random.randint(20, 90)
        return self

    def stop(self) -> None:
        """End SITL (its process group); idempotent. Its dataflash log stays until the context exits."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)

    @property
    def dataflash_log(self) -> Path | None:
        """The newest dataflash log SITL wrote (logs/NNNNNNNN.BIN in its working folder), None if none."""
        logs = sorted((self.workdir / "logs").glob("*.BIN")) if self.workdir is not None else []
        return logs[-1] if logs else None

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.log.close()
        if self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)


@dataclass
class Track:
    """What the monitor recorded: (monotonic time, lat, lon, alt) of the truth and of the EKF, and events."""

    truth: list = field(default_factory=list)
    ekf: list = field(default_factory=list)
    texts: list = field(default_factory=list)
    ekf_flags: list = field(default_factory=list)
    clock: list = field(default_factory=list)         # (time, SITL's boot seconds) from GLOBAL_POSITION_INT
    reached: list = field(default_factory=list)
    acks: list = field(default_factory=list)          # (time, command, result) of COMMAND_ACK
    gps_fix: list = field(default_factory=list)       # (time, fix_type) of GPS_RAW_INT
    armed: bool = False
    mode: str = ""
    relative_alt_m: float = 0.0


class Monitor:
    """SERIAL0: streams requested at start, a reader thread recording truth (SIM_STATE), the EKF
    (GLOBAL_POSITION_INT), EKF_STATUS_REPORT, STATUSTEXT, GPS_RAW_INT times; commands on the same link."""

    def __init__(self, port: int) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="ardupilotmega",
                                               source_system=250)
        self.track = Track()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lock = threading.Lock()

    def start(self, timeout_s: float = 60.0) -> None:
        if self.conn.wait_heartbeat(timeout=timeout_s) is None:
            raise AerialLocError(f"SITL did not speak within {timeout_s:.0f} s")
        m = self.conn.mav
        for msg_id, hz in ((108, 10), (33, 10), (193, 4), (24, 10), (0, 1), (46, 1)):  # SIM_STATE, GPI, EKF...
            m.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msg_id, 1e6 / hz,
                                0, 0, 0, 0, 0)
        self._thread = threading.Thread(target=self._read, name="sitl-monitor", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        while not self._stop.is_set():
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is not None:
                self._record(msg)

    def _record(self, msg) -> None:
        """Keep what the track needs from one message (the reader thread's, or the mission upload's)."""
        now = time.monotonic()
        kind = msg.get_type()
        with self.lock:
            t = self.track
            if kind == "SIM_STATE" and (msg.lat_int or msg.lon_int):
                t.truth.append((now, msg.lat_int / 1e7, msg.lon_int / 1e7, float(msg.alt)))
            elif kind == "GLOBAL_POSITION_INT":
                t.clock.append((now, msg.time_boot_ms / 1000.0))
                if msg.lat or msg.lon:
                    t.ekf.append((now, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0))
                    t.relative_alt_m = msg.relative_alt / 1000.0
            elif kind == "EKF_STATUS_REPORT":
                t.ekf_flags.append((now, int(msg.flags)))
            elif kind == "STATUSTEXT":
                t.texts.append((now, msg.text))
            elif kind == "COMMAND_ACK":
                t.acks.append((now, int(msg.command), int(msg.result)))
            elif kind == "GPS_RAW_INT":
                t.gps_fix.append((now, int(msg.fix_type)))
            elif kind == "MISSION_ITEM_REACHED" and msg.seq != 65535 and msg.seq not in t.reached:
                t.reached.append(int(msg.seq))     # (ArduPilot repeats it; 65535: none reached yet)
            elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
                t.armed = bool(msg.base_mode & mavutil.mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
                t.mode = mavutil.mode_string_v10(msg)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2)
        self.conn.close()

    # -- commands -------------------------------------------------------------------------------------------
    def set_mode(self, mode: str) -> None:
        self.conn.set_mode(self.conn.mode_mapping()[mode])

    def arm(self) -> None:
        self.conn.mav.command_long_send(1, 1, mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)

    def set_source_set(self, source_set: int) -> None:
        """The EKF's active source set (1..3, EK3_SRCn_*): MAV_CMD_SET_EKF_SOURCE_SET."""
        self.conn.mav.command_long_send(1, 1, MAV_CMD_SET_EKF_SOURCE_SET, 0, source_set, 0, 0, 0, 0, 0, 0)

    def set_param(self, name: str, value: float) -> None:
        self.conn.mav.param_set_send(1, 1, name.encode(), float(value), mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

    def upload_mission(self, items: list[tuple[int, float, float, float, float]], timeout_s: float = 20.0) -> None:
        """Items (command, lat, lon, alt relative to home, param1); item 0 is home (overwritten by the
        autopilot)."""
        mav = mavutil.mavlink
        frame = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        full = [(mav.MAV_CMD_NAV_WAYPOINT, 0.0, 0.0, 0.0, 0.0)] + items
        self._stop.set()
        self._thread.join(2)          # the mission protocol reads the link itself
        try:
            self.conn.mav.mission_count_send(1, 1, len(full), mav.MAV_MISSION_TYPE_MISSION)
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                # everything else is recorded as the reader would (a filtered read dropped the STATUSTEXT
                # "EKF3 IMU0 is using GPS" that came during an upload)
                msg = self.conn.recv_match(blocking=True, timeout=1.0)
                if msg is None:
                    continue
                if msg.get_type() not in ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"):
                    self._record(msg)
                    continue
                if msg.get_type() == "MISSION_ACK":
                    if msg.type != mav.MAV_MISSION_ACCEPTED:
                        raise AerialLocError(f"SITL refused the mission (MISSION_ACK type {msg.type})")
                    return
                cmd, lat, lon, alt, param1 = full[msg.seq]
                self.conn.mav.mission_item_int_send(1, 1, msg.seq, frame, cmd, 0, 1, param1, 0, 0, 0,
                                                    int(lat * 1e7), int(lon * 1e7), alt,
                                                    mav.MAV_MISSION_TYPE_MISSION)
            raise AerialLocError("SITL did not acknowledge the mission upload")
        finally:
            self._stop.clear()
            self._thread = threading.Thread(target=self._read, name="sitl-monitor", daemon=True)
            self._thread.start()

    def wait(self, predicate, timeout_s: float, what: str) -> None:
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self.lock:
                if predicate(self.track):
                    return
            time.sleep(0.1)
        with self.lock:
            texts = [t for _, t in self.track.texts[-8:]]
        raise AerialLocError(f"SITL: timed out after {timeout_s:.0f} s waiting for {what}; last messages: {texts}")


def sim_clock(pairs: list[tuple[float, float]]):
    """Monotonic seconds -> SITL's seconds since boot, from (arrival, time_boot_ms / 1000) pairs: linear between
    them, extended at the ends at the rate measured over them."""
    if len(pairs) < 2:
        raise AerialLocError("SITL: too few GLOBAL_POSITION_INT messages to read its clock")
    mono, sim = (np.asarray(v, dtype=float) for v in zip(*pairs, strict=True))
    rate = (sim[-1] - sim[0]) / max(1e-9, mono[-1] - mono[0])

    def to_sim(t: float) -> float:
        if t < mono[0]:
            return float(sim[0] + (t - mono[0]) * rate)
        if t > mono[-1]:
            return float(sim[-1] + (t - mono[-1]) * rate)
        return float(np.interp(t, mono, sim))
    return to_sim


def read_dataflash(path: str | os.PathLike, gps_instance: int = 0) -> dict[str, list]:
    """What SITL logged, on its own clock (TimeUS as seconds since boot): the truth (SIM), the EKF's position
    (POS), each as (t, lat, lon, alt AMSL), and the update intervals of GPS ``gps_instance`` (0 = GPS1) (t,
    GPA.Delta ms: the time between its last two updates as ArduPilot stamps them; over 245 ms it marks the GPS
    unhealthy; the first is skipped: it has no update before it, ArduPilot logs the time since boot or a wrapped
    value there), and EKF3's own horizontal position variance (t, XKV1.V07 + V08 of its first core, m^2: the
    north and east position states' variances)."""
    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(path), zero_time_base=True)
    out: dict[str, list] = {"truth": [], "ekf": [], "gps_delta_ms": [], "ekf_var_m2": []}
    first_gpa = True
    while (m := log.recv_match(type=["SIM", "POS", "GPA", "XKV1"])) is not None:
        t, kind = m.TimeUS / 1e6, m.get_type()
        if kind == "XKV1":
            if m.C == 0:
                out["ekf_var_m2"].append((t, float(m.V07) + float(m.V08)))
        elif kind == "GPA":
            if getattr(m, "I", 0) == gps_instance:
                if first_gpa:
                    first_gpa = False
                else:
                    out["gps_delta_ms"].append((t, int(m.Delta)))
        else:
            out["truth" if kind == "SIM" else "ekf"].append((t, float(m.Lat), float(m.Lng), float(m.Alt)))
    return out


def timed_horizontal_errors(truth: list, ekf: list, max_gap_s: float = 0.3) -> list[tuple[float, float]]:
    """(time, EKF minus truth in metres) for each EKF sample, the truth interpolated linearly at its time
    between the two samples around it (at most ``max_gap_s`` apart); samples outside the truth's span skipped."""
    import bisect

    times = [t[0] for t in truth]
    out = []
    for t, lat, lon, _ in ekf:
        i = bisect.bisect_left(times, t)
        if i == 0 or i >= len(truth):
            if i < len(truth) and times[i] == t:
                tl, tn = truth[i][1], truth[i][2]
            else:
                continue
        else:
            (ta, la, na, _), (tb, lb, nb, _) = truth[i - 1], truth[i]
            if tb - ta > max_gap_s:
                continue
            w = (t - ta) / (tb - ta) if tb > ta else 0.0
            tl, tn = la + w * (lb - la), na + w * (nb - na)
        out.append((t, _distance_m((t, lat, lon), (t, tl, tn))))
    return out


def _distance_m(a: tuple, b: tuple) -> float:
    """Horizontal distance between two (time, lat, lon, ...) rows, metres (equirectangular)."""
    dn = math.radians(a[1] - b[1]) * EARTH_RADIUS_M
    de = math.radians(a[2] - b[2]) * EARTH_RADIUS_M * math.cos(math.radians(b[1]))
    return math.hypot(dn, de)


def horizontal_errors_m(truth: list, ekf: list) -> list[float]:
    """EKF minus truth, metres, the truth interpolated at each EKF sample's time (``timed_horizontal_errors``)."""
    return [e for _, e in timed_horizontal_errors(truth, ekf)]


def offset_latlon(lat: float, lon: float, east_m: float, north_m: float) -> tuple[float, float]:
    return (lat + math.degrees(north_m / EARTH_RADIUS_M),
            lon + math.degrees(east_m / (EARTH_RADIUS_M * math.cos(math.radians(lat)))))


def _plan(vehicle: str, database: Any, lat0: float, lon0: float, leg_m: float, altitude_m: float,
          camera_min_alt_m: float = 40.0) -> list:
    """Mission items (command, lat, lon, alt above home, param1). Copter: take off at home, a leg east and back,
    RTL (lands). Plane: take off north (home in the map's south) to half the loop's altitude (at least 1.5 x the
    camera's lowest: the agent's first fixes, from the scenario's prior, come during the climb), a rectangular
    loop 300 m inside the map's edges at ``altitude_m`` (camera footprint and turns stay on the map), then a
    landing sequence: DO_LAND_START, an approach point north over the map at ``PLANE_APPROACH_ALT_M``
    and NAV_LAND at home heading south (``PLANE_GLIDE_M`` of final: the vision fix down to ``camera_min_alt_m``,
    dead reckoning below)."""
    mav = mavutil.mavlink
    if vehicle == "copter":
        return [(mav.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, altitude_m, 0.0),
                (mav.MAV_CMD_NAV_WAYPOINT, *offset_latlon(lat0, lon0, leg_m, 0.0), altitude_m, 0.0),
                (mav.MAV_CMD_NAV_WAYPOINT, *offset_latlon(lat0, lon0, 5.0, 0.0), altitude_m, 0.0),
                (mav.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0, 0.0, 0.0, 0.0)]
    w, h, m = database.width_m, database.height_m, 300.0

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


#: the plane's final: from this height above home, this far north of it (a 5.7 deg glide), south to touchdown
PLANE_APPROACH_ALT_M = 100.0
PLANE_GLIDE_M = 1000.0


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
    SITL's wind (speed m/s, direction it blows from, degrees; SIM_WIND_SPD / SIM_WIND_DIR), none by default."""
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.mavlink import cli as mav_cli

    missions = MISSIONS if vehicle == "copter" else PLANE_MISSIONS
    if mission not in missions:
        raise ConfigError(f"--mission {mission!r} for --vehicle {vehicle}: use one of {', '.join(missions)}")
    spec = missions[mission]
    env = gym.make(scenario)
    env.reset(seed=seed)
    database = env.unwrapped.database
    scenario_alt_m = float(env.unwrapped.scenario.flight.altitude_m)
    altitude_m = scenario_alt_m if altitude_m is None else altitude_m
    # the camera gives the agent frames within its own altitude range (follow mode), e.g. template-ncc down to 40 m
    camera_min_alt_m = float(make_agent(agent).altitude_range_m(env.unwrapped.briefing)[0])
    home_xy = None if vehicle == "copter" else (database.width_m / 2.0, 250.0)
    home = sitl_home(database, ground_amsl_m, 0.0, home_xy)
    env.close()
    lat0, lon0 = (float(v) for v in home.split(",")[:2])
    items = _plan(vehicle, database, lat0, lon0, leg_m, altitude_m, camera_min_alt_m)
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
        bridge = threading.Thread(target=lambda: result.setdefault("rc", mav_cli.run(
            args, out=log or open(os.devnull, "w"), should_stop=stop.is_set, on_step=on_step)), daemon=True)
        bridge.start()
        monitor = Monitor(sitl.monitor_port)
        try:
            monitor.start()
            monitor.wait(lambda t: any(spec.ready_text in x for _, x in t.texts), 120 / speedup, spec.ready_what)
            t_fix = time.monotonic()
            monitor.upload_mission(items)
            end_arm = time.monotonic() + 60 / speedup
            while not monitor.track.armed:
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


def touchdown(truth: list, ekf: list, steps: list, land_at: tuple[float, float], t_landing: float | None,
              ekf_var_m2: list | None = None) -> dict:
    """Where and how the plane came down, on SITL's clock: the first truth sample of the landing sequence
    (from ``t_landing``) within 0.5 m of the ground height (the truth's median before take-off), the distance
    from there to the NAV_LAND point (along the final, south, and across it), the EKF's error at that moment and
    the horizontal accuracy it claimed (sqrt of its north + east position variances, ``ekf_var_m2``: (t, m^2)),
    where the vehicle stopped; the last camera frame before it (altitude, seconds of dead reckoning)."""
    if not truth or t_landing is None:
        return {}
    ground = float(np.median([r[3] for r in truth[:50]]))
    down = next((r for r in truth if r[0] >= t_landing and r[3] <= ground + 0.5), None)
    if down is None:
        return {"landed": False}
    t_down = down[0]
    north = math.radians(down[1] - land_at[0]) * EARTH_RADIUS_M
    east = math.radians(down[2] - land_at[1]) * EARTH_RADIUS_M * math.cos(math.radians(land_at[0]))
    at_down = [e for t, e in timed_horizontal_errors(truth, ekf) if abs(t - t_down) <= 0.5]
    rest = truth[-1]
    cam = [s for s in steps if s[1] == "camera" and s[0] <= t_down]
    var = [v for t, v in (ekf_var_m2 or []) if t <= t_down]
    return {"landed": True, "t_s": t_down, "distance_m": math.hypot(north, east),
            "along_m": -north, "cross_m": east,     # the final runs south: along = beyond the point, cross = east
            "ekf_error_m": float(at_down[len(at_down) // 2]) if at_down else math.nan,
            "ekf_sigma_m": math.sqrt(max(0.0, var[-1])) if var else math.nan,
            "rest_from_land_point_m": _distance_m(rest, (0.0, *land_at)),
            "last_fix_alt_m": float(cam[-1][5]) if cam else math.nan,
            "dead_reckoning_s": t_down - cam[-1][0] if cam else math.nan}


def vision_fix_s(steps: list, after: float | None = None) -> float:
    """Seconds the bridge sent camera fixes (sum of step intervals, each at most 1 s, ending on a camera step)."""
    total = 0.0
    for a, b in zip(steps, steps[1:], strict=False):
        t0, t1, src = a[0], b[0], b[1]
        if src == "camera" and (after is None or t0 >= after):
            total += min(1.0, t1 - t0)
    return total


def summary(record: dict) -> dict:
    """The figures the issue asks for, from a mission record."""
    e = np.asarray(record["horizontal_errors_m"], dtype=float)
    g = np.asarray(record["gps_gaps_ms"], dtype=float)
    legs = np.asarray(record["leg_errors_m"], dtype=float)
    steps = record.get("steps", [])
    est = np.asarray([s[2] for s in steps if s[1] == "camera" and s[2] is not None], dtype=float)
    frames = [s[0] for s in steps if s[1] == "camera"]
    # between consecutive camera frames (not across the camera out of range: pad or lost steps between)
    dt = np.asarray([b[0] - a[0] for a, b in zip(steps, steps[1:], strict=False)
                     if a[1] == "camera" and b[1] == "camera"], dtype=float)
    frame_intervals = ({"median": float(np.median(dt)), "p95": float(np.percentile(dt, 95)), "max": float(dt.max())}
                       if dt.size else {})
    events = [x for _, x in record["texts"] if any(k in x for k in ("ailsafe", "EKF variance", "Glitch",
                                                                     "stopped aiding", "is using", "source"))]
    out = {"mission": record.get("mission", "gps-input"),
           "vehicle": record.get("vehicle", "copter"), "wind": record.get("wind"),
           # copter: the last waypoint reached (then RTL landed: the run waits for the disarm); plane: touched down
           "mission_completed": (record.get("touchdown", {}).get("landed", False) if record.get("vehicle") == "plane"
                                 else record.get("last_wp", 3) in record["reached"]),
           "legs_ekf_rmse_m": float(np.sqrt(np.mean(legs ** 2))) if legs.size else math.nan,
           "legs_ekf_max_m": float(legs.max()) if legs.size else math.nan,
           "ekf_rmse_m": float(np.sqrt(np.mean(e ** 2))) if e.size else math.nan,
           "ekf_max_m": float(e.max()) if e.size else math.nan,
           "estimator_rmse_m": float(np.sqrt(np.mean(est ** 2))) if est.size else math.nan,
           "estimator_max_m": float(est.max()) if est.size else math.nan,
           # in SITL's seconds (the record's times are on SITL's clock)
           "vision_fix_s": vision_fix_s(steps, record.get("t_denied")),
           "fix_to_arm_s": record["fix_to_arm_s"], "flight_s": record["flight_s"],
           "speedup": record.get("speedup", 1.0), "speedup_achieved": record.get("speedup_achieved", math.nan),
           # how the agent kept up: camera frames and the intervals between them, SITL seconds
           "camera_frames": len(frames), "frame_interval_s": frame_intervals,
           "share_of_flight_with_absolute_position": (sum(1 for _, f in record["ekf_flags"] if f & 16)
                                                      / max(1, len(record["ekf_flags"]))),
           "ekf_flags_seen": sorted({f for _, f in record["ekf_flags"]}),
           "gps_gaps_over_245ms": int((g > 245).sum()), "gps_gap_max_ms": float(g.max()) if g.size else math.nan,
           "gps_gap_max_before_fix_ms": float(record.get("gps_gap_max_before_fix_ms", math.nan)),
           "events": list(dict.fromkeys(events))}
    if record.get("acquisition_errors_m"):
        out["acquisition_ekf_max_m"] = float(max(record["acquisition_errors_m"]))
    if record.get("touchdown"):
        out["touchdown"] = record["touchdown"]
    if record.get("t_denied") is not None:     # the EKF after the GNSS was switched off
        t_d = record["t_denied"]
        after = [r for r in record["truth"] if r[0] >= t_d], [r for r in record["ekf"] if r[0] >= t_d]
        d = np.asarray(horizontal_errors_m(*after), dtype=float)
        out["denied_ekf_rmse_m"] = float(np.sqrt(np.mean(d ** 2))) if d.size else math.nan
        out["denied_ekf_max_m"] = float(d.max()) if d.size else math.nan
    return out


def write_outputs(record: dict, out_dir: Path) -> list[Path]:
    """errors.csv (time, EKF, error), messages.txt (STATUSTEXT), summary.json and, with matplotlib, track.png
    (true and EKF tracks, estimates; errors over time)."""
    import csv

    out_dir.mkdir(parents=True, exist_ok=True)
    import json

    paths = [out_dir / "errors.csv", out_dir / "messages.txt", out_dir / "summary.json"]
    paths[2].write_text(json.dumps(summary(record), indent=1) + "\n")
    truth, ekf = record["truth"], record["ekf"]
    t0 = truth[0][0] if truth else 0.0
    lines = [f"{t - t0:8.1f} s  {x}" for t, x in record["texts"]]
    if record.get("t_denied") is not None:
        lines.append(f"{record['t_denied'] - t0:8.1f} s  [{record.get('denial', 'SIM_GPS1_ENABLE 0')}]")
    paths[1].write_text("\n".join(sorted(lines, key=lambda x: float(x.split()[0]))) + "\n")
    with open(paths[0], "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "ekf_lat_deg", "ekf_lon_deg", "ekf_alt_m", "horizontal_error_m"])
        err_at = dict(record.get("timed_errors", []))
        for t, lat, lon, alt in ekf:
            if t in err_at:
                w.writerow([f"{t - t0:.2f}", f"{lat:.8f}", f"{lon:.8f}", f"{alt:.2f}", f"{err_at[t]:.3f}"])
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return paths
    if truth:
        lat0, lon0 = truth[0][1], truth[0][2]

        def en(rows):
            return ([math.radians(r[2] - lon0) * EARTH_RADIUS_M * math.cos(math.radians(lat0)) for r in rows],
                    [math.radians(r[1] - lat0) * EARTH_RADIUS_M for r in rows])

        fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.6), gridspec_kw={"width_ratios": [1.4, 1]})
        ax.plot(*en(truth), "g-", lw=2, label="SITL truth")
        ax.plot(*en(ekf), "r--", lw=1.2, label="EKF")
        if record.get("estimates"):
            ax.plot(*en(record["estimates"]), "b.", ms=2, label="estimates (camera)")
        ax.set_xlabel("east of take-off, m")
        ax.set_ylabel("north, m")
        ax.set_title(f"{record.get('vehicle', 'copter')}, {record.get('mission', 'gps-input')}: track", fontsize=9)
        ax.legend(fontsize=7)
        timed = record.get("timed_errors", [])
        ax2.plot([t - t0 for t, _ in timed], [e for _, e in timed], "r-", lw=1, label="EKF vs truth")
        cam = [s for s in record.get("steps", []) if s[1] == "camera" and s[2] is not None]
        if cam:
            ax2.plot([s[0] - t0 for s in cam], [s[2] for s in cam], "b.", ms=2, label="estimator vs truth")
        if record.get("t_denied") is not None:
            ax2.axvline(record["t_denied"] - t0, color="k", lw=0.8, ls=":", label="GNSS off")
        ax2.set_yscale("log")
        ax2.set_xlabel("time since arming, s")
        ax2.set_ylabel("horizontal error, m")
        ax2.legend(fontsize=7)
        fig.savefig(out_dir / "track.png", dpi=90, bbox_inches="tight")
        plt.close(fig)
        paths.append(out_dir / "track.png")
    return paths


def main(argv: list[str] | None = None) -> int:
    import argparse
    import json
    import sys

    ap = argparse.ArgumentParser(prog="aerial-loc sitl", description="fly an ArduPilot SITL mission on the vision "
                                 "fix: SITL on loopback at the map, the bridge with the camera at SITL's truth")
    ap.add_argument("--vehicle", default="copter", choices=tuple(VEHICLES))
    ap.add_argument("--scenario", default=None, help="default: AerialLoc/Small-v1 (copter), "
                    "AerialLoc/PaperShadows-v1 (plane: 1.2 x 1.4 km at 200 m, room for a fixed wing's loop)")
    ap.add_argument("--agent", default="template-ncc")
    ap.add_argument("--mission", default="gps-input", choices=tuple(MISSIONS),
                    help="gps-input: GPS_INPUT as GPS1; external-nav (copter): VISION_POSITION_ESTIMATE, no GNSS; "
                         "gnss-denial: SITL's GPS, switched off in flight; copter: EKF to ExternalNav (source set "
                         "2); plane: the vision fix as GPS2, the autopilot switches to it (GPS_AUTO_SWITCH 4)")
    ap.add_argument("--ground-amsl-m", type=float, default=30.0, help="SITL's home altitude = the map's ground")
    ap.add_argument("--sitl-bin", default=None, help=f"folder of the SITL binaries (default {DEFAULT_SITL_DIR})")
    ap.add_argument("--speedup", type=float, default=1.0, help="SITL's --speedup; the camera follows SITL's clock "
                    "(frame times and odometry scaled by it): keep it where SITL and the agent keep pace")
    ap.add_argument("--wind", default=None, metavar="SPEED,FROM_DEG",
                    help="SITL's wind: speed m/s and the direction it blows from, degrees (e.g. 5,270); default none")
    ap.add_argument("--out", default="sitl-run", help="folder for errors.csv and track.png")
    args = ap.parse_args(argv)
    try:
        wind = None if args.wind is None else tuple(float(v) for v in args.wind.split(","))
    except ValueError:
        wind = ()
    if wind is not None and (len(wind) != 2 or not 0 <= wind[0] <= 30 or not math.isfinite(wind[1])):
        ap.error(f"--wind {args.wind!r}: give SPEED,FROM_DEG with the speed in 0..30 m/s and the direction the wind "
                 f"blows from in degrees, e.g. 5,270")
    scenario = args.scenario or ("AerialLoc/Small-v1" if args.vehicle == "copter" else "AerialLoc/PaperShadows-v1")
    record = fly_mission(scenario, args.agent, ground_amsl_m=args.ground_amsl_m, vehicle=args.vehicle,
                         mission=args.mission, speedup=args.speedup, sitl_dir=args.sitl_bin, log=sys.stdout,
                         wind=wind)
    paths = write_outputs(record, Path(args.out))
    print(json.dumps(summary(record), indent=1))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


__all__ = ["SitlProcess", "Monitor", "find_sitl", "sitl_home", "horizontal_errors_m", "timed_horizontal_errors",
           "fly_mission", "summary", "write_outputs", "main", "COPTER_GPS_INPUT", "COPTER_EXTERNAL_NAV",
           "COPTER_GNSS_DENIAL", "MISSIONS", "Mission", "vision_fix_s", "sim_clock", "read_dataflash"]
