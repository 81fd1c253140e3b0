"""The MAVLink sender: a thread that streams the latest fix at a steady rate, as a vision companion computer.

Why a thread with absolute deadlines: ArduPilot declares a MAVLink GPS unhealthy after about 0.245 s without
GPS_INPUT, and the EKFs dislike jittery external-navigation timing, so the send rate must not depend on how
long the simulator or the estimator take. The sender emits whatever fix the slot holds, ageing it.
"""

from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import re
import threading
import time
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mavlink2

from aerial_loc_env.config import build_config, rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.mavlink import messages as msgs
from aerial_loc_env.mavlink.fix import FixPolicy, FixQuality, FixSlot, GeoOrigin, PoseFix, SlotItem, assess
from aerial_loc_env.mavlink.link import Endpoint, Link, parse_connection
from aerial_loc_env.mavlink.timebase import MonotonicClock, Schedule, SimClock, signing_timestamp

ARDUPILOT_GPS_TIMEOUT_S = 0.245   # AP_GPS marks a MAVLink GPS unhealthy after gaps longer than this
MIN_GPS_INPUT_RATE_HZ = 5.0
MIN_HEX_KEY_LOOKALIKE = 32        # an all-hex passphrase this long is a mistyped 64-digit key, not a passphrase
RECEIVE_POLL_S = 0.01            # following a simulator: its messages are read at least this often
MAX_CAPTURE_AGE_S = 2.0           # a fix's own time further back than this is not a capture time on the clock


@dataclass(frozen=True)
class SenderConfig:
    """What to send, where, how often, and as whom."""

    connect: str = "udpout:127.0.0.1:14550"
    messages: tuple[str, ...] = ("gps_input",)
    rate_hz: float = field(default=10.0, metadata=rng(0.0, 200.0, lo_open=True))
    heartbeat_hz: float = field(default=1.0, metadata=rng(0.0, 50.0, lo_open=True))
    system_id: int = field(default=1, metadata=rng(1, 255))
    component_id: int = field(default=mavlink2.MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY, metadata=rng(1, 255))
    target_system: int = field(default=0, metadata=rng(0, 255))      # origin/requests target; 0: all
    gps_id: int = field(default=0, metadata=rng(0, 255))             # GPS_INPUT.gps_id = the GPS instance
    gps_yaw: bool = False                                            # fill GPS_INPUT.yaw from the estimate
    odometry_frames: str = field(default="local_frd", metadata=rng(choices=tuple(msgs.ODOMETRY_FRAMES)))
    origin_period_s: float = field(default=5.0, metadata=rng(0.1, 3600.0))
    signing_key: str = field(default="", repr=False)                 # 64 hex digits or a passphrase (sha256)
    signing_link_id: int = field(default=0, metadata=rng(0, 255))
    reconnect_s: float = field(default=1.0, metadata=rng(0.05, 60.0))
    baud: int = field(default=57600, metadata=rng(1, 10_000_000))
    request_vehicle_hz: float = field(default=0.0, metadata=rng(0.0, 50.0))  # >0: request SIM_STATE (truth)
    # following a simulator (request_vehicle_hz > 0): its clock's rate (SITL --speedup); message times, the fix's
    # age and the truth's times run on the simulator's clock (SYSTEM_TIME), see timebase.SimClock
    sim_speedup: float = field(default=1.0, metadata=rng(0.1, 20.0))
    allow_slow_gps: bool = False                                      # permit GPS_INPUT below 5 Hz (replay)
    external_position_hz: float = field(default=1.0, metadata=rng(0.01, 50.0))  # the low-rate global fix

    def validate(self, where: str) -> None:
        bad = [m for m in self.messages if m not in msgs.MESSAGE_KINDS]
        if bad or not self.messages:
            raise ConfigError(f"{where}: field 'messages' = {list(self.messages)!r}: choose one or more of "
                              f"{', '.join(msgs.MESSAGE_KINDS)}")
        if "gps_input" in self.messages and self.rate_hz < MIN_GPS_INPUT_RATE_HZ and not self.allow_slow_gps:
            raise ConfigError(
                f"{where}: field 'rate_hz' = {self.rate_hz} is below {MIN_GPS_INPUT_RATE_HZ} Hz: ArduPilot "
                f"marks a MAVLink GPS unhealthy after {ARDUPILOT_GPS_TIMEOUT_S * 1000:.0f} ms without "
                "GPS_INPUT; raise the rate (or set allow_slow_gps)")
        parse_connection(self.connect, baud=self.baud, field=f"{where}: field 'connect'")
        signing_secret(self.signing_key, where)

    @property
    def endpoint(self) -> Endpoint:
        return parse_connection(self.connect, baud=self.baud)


