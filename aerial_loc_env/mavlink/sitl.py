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

from pymavlink import mavutil

from ..errors import AerialLocError, ConfigError
from .selfcheck import free_udp_port

VEHICLES = {"copter": ("arducopter", "+", "copter.parm"), "plane": ("arduplane", "plane", "plane.parm")}
DEFAULT_SITL_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "sitl"

# GPS_INPUT (ArduPilot's MAVLink GPS): GPS1 from the bridge, vertical speed not from the GPS, 100 m RTL
COPTER_GPS_INPUT = {"GPS1_TYPE": 14, "EK3_SRC1_VELZ": 0, "AUTO_OPTIONS": 7, "WPNAV_SPEED": 1000,
                    "WPNAV_SPEED_UP": 500, "RTL_ALT": 10000, "RTL_ALT_FINAL": 0, "LAND_SPEED_HIGH": 500,
                    "WP_YAW_BEHAVIOR": 1}   # nose first, RTL too: the env's odometry is a unicycle's


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


def sitl_home(orthomap: Any, ground_amsl_m: float, heading_deg: float = 0.0) -> str:
    """SITL's ``--home`` (LAT,LON,ALT,HEADING) at the map's centre: start the autopilot where the map is."""
    lat, lon = (float(v) for v in orthomap.world_to_latlon(orthomap.width_m / 2.0, orthomap.height_m / 2.0))
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
        cmd = [str(self.binary), "--model", self.model, "--speedup", f"{self.speedup:g}", "--home", self.home,
               "--defaults", f"{self.defaults},{extra}", "--wipe", "-I", str(self.instance),
               "--serial0", f"udpclient:127.0.0.1:{self.monitor_port}",
               "--serial1", f"udpclient:127.0.0.1:{self.bridge_port}"]
        self.log = open(self.workdir / "sitl.log", "wb")   # noqa: SIM115 (closed in __exit__)
        self.proc = subprocess.Popen(cmd, cwd=self.workdir, stdout=self.log, stderr=subprocess.STDOUT,
                                     start_new_session=True, preexec_fn=_die_with_parent)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)
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
    gps_gaps_ms: list = field(default_factory=list)
    reached: list = field(default_factory=list)
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
        self._last_gps_ms: int | None = None
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
            if msg is None:
                continue
            now = time.monotonic()
            kind = msg.get_type()
            with self.lock:
                t = self.track
                if kind == "SIM_STATE" and (msg.lat_int or msg.lon_int):
                    t.truth.append((now, msg.lat_int / 1e7, msg.lon_int / 1e7, float(msg.alt)))
                elif kind == "GLOBAL_POSITION_INT" and (msg.lat or msg.lon):
                    t.ekf.append((now, msg.lat / 1e7, msg.lon / 1e7, msg.alt / 1000.0))
                    t.relative_alt_m = msg.relative_alt / 1000.0
                elif kind == "EKF_STATUS_REPORT":
                    t.ekf_flags.append((now, int(msg.flags)))
                elif kind == "STATUSTEXT":
                    t.texts.append((now, msg.text))
                elif kind == "GPS_RAW_INT" and msg.fix_type >= 3:
                    ms = msg.time_usec // 1000
                    if self._last_gps_ms is not None and ms > self._last_gps_ms:
                        t.gps_gaps_ms.append(ms - self._last_gps_ms)
                    self._last_gps_ms = ms
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

    def set_param(self, name: str, value: float) -> None:
        self.conn.mav.param_set_send(1, 1, name.encode(), float(value), mavutil.mavlink.MAV_PARAM_TYPE_REAL32)

    def upload_mission(self, items: list[tuple[int, float, float, float]], timeout_s: float = 20.0) -> None:
        """Items (command, lat, lon, alt relative to home); item 0 is home (overwritten by the autopilot)."""
        mav = mavutil.mavlink
        frame = mav.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        full = [(mav.MAV_CMD_NAV_WAYPOINT, 0.0, 0.0, 0.0)] + items
        self._stop.set()
        self._thread.join(2)          # the mission protocol reads the link itself
        try:
            self.conn.mav.mission_count_send(1, 1, len(full), mav.MAV_MISSION_TYPE_MISSION)
            end = time.monotonic() + timeout_s
            while time.monotonic() < end:
                msg = self.conn.recv_match(type=["MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"],
                                           blocking=True, timeout=1.0)
                if msg is None:
                    continue
                if msg.get_type() == "MISSION_ACK":
                    if msg.type != mav.MAV_MISSION_ACCEPTED:
                        raise AerialLocError(f"SITL refused the mission (MISSION_ACK type {msg.type})")
                    return
                cmd, lat, lon, alt = full[msg.seq]
                self.conn.mav.mission_item_int_send(1, 1, msg.seq, frame, cmd, 0, 1, 0, 0, 0, 0,
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


def horizontal_errors_m(truth: list, ekf: list) -> list[float]:
    """EKF minus truth, metres, each EKF sample against the truth sample nearest in time (within 0.15 s)."""
    import bisect

    times = [t[0] for t in truth]
    out = []
    for t, lat, lon, _ in ekf:
        i = bisect.bisect_left(times, t)
        best = min((j for j in (i - 1, i) if 0 <= j < len(truth)), key=lambda j: abs(times[j] - t), default=None)
        if best is None or abs(times[best] - t) > 0.15:
            continue
        _, tl, tn, _ = truth[best]
        dn = math.radians(lat - tl) * 6_371_008.8
        de = math.radians(lon - tn) * 6_371_008.8 * math.cos(math.radians(tl))
        out.append(math.hypot(dn, de))
    return out





def offset_latlon(lat: float, lon: float, east_m: float, north_m: float) -> tuple[float, float]:
    return (lat + math.degrees(north_m / 6_371_008.8),
            lon + math.degrees(east_m / (6_371_008.8 * math.cos(math.radians(lat)))))


def fly_copter_mission(scenario: str, agent: str, *, ground_amsl_m: float, leg_m: float = 80.0,
                       altitude_m: float = 100.0, speedup: float = 1.0, sitl_dir=None, seed: int = 0,
                       timeout_s: float = 300.0, log=None) -> dict:
    """ArduCopter on the vision fix (GPS_INPUT, GPS1_TYPE 14): arm in AUTO on the fix, take off, fly a leg east
    and back over the map, RTL and land; the camera follows SITL's truth. Returns the monitor's record."""
    import gymnasium as gym

    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)

    from . import cli as mav_cli

    env = gym.make(scenario)
    home = sitl_home(env.unwrapped.database, ground_amsl_m)
    env.close()
    lat0, lon0 = (float(v) for v in home.split(",")[:2])
    stop = threading.Event()
    result: dict = {}
    with SitlProcess("copter", home, COPTER_GPS_INPUT, speedup=speedup, sitl_dir=sitl_dir) as sitl:
        args = mav_cli.build_parser().parse_args([
            "--scenario", scenario, "--agent", agent, "--follow", "--seed", str(seed),
            "--ground-amsl-m", str(ground_amsl_m), "--connect", f"udpin:127.0.0.1:{sitl.bridge_port}",
            "--rate-hz", str(10.0 * speedup), *([] if log is not None else ["--quiet"])])
        bridge = threading.Thread(target=lambda: result.setdefault("rc", mav_cli.run(
            args, out=log or open(os.devnull, "w"), should_stop=stop.is_set)), daemon=True)
        bridge.start()
        monitor = Monitor(sitl.monitor_port)
        try:
            monitor.start()
            monitor.wait(lambda t: any("is using GPS" in x for _, x in t.texts), 120 / speedup,
                         "the EKF to use the vision fix (GPS_INPUT)")
            t_fix = time.monotonic()
            east = offset_latlon(lat0, lon0, leg_m, 0.0)
            back = offset_latlon(lat0, lon0, 5.0, 0.0)
            mav = mavutil.mavlink
            monitor.upload_mission([(mav.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, altitude_m),
                                    (mav.MAV_CMD_NAV_WAYPOINT, *east, altitude_m),
                                    (mav.MAV_CMD_NAV_WAYPOINT, *back, altitude_m),
                                    (mav.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0.0, 0.0, 0.0)])
            end_arm = time.monotonic() + 60 / speedup
            while not monitor.track.armed:
                if time.monotonic() > end_arm:
                    raise AerialLocError(f"SITL: could not arm in 60 s; last messages: "
                                         f"{[x for _, x in monitor.track.texts[-8:]]}")
                monitor.set_mode("AUTO")
                monitor.arm()
                time.sleep(1.0)
            t_armed = time.monotonic()
            monitor.wait(lambda t: 3 in t.reached, timeout_s / speedup, "the mission's last waypoint")
            monitor.wait(lambda t: not t.armed, timeout_s / speedup, "landing and disarming after RTL")
            t_end = time.monotonic()
        finally:
            stop.set()
            bridge.join(10)
            monitor.stop()
        with monitor.lock:
            tr = monitor.track
            flight = [s for s in tr.truth if t_armed <= s[0] <= t_end]
            ekf = [s for s in tr.ekf if t_armed <= s[0] <= t_end]
            flags = [f for f in tr.ekf_flags if t_armed <= f[0] <= t_end]
            record = {"truth": flight, "ekf": ekf, "texts": list(tr.texts), "ekf_flags": flags,
                      "gps_gaps_ms": list(tr.gps_gaps_ms), "reached": list(tr.reached),
                      "fix_to_arm_s": t_armed - t_fix, "flight_s": t_end - t_armed, "bridge_rc": result.get("rc")}
    record["horizontal_errors_m"] = horizontal_errors_m(record["truth"], record["ekf"])
    # the AUTO legs on the vision fix: from the first waypoint to the start of RTL
    starts = {k: next((t for t, x in record["texts"] if x.startswith(f"Mission: {k}")), None) for k in (2, 4)}
    if starts[2] is not None and starts[4] is not None:
        legs = lambda rows: [r for r in rows if starts[2] <= r[0] <= starts[4]]   # noqa: E731
        record["leg_errors_m"] = horizontal_errors_m(legs(record["truth"]), legs(record["ekf"]))
        record["leg_flags"] = legs(record["ekf_flags"])
    else:
        record["leg_errors_m"], record["leg_flags"] = [], []
    return record


