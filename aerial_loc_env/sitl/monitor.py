"""The MAVLink monitor of SITL's SERIAL0: what the autopilot says and where its vehicle truly is, and commands.

A reader thread records the truth (SIM_STATE), the EKF (GLOBAL_POSITION_INT), EKF_STATUS_REPORT, STATUSTEXT,
COMMAND_ACK, GPS_RAW_INT and the mission's progress into a ``Track``; every wait also runs a ``watchdog`` (SITL's
process and the bridge alive), so that a death is reported at once, not as the timeout of what was awaited.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from pymavlink import mavutil

from aerial_loc_env.errors import AerialLocError

MAV_CMD_SET_EKF_SOURCE_SET = 42007     # ardupilotmega: param1 = source set 1..3


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
    modes: list = field(default_factory=list)         # (time, mode name) at each change of the flight mode
    armed: bool = False
    mode: str = ""
    relative_alt_m: float = 0.0


class Monitor:
    """SERIAL0: streams requested at start, a reader thread recording the ``Track``; commands on the same link.

    ``watchdog`` (no arguments) raises when what the flight depends on has died; every wait calls it.
    """

    def __init__(self, port: int, watchdog: Callable[[], None] | None = None) -> None:
        self.conn = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", dialect="ardupilotmega",
                                               source_system=250)
        self.track = Track()
        self.watchdog = watchdog or (lambda: None)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lock = threading.Lock()

    def start(self, timeout_s: float = 60.0) -> None:
        end = time.monotonic() + timeout_s
        while self.conn.wait_heartbeat(timeout=min(1.0, max(0.01, end - time.monotonic()))) is None:
            self.watchdog()
            if time.monotonic() >= end:
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
                mode = mavutil.mode_string_v10(msg)
                if mode != t.mode:
                    t.modes.append((now, mode))
                t.mode = mode

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
                self.watchdog()
                # everything else is recorded as the reader would (a filtered read would drop a STATUSTEXT
                # such as "EKF3 IMU0 is using GPS" arriving during the upload)
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

    def wait(self, predicate: Callable[[Track], bool], timeout_s: float, what: str) -> None:
        """Until ``predicate(track)`` holds; the watchdog's error at once, a timeout's after ``timeout_s``."""
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            with self.lock:
                if predicate(self.track):
                    return
            self.watchdog()
            time.sleep(0.1)
        self.watchdog()
        with self.lock:
            texts = [t for _, t in self.track.texts[-8:]]
        raise AerialLocError(f"SITL: timed out after {timeout_s:.0f} s waiting for {what}; last messages: {texts}")


def sim_clock(pairs: list[tuple[float, float]]) -> Callable[[float], float]:
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