def signing_secret(key: str, where: str = "signing_key") -> bytes | None:
    """32-byte secret from 64 hex digits, or sha256 of a passphrase (MAVProxy's ``signing setup``)."""
    if not key:
        return None
    if not isinstance(key, str):
        raise ConfigError(f"{where}: field 'signing_key' must be a string (64 hex digits or a passphrase)")
    if re.fullmatch(r"[0-9a-fA-F]{64}", key):
        return bytes.fromhex(key)
    if len(key) >= MIN_HEX_KEY_LOOKALIKE and re.fullmatch(r"[0-9a-fA-F]+", key):
        raise ConfigError(f"{where}: field 'signing_key' has {len(key)} hex digits; a hex key has exactly 64 "
                          "(32 bytes). Check for a digit lost or added in copying, or use a passphrase that is "
                          "not all hex digits")
    try:
        return hashlib.sha256(key.encode("utf-8")).digest()
    except UnicodeEncodeError as exc:
        raise ConfigError(f"{where}: field 'signing_key' is not valid UTF-8 text (byte {exc.start}); the "
                          "passphrase is hashed as UTF-8 (as MAVProxy's 'signing setup' does): give it in UTF-8 "
                          "or as 64 hex digits") from None


@dataclass(frozen=True)
class VehicleState:
    """The simulated vehicle's true state as SITL reports it (SIM_STATE), for follow mode.

    Why SIM_STATE and never GLOBAL_POSITION_INT: the latter is the autopilot's EKF estimate, which is built from
    the very fixes the bridge sends; rendering the camera there would close the loop on itself.
    """

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    vel_ned_mps: tuple[float, float, float]
    heading_rad: float          # MAVLink yaw (CW from north)
    roll_rad: float
    pitch_rad: float
    received_mono_s: float
    system_id: int
    sim_time_s: float = math.nan   # the simulator's clock at its arrival (SYSTEM_TIME-synced), NaN before synced


def vehicle_state(m, now_s: float) -> VehicleState | None:
    """VehicleState of a SIM_STATE message, or None for SITL's placeholder before it has a position (0, 0).

    ArduPilot fills the float lat/lon fields in degE7 and the int32 extensions ``lat_int``/``lon_int`` in degE7;
    other simulators send degrees in the float fields: both are accepted.
    """
    lat_i, lon_i = getattr(m, "lat_int", 0) or 0, getattr(m, "lon_int", 0) or 0
    if lat_i or lon_i:
        lat, lon = lat_i / 1e7, lon_i / 1e7
    else:
        lat, lon = float(m.lat), float(m.lon)
        if abs(lat) > 90.0 or abs(lon) > 180.0:
            lat, lon = lat / 1e7, lon / 1e7
    values = (lat, lon, m.alt, m.vn, m.ve, m.vd, m.yaw, m.roll, m.pitch)
    if (lat == 0.0 and lon == 0.0) or not all(math.isfinite(v) for v in values) or abs(lat) > 90.0:
        return None
    return VehicleState(lat_deg=lat, lon_deg=lon, alt_amsl_m=float(m.alt),
                        vel_ned_mps=(float(m.vn), float(m.ve), float(m.vd)),
                        heading_rad=msgs.wrap_pi(float(m.yaw)), roll_rad=float(m.roll), pitch_rad=float(m.pitch),
                        received_mono_s=now_s, system_id=m.get_srcSystem())