def summary(record: dict) -> dict:
    """The figures the issue asks for, from a mission record."""
    import numpy as np

    e = np.asarray(record["horizontal_errors_m"], dtype=float)
    g = np.asarray(record["gps_gaps_ms"], dtype=float)
    legs = np.asarray(record["leg_errors_m"], dtype=float)
    return {"mission_completed": 3 in record["reached"] and not record.get("armed_at_end", False),
            "legs_ekf_rmse_m": float(np.sqrt(np.mean(legs ** 2))) if legs.size else math.nan,
            "legs_ekf_max_m": float(legs.max()) if legs.size else math.nan,
            "ekf_rmse_m": float(np.sqrt(np.mean(e ** 2))) if e.size else math.nan,
            "ekf_max_m": float(e.max()) if e.size else math.nan,
            "fix_to_arm_s": record["fix_to_arm_s"], "flight_s": record["flight_s"],
            "share_of_flight_with_absolute_position": (sum(1 for _, f in record["ekf_flags"] if f & 16)
                                                       / max(1, len(record["ekf_flags"]))),
            "gps_gaps_over_245ms": int((g > 245).sum()), "gps_gap_max_ms": float(g.max()) if g.size else math.nan}


def write_outputs(record: dict, out_dir: Path) -> list[Path]:
    """errors.csv (time, truth, EKF, error) and, with matplotlib, track.png (true and EKF tracks)."""
    import csv

    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "errors.csv"]
    truth, ekf = record["truth"], record["ekf"]
    t0 = truth[0][0] if truth else 0.0
    with open(paths[0], "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "ekf_lat_deg", "ekf_lon_deg", "ekf_alt_m", "horizontal_error_m"])
        for (t, lat, lon, alt), err in zip(ekf, record["horizontal_errors_m"], strict=False):
            w.writerow([f"{t - t0:.2f}", f"{lat:.8f}", f"{lon:.8f}", f"{alt:.2f}", f"{err:.3f}"])
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return paths
    if truth:
        lat0, lon0 = truth[0][1], truth[0][2]

        def en(rows):
            return ([math.radians(r[2] - lon0) * 6_371_008.8 * math.cos(math.radians(lat0)) for r in rows],
                    [math.radians(r[1] - lat0) * 6_371_008.8 for r in rows])

        fig, ax = plt.subplots(figsize=(6, 5))
        ax.plot(*en(truth), "g-", label="SITL truth")
        ax.plot(*en(ekf), "r--", label="EKF (on the vision fix)")
        ax.set_xlabel("east of take-off, m")
        ax.set_ylabel("north, m")
        ax.set_aspect("equal")
        ax.legend()
        fig.savefig(out_dir / "track.png", dpi=100, bbox_inches="tight")
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
    ap.add_argument("--scenario", default="AerialLoc/Small-v0")
    ap.add_argument("--agent", default="template-ncc")
    ap.add_argument("--mission", default="gps-input", choices=("gps-input",))
    ap.add_argument("--ground-amsl-m", type=float, default=30.0, help="SITL's home altitude = the map's ground")
    ap.add_argument("--sitl-bin", default=None, help=f"folder of the SITL binaries (default {DEFAULT_SITL_DIR})")
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--out", default="sitl-run", help="folder for errors.csv and track.png")
    args = ap.parse_args(argv)
    if args.vehicle != "copter":
        raise ConfigError("--vehicle plane: the plane mission is not built yet (issue 14); use --vehicle copter")
    record = fly_copter_mission(args.scenario, args.agent, ground_amsl_m=args.ground_amsl_m,
                                speedup=args.speedup, sitl_dir=args.sitl_bin, log=sys.stdout)
    paths = write_outputs(record, Path(args.out))
    print(json.dumps(summary(record), indent=1))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0

__all__ = ["SitlProcess", "Monitor", "find_sitl", "sitl_home", "horizontal_errors_m", "fly_copter_mission",
           "summary", "write_outputs", "main", "COPTER_GPS_INPUT"]