@dataclass(frozen=True)
class SenderStats:
    """A snapshot of what the sender did; ``tick_intervals_s`` are the last intervals between main ticks."""

    sent: dict[str, int]
    dropped: int
    skipped_ticks: int
    link_up: bool
    reconnects: int
    last_error: str | None
    quality: FixQuality | None
    fix_age_s: float | None
    fix_seq: int | None
    reset_counter: int
    tick_intervals_s: tuple[float, ...]
    running: bool

    @property
    def rate_hz(self) -> float:
        n = len(self.tick_intervals_s)
        return n / sum(self.tick_intervals_s) if n else 0.0

    @property
    def jitter_s(self) -> float:
        """Standard deviation of the tick intervals."""
        n = len(self.tick_intervals_s)
        if n < 2:
            return 0.0
        mean = sum(self.tick_intervals_s) / n
        return math.sqrt(sum((t - mean) ** 2 for t in self.tick_intervals_s) / (n - 1))


class _LinkFile:
    """The file object pymavlink's encoder writes to: counts frames the link could not take."""

    def __init__(self, link: Link) -> None:
        self.link = link
        self.dropped = 0

    def write(self, buf: bytes) -> None:
        if not self.link.write(bytes(buf)):
            self.dropped += 1


class MavlinkSender:
    """Streams the latest :class:`PoseFix` as GPS_INPUT / VISION_POSITION_ESTIMATE / ODOMETRY at ``rate_hz``.

    Use as a context manager (``with MavlinkSender(cfg, origin=...) as s: s.publish(fix)``) or start()/stop().
    """

    def __init__(self, config: SenderConfig | None = None, *, policy: FixPolicy | None = None,
                 origin: GeoOrigin | None = None, slot: FixSlot | None = None, **overrides) -> None:
        config = config or SenderConfig()
        if overrides:
            config = build_config(SenderConfig, overrides, where="MavlinkSender overrides", base=config)
        else:
            config.validate("SenderConfig")
        self.config = config
        self.policy = policy or FixPolicy()
        self.origin = origin
        self.slot = slot or FixSlot(self.policy.jump_threshold_m, self.policy.jump_sigma)
        self.link = Link(config.endpoint, reconnect_s=config.reconnect_s)
        self._file = _LinkFile(self.link)
        self._mav = mavlink2.MAVLink(self._file, srcSystem=config.system_id, srcComponent=config.component_id)
        self._parser = mavlink2.MAVLink(None)
        self._parser.robust_parsing = True
        secret = signing_secret(config.signing_key)
        if secret is not None:
            self._mav.signing.secret_key = secret
            self._mav.signing.link_id = config.signing_link_id
            self._mav.signing.sign_outgoing = True
        # message times: the wall clock, or the followed simulator's (an autopilot corrects offboard stamps
        # against its own clock); MAVLink signing always on the wall clock (receivers check it against theirs)
        self.wall_clock = MonotonicClock()
        self.following = config.request_vehicle_hz > 0
        self.clock: MonotonicClock | SimClock = SimClock(config.sim_speedup) if self.following else self.wall_clock
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Condition()     # guards the stats; notified when a tick takes a new fix
        self._sent: collections.Counter[str] = collections.Counter()
        self._intervals: collections.deque[float] = collections.deque(maxlen=600)
        self._last_tick_s: float | None = None
        self._quality: FixQuality | None = None
        self._item: SlotItem | None = None
        self._age_s: float | None = None
        self._vehicle: VehicleState | None = None
        self._autopilot_sysid: int | None = None   # who answered: the origin's target, and "heard" for udpin
        self._origin_now = False
        self._sim_time_mono_s: float | None = None
        self._skipped = 0
        self._latency_seq: int | None = None
        self._new_last_tick = False        # the last tick sent a fix for the first time
        self._acks: collections.Counter[int] = collections.Counter()
        self._extpos: Schedule | None = None
        self._latencies_s: collections.deque[float] = collections.deque(maxlen=10_000)
        self.error: BaseException | None = None

    # -- lifecycle -------------------------------------------------------------------------------------------
    def start(self) -> MavlinkSender:
        """Open the link (errors raise here, in the caller's thread) and start the sender thread."""
        if self._thread is not None:
            raise RuntimeError("MavlinkSender already started")
        self.link.open()
        self._thread = threading.Thread(target=self._run, name="mavlink-sender", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout_s: float = 2.0) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
        self.link.close()

    def __enter__(self) -> MavlinkSender:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def publish(self, fix: PoseFix) -> SlotItem:
        """Hand a new estimate to the sender (any thread, any rate)."""
        return self.slot.put(fix)

    def wait_taken(self, seq: int, timeout_s: float) -> bool:
        """Wait until a tick has taken fix ``seq`` (or a later one) from the slot; False on timeout.

        Replaying faster than real time (``--speed 0``) waits on this so that every fix reaches the wire."""
        with self._lock:
            return self._lock.wait_for(lambda: self._item is not None and self._item.seq >= seq, timeout_s)

    def vehicle(self) -> VehicleState | None:
        """The simulator's latest true vehicle state (SIM_STATE), or None if none was received."""
        with self._lock:
            return self._vehicle

    @property
    def autopilot_sysid(self) -> int | None:
        """System id of the autopilot once its HEARTBEAT was received (None before)."""
        with self._lock:
            return self._autopilot_sysid

    def stats(self) -> SenderStats:
        with self._lock:
            item = self._item
            return SenderStats(
                sent=dict(self._sent), dropped=self._file.dropped, skipped_ticks=self._skipped,
                link_up=self.link.up, reconnects=self.link.reconnects, last_error=self.link.last_error,
                quality=self._quality, fix_age_s=self._age_s, fix_seq=None if item is None else item.seq,
                reset_counter=0 if item is None else item.reset_counter,
                tick_intervals_s=tuple(self._intervals), running=self.running,
            )

    # -- the loop --------------------------------------------------------------------------------------------
    def _run(self) -> None:
        try:
            self._loop()
        except Exception as exc:  # surfaced through .error and stats().running, never a stray traceback
            self.error = exc

    def _loop(self) -> None:
        cfg = self.config
        t0 = time.monotonic()
        main = Schedule(cfg.rate_hz, t0)
        beat = Schedule(cfg.heartbeat_hz, t0)
        # the origin: every second until the autopilot has spoken (on udpin nothing can be sent before, and an
        # autopilot that boots late missed the first), at once when it first speaks, then every origin_period_s
        origin_early = Schedule(1.0 / min(1.0, cfg.origin_period_s), t0) if self.origin is not None else None
        origin = Schedule(1.0 / cfg.origin_period_s, t0) if self.origin is not None else None
        request = Schedule(0.5, t0) if cfg.request_vehicle_hz > 0 else None
        self._extpos = Schedule(cfg.external_position_hz, t0) if "external_position" in cfg.messages else None
        while not self._stop.is_set():
            now = time.monotonic()
            if beat.due(now):
                self._send("heartbeat", msgs.heartbeat())
                beat.advance(now)
            if origin is not None:
                heard = self.autopilot_sysid is not None
                sched = origin if heard else origin_early
                if sched.due(now) or self._origin_now:
                    self._origin_now = False
                    target = cfg.target_system or (self.autopilot_sysid or 0)
                    self._send("set_gps_global_origin", msgs.set_gps_global_origin(
                        self.origin, self.clock.unix_us(now), target))
                    sched.advance(now)
            if request is not None and request.due(now):
                self._request_vehicle_streams()
                request.advance(now)
            if main.due(now):
                self._tick(now)
                main.advance(now)
                with self._lock:
                    self._skipped = main.skipped
            self._receive()
            if self._extpos is not None and self._extpos.due(now):
                self._external_position(now)
                self._extpos.advance(now)
            schedules = [s for s in (main, beat, request, self._extpos) if s is not None]
            if origin is not None:
                schedules.append(origin if self.autopilot_sysid is not None else origin_early)
            wait = min(s.deadline_s for s in schedules) - time.monotonic()
            if self.following:           # read the simulator's truth as it arrives, not once per send tick
                wait = min(wait, RECEIVE_POLL_S)
            if wait > 0 and not self._origin_now:
                self._stop.wait(wait)

    def _tick(self, now: float) -> None:
        with self._lock:
            if self._last_tick_s is not None:
                self._intervals.append(now - self._last_tick_s)
            self._last_tick_s = now
        item = self.slot.get()
        if item is None:
            return  # nothing estimated yet: heartbeats only
        with self._lock:
            sent = self._item
        if "gps_input" in self.config.messages and sent is not None and item.seq != sent.seq and self._new_last_tick:
            # a resend between two new fixes: GPS_INPUT carries each fix's capture time, so ArduPilot's update
            # interval is 0 on a resend and a frame's interval between new fixes, and two of those in a row (a
            # backlog after a stall) are two delayed updates, which it calls unhealthy; the new fix goes next tick
            item = sent
        self._new_last_tick = sent is None or item.seq != sent.seq
        age = (now - item.received_mono_s) * (self.config.sim_speedup if self.following else 1.0)
        quality = assess(item.fix, age, self.policy)
        with self._lock:
            self._item, self._age_s, self._quality = item, age, quality
            self._lock.notify_all()
        cfg = self.config
        fix = item.fix
        unix_s = self.capture_unix_s(item, now)
        usec = int(unix_s * 1e6)
        with self._lock:
            if self._latency_seq != item.seq:        # the first send of each fix: capture to wire, clock seconds
                self._latency_seq = item.seq
                self._latencies_s.append(self.clock.unix_s(now) - unix_s)
        for kind in cfg.messages:
            if kind == "gps_input":
                self._send(kind, msgs.gps_input(fix, quality, unix_s, gps_id=cfg.gps_id,
                                                send_yaw=cfg.gps_yaw))
            elif kind == "vision_position_estimate" and quality.usable:
                self._send(kind, msgs.vision_position_estimate(fix, quality, usec, item.reset_counter))
            elif kind == "odometry":
                self._send(kind, msgs.odometry(fix, quality, usec, item.reset_counter, cfg.odometry_frames))

    def _external_position(self, now: float) -> None:
        """MAV_CMD_EXTERNAL_POSITION_ESTIMATE of the latest fix, withheld from the position feed or not (it is the
        low-rate fix for an autopilot dead reckoning), if it is usable: sent time on the message clock since
        this sender started, processing time = capture to send."""
        item = self.slot.get()
        if item is None:
            return
        fix = dataclasses.replace(item.fix, withheld=False)
        age = (now - item.received_mono_s) * (self.config.sim_speedup if self.following else 1.0)
        quality = assess(fix, age, self.policy)
        if not quality.usable:
            return
        sent = self.clock.unix_s(now)
        target = self.config.target_system or (self.autopilot_sysid or 1)
        self._send("external_position", msgs.external_position_estimate(
            fix, quality, sent - self.clock.anchor_unix_s, sent - self.capture_unix_s(item, now), target, 1))

    def acks(self) -> dict[int, int]:
        """COMMAND_ACK results received for MAV_CMD_EXTERNAL_POSITION_ESTIMATE: result -> count."""
        with self._lock:
            return dict(self._acks)

    def capture_unix_s(self, item: SlotItem, now: float) -> float:
        """The message stamp of the fix in ``item``: when its frame was captured, on the clock the messages run
        on. Following a simulator whose clock is known, the fix's own time (the truth sample's, SITL's boot
        seconds); otherwise (or when that time is not on the simulator's clock) when it was published. Never
        later than now, never earlier than its publication minus ``MAX_CAPTURE_AGE_S``."""
        now_unix = self.clock.unix_s(now)
        if isinstance(self.clock, MonotonicClock):    # the wall clock: exact, and the same on every resend
            published = self.clock.unix_s(item.received_mono_s)
        else:
            published = now_unix - max(0.0, now - item.received_mono_s) * self.config.sim_speedup
        if self.following and isinstance(self.clock, SimClock) and self.clock.synced:
            frame = self.clock.unix_of_sim_s(item.fix.time_s)
            if published - MAX_CAPTURE_AGE_S <= frame <= now_unix:
                return frame
        return min(published, now_unix)

    def latencies_s(self) -> tuple[float, ...]:
        """Capture-to-send latency of each fix's first send (the clock's seconds: the simulator's when
        following), the last ``maxlen`` of them."""
        with self._lock:
            return tuple(self._latencies_s)

    def _send(self, kind: str, message) -> None:
        signing = self._mav.signing
        if signing.sign_outgoing:  # keep signing timestamps >= real time (receivers reject stale streams)
            signing.timestamp = max(signing.timestamp, signing_timestamp(self.wall_clock.unix_s()))
        dropped = self._file.dropped
        self._mav.send(message)
        if self._file.dropped == dropped:      # counted only if the link took it (dropped frames count there)
            with self._lock:
                self._sent[kind] += 1

    def _request_vehicle_streams(self) -> None:
        """Ask for SIM_STATE, the simulator's truth, and SYSTEM_TIME, its clock, at the same interval
        (MAV_CMD_SET_MESSAGE_INTERVAL; ArduPilot sends messages of one interval together), until they come."""
        vehicle = self.vehicle()
        now = time.monotonic()
        for msg_id, last in ((mavlink2.MAVLINK_MSG_ID_SIM_STATE, None if vehicle is None else vehicle.received_mono_s),
                             (mavlink2.MAVLINK_MSG_ID_SYSTEM_TIME, self._sim_time_mono_s)):
            if last is not None and now - last < 2.0:
                continue
            target = self.config.target_system or (self.autopilot_sysid or 0)
            self._send("command_long", mavlink2.MAVLink_command_long_message(
                target, 1, mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                float(msg_id), 1e6 / self.config.request_vehicle_hz, 0, 0, 0, 0, 0))

    def _receive(self, max_reads: int = 256) -> None:
        """Parse everything that arrived: a UDP read returns one datagram, and SITL sends many per tick (reading
        one per tick let a backlog build up, so the followed truth lagged further and further)."""
        received: list = []
        for _ in range(max_reads):
            data = self.link.read()
            if not data:
                break
            try:
                received += self._parser.parse_buffer(data) or []
            except mavlink2.MAVError:
                continue
        now = time.monotonic()
        # the simulator's time of each truth sample: SITL sends SIM_STATE and SYSTEM_TIME at one interval, in one
        # burst, so the SYSTEM_TIME nearest it in the batch dates it (its arrival would date it up to a read
        # period late)
        boots = [(i, m.time_boot_ms / 1000.0) for i, m in enumerate(received)
                 if m.get_type() == "SYSTEM_TIME" and m.get_srcComponent() == 1]
        for i, m in enumerate(received):
            name = m.get_type()
            if name == "HEARTBEAT" and m.autopilot != mavlink2.MAV_AUTOPILOT_INVALID:
                with self._lock:
                    first = self._autopilot_sysid is None
                    self._autopilot_sysid = m.get_srcSystem()
                if first and self.origin is not None:
                    self._origin_now = True       # the link can reach it now: announce the origin at once
            elif name == "SYSTEM_TIME" and self.following and m.get_srcComponent() == 1:
                self.clock.observe(m.time_boot_ms / 1000.0, now)     # the simulator's clock
                self._sim_time_mono_s = now
            elif name == "COMMAND_ACK" and m.command == mavlink2.MAV_CMD_EXTERNAL_POSITION_ESTIMATE:
                with self._lock:
                    self._acks[int(m.result)] += 1
            elif name == "SIM_STATE":
                state = vehicle_state(m, now)
                if state is not None:
                    if self.following and boots:
                        sim_s = min(boots, key=lambda b: abs(b[0] - i))[1]
                        state = dataclasses.replace(state, sim_time_s=sim_s)
                    elif self.following and self.clock.synced:
                        state = dataclasses.replace(state, sim_time_s=self.clock.sim_at_s(now))
                    with self._lock:
                        self._vehicle = state


__all__ = ["MavlinkSender", "SenderConfig", "SenderStats", "VehicleState", "vehicle_state", "PoseFix", "GeoOrigin",
           "FixPolicy", "signing_secret"]
