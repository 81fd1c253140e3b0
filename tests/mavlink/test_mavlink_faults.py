"""Faults around the MAVLink sender, over real loopback sockets: no peer, peer restarts, TCP peer gone and
back, bad connection strings, a slow estimator, Ctrl-C, and the follow mode's closed loop."""

from __future__ import annotations

import contextlib
import io
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from aerial_loc_env.cli import main as aerial_loc_main
from aerial_loc_env.mavlink import cli as mav_cli
from aerial_loc_env.mavlink.fix import FixPolicy, GeoOrigin, PoseFix
from aerial_loc_env.mavlink.link import LinkError
from aerial_loc_env.mavlink.selfcheck import free_udp_port
from aerial_loc_env.mavlink.sender import MavlinkSender, SenderConfig

REPO = Path(__file__).resolve().parents[2]
FIX = PoseFix(time_s=0.0, lat_deg=47.0, lon_deg=8.0, alt_amsl_m=600.0, east_m=0.0, north_m=0.0, up_m=200.0,
              vel_enu_mps=(5.0, 0.0, 0.0), yaw_rad=0.0, cov_en_m2=(2.0, 0.0, 2.0), v_std_m=0.5)


def _udp_socket(port: int = 0) -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", port))
    s.settimeout(0.05)
    return s


def _collect(sock: socket.socket, seconds: float, parser=None) -> list[tuple[float, object, tuple]]:
    """(monotonic time, message, sender address) of every frame received for ``seconds``."""
    parser = parser or mavlink2.MAVLink(None)
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            data, addr = sock.recvfrom(65536)
        except (TimeoutError, BlockingIOError):
            continue
        for m in parser.parse_buffer(data) or []:
            out.append((time.monotonic(), m, addr))
    return out


def _names(frames) -> list[str]:
    return [m.get_type() for _, m, _ in frames]


def test_no_peer_listening_keeps_sending():
    port = free_udp_port()
    with MavlinkSender(SenderConfig(connect=f"udpout:127.0.0.1:{port}", rate_hz=20.0)) as sender:
        sender.publish(FIX)
        time.sleep(1.0)
        stats = sender.stats()
    assert sender.error is None and stats.running
    assert stats.sent["gps_input"] >= 15 and stats.dropped == 0   # UDP hands frames over, listener or not


def test_udp_peer_restarting_receives_again():
    sock = _udp_socket()
    port = sock.getsockname()[1]
    with MavlinkSender(SenderConfig(connect=f"udpout:127.0.0.1:{port}", rate_hz=20.0)) as sender:
        sender.publish(FIX)
        first = _collect(sock, 0.5)
        sock.close()                   # the peer goes away (ICMP port unreachable for a while) ...
        time.sleep(0.5)
        sock = _udp_socket(port)       # ... and comes back on the same port
        second = _collect(sock, 0.5)
        sock.close()
        assert sender.error is None and sender.running
    assert _names(first).count("GPS_INPUT") >= 5 and _names(second).count("GPS_INPUT") >= 5
    assert second[0][1].get_seq() != (first[-1][1].get_seq() + 1) % 256     # frames were sent in between


def _tcp_server(port: int) -> socket.socket:
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    srv.bind(("127.0.0.1", port))
    srv.listen(1)
    srv.settimeout(5.0)
    return srv


def _tcp_frames(conn: socket.socket, seconds: float) -> list[str]:
    parser = mavlink2.MAVLink(None)
    conn.settimeout(0.05)
    names = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            data = conn.recv(65536)
        except (TimeoutError, BlockingIOError):
            continue
        if not data:
            break
        names += [m.get_type() for m in parser.parse_buffer(data) or []]
    return names


def _wait(predicate, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.02)
    return predicate()


def test_tcp_peer_absent_then_gone_and_back_reconnects():
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    cfg = SenderConfig(connect=f"tcp:127.0.0.1:{port}", rate_hz=20.0, reconnect_s=0.1)
    with MavlinkSender(cfg) as sender:            # nobody listening yet: not fatal, the link retries
        sender.publish(FIX)
        time.sleep(0.3)
        assert not sender.stats().link_up and sender.stats().dropped > 0
        srv = _tcp_server(port)
        conn, _ = srv.accept()
        first = _tcp_frames(conn, 0.5)
        conn.close()                              # the autopilot goes away ...
        srv.close()
        assert _wait(lambda: not sender.stats().link_up, 3.0)
        srv = _tcp_server(port)                   # ... and comes back
        conn, _ = srv.accept()
        second = _tcp_frames(conn, 0.5)
        conn.close()
        srv.close()
        stats = sender.stats()
    assert first.count("GPS_INPUT") >= 5 and second.count("GPS_INPUT") >= 5
    assert stats.reconnects >= 2 and sender.error is None


def test_udpin_sends_only_after_the_peer_spoke():
    port = free_udp_port()
    with MavlinkSender(SenderConfig(connect=f"udpin:127.0.0.1:{port}", rate_hz=20.0)) as sender:
        sender.publish(FIX)
        time.sleep(0.3)
        assert sender.stats().dropped > 0                  # nowhere to send yet
        peer = _udp_socket()
        mav = mavlink2.MAVLink(peer, srcSystem=1, srcComponent=1)
        peer.sendto(mavlink2.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mav), ("127.0.0.1", port))
        frames = _collect(peer, 0.5)
        peer.close()
    assert _names(frames).count("GPS_INPUT") >= 5


@pytest.mark.parametrize("argv, words", [
    (["--connect", "udpout:localhost"], "HOST:PORT"),
    (["--connect", "tcp:127.0.0.1:0"], "1..65535"),
    (["--connect", "carrier-pigeon:1:2"], "unknown scheme"),
    (["--connect", "udpout:no-such-host.invalid:14550"], "cannot resolve host"),
    (["--message", "gps,telepathy"], "telepathy"),
    (["--rate-hz", "2"], "245 ms"),
    ([], None),
])
def test_cli_argument_errors_are_clear(argv, words, capsys):
    if words is None:   # no source at all
        rc = aerial_loc_main(["mavlink", "--connect", "udpout:127.0.0.1:9"])
        words = "--scenario and --agent"
    else:
        rc = aerial_loc_main(["mavlink", "--demo", "--quiet", "--duration-s", "0.1", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and words in err and "Traceback" not in err


def test_udpin_port_in_use_is_a_clear_error():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as busy:
        busy.bind(("127.0.0.1", 0))
        port = busy.getsockname()[1]
        sender = MavlinkSender(SenderConfig(connect=f"udpin:127.0.0.1:{port}"))
        with pytest.raises(LinkError, match="cannot open"):
            sender.start()


def test_slow_estimator_keeps_rate_then_degrades_and_drops_fix():
    sock = _udp_socket()
    port = sock.getsockname()[1]
    rate = 20.0
    policy = FixPolicy(stale_after_s=0.15, lost_after_s=0.8, stale_growth_mps=5.0)
    cfg = SenderConfig(connect=f"udpout:127.0.0.1:{port}", rate_hz=rate)
    with MavlinkSender(cfg, policy=policy) as sender:
        stop = threading.Event()

        def slow_estimator():   # 2.5 Hz for 1 s, then nothing: the sender must not follow its pace
            for k in range(3):
                sender.publish(PoseFix(**{**FIX.__dict__, "time_s": 0.4 * k, "east_m": 2.0 * k}))
                if stop.wait(0.4):
                    return

        worker = threading.Thread(target=slow_estimator)
        worker.start()
        frames = _collect(sock, 2.4)
        stop.set()
        worker.join()
    sock.close()
    gps = [(t, m) for t, m, _ in frames if m.get_type() == "GPS_INPUT"]
    t = [x[0] for x in gps]
    assert (len(t) - 1) / (t[-1] - t[0]) == pytest.approx(rate, rel=0.10)
    fix_types = [m.fix_type for _, m in gps]
    h_acc = [m.horiz_accuracy for _, m in gps]
    assert fix_types[0] == 3 and fix_types[-1] == 1        # held, then dropped once lost_after_s passed
    assert fix_types == sorted(fix_types, reverse=True)     # never recovers without a new estimate
    held = [m for _, m in gps if m.fix_type == 3]
    # held fixes degrade as hypot(h_std, growth * (age - stale)), up to age lost_after_s; the last held frame
    # is a period before it (three periods of slack for a loaded machine)
    def acc(age_s: float) -> float:
        return math.hypot(2.0, policy.stale_growth_mps * max(0.0, age_s - policy.stale_after_s))

    assert min(h_acc) == pytest.approx(2.0)
    assert acc(policy.lost_after_s - 3 / rate) <= max(m.horiz_accuracy for m in held)
    assert max(m.horiz_accuracy for m in held) <= acc(policy.lost_after_s) * (1 + 1e-6)
    assert {m.satellites_visible for m in held} == {policy.satellites_ok, policy.satellites_degraded}
    assert all(m.satellites_visible == 0 for _, m in gps if m.fix_type == 1)


def test_ctrl_c_exits_cleanly():
    sock = _udp_socket()
    port = sock.getsockname()[1]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # A terminal delivers Ctrl-C to a process whose SIGINT is at its default; a test runner started in the
    # background (e.g. `make test &` in a script) has SIGINT ignored, and exec keeps ignored signals.
    proc = subprocess.Popen([sys.executable, "-m", "aerial_loc_env.cli", "mavlink", "--demo", "--connect",
                             f"udpout:127.0.0.1:{port}", "--duration-s", "60"], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 20.0       # the interpreter may start slowly on a loaded machine
        while "GPS_INPUT" not in _names(_collect(sock, 0.2)) and time.monotonic() < deadline:
            pass
        assert proc.poll() is None and time.monotonic() < deadline, "the CLI never streamed"
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    finally:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        sock.close()
    assert proc.returncode == 130
    assert "Traceback" not in err
    assert out.strip().splitlines()[-1].startswith("interrupted:")


def _sim_state(lat_deg: float, lon_deg: float, alt_m: float, yaw_rad: float, *, ardupilot: bool = True):
    """SIM_STATE as ArduPilot SITL fills it: degE7 in the float fields too, and in lat_int/lon_int."""
    lat, lon = (lat_deg * 1e7, lon_deg * 1e7) if ardupilot else (lat_deg, lon_deg)
    return mavlink2.MAVLink_sim_state_message(
        1.0, 0.0, 0.0, 0.0, 0.0, 0.0, yaw_rad, 0.0, 0.0, -9.8, 0.0, 0.0, 0.0, lat, lon, alt_m, 0.0, 0.0,
        1.0, 2.0, -0.5, round(lat_deg * 1e7) if ardupilot else 0, round(lon_deg * 1e7) if ardupilot else 0)


def test_follow_mode_follows_sitl_truth_not_the_ekf():
    """A fake SITL at --speedup 4 answers the stream requests with SIM_STATE (truth), SYSTEM_TIME (its clock) and
    a far-away GLOBAL_POSITION_INT (its EKF): the demo follows the truth, the placeholder (0, 0) SITL sends before
    it has a position is ignored, and GPS_INPUT's GPS time runs on SITL's clock (ArduPilot corrects it against
    its own: wall-clock stamps would fall behind by 3 s every 4 s).
    """
    sock = _udp_socket()
    port = sock.getsockname()[1]
    lat, lon, heading_deg = -35.36, 149.17, 30.0          # ~ 600 m from the demo track's centre
    speedup, t0 = 4.0, time.monotonic()
    args = mav_cli.build_parser().parse_args(["--demo", "--follow", "--connect", f"udpout:127.0.0.1:{port}",
                                              "--duration-s", "2.5", "--quiet", "--sim-speedup", str(speedup),
                                              "--rate-hz", "40"])
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("rc", mav_cli.run(args, out=io.StringIO())))
    runner.start()
    ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = mavlink2.MAVLink(None)
    seen: list = []
    end = time.monotonic() + 2.4
    while time.monotonic() < end:
        frames = _collect(sock, 0.1, parser)
        seen += frames
        if frames:
            addr = frames[-1][2]
            sock.sendto(mavlink2.MAVLink_global_position_int_message(      # the EKF, 1 km off: never followed
                0, round((lat + 0.01) * 1e7), round(lon * 1e7), 684_000, 100_000, 500, 0, 0, 3000).pack(ap), addr)
            sock.sendto(_sim_state(lat, lon, 684.0, math.radians(heading_deg)).pack(ap), addr)
            sock.sendto(_sim_state(0.0, 0.0, 0.0, 0.0).pack(ap), addr)    # placeholder: ignored
            sock.sendto(mavlink2.MAVLink_system_time_message(                # SITL's clock, 4x real time
                0, 5000 + round((time.monotonic() - t0) * speedup * 1000)).pack(ap), addr)
    runner.join(10)
    sock.close()
    assert result.get("rc") == 0
    requests = {int(m.param1) for _, m, _ in seen if m.get_type() == "COMMAND_LONG"
                and m.command == mavlink2.MAV_CMD_SET_MESSAGE_INTERVAL}
    assert requests == {mavlink2.MAVLINK_MSG_ID_SIM_STATE, mavlink2.MAVLINK_MSG_ID_SYSTEM_TIME}
    # GPS time per real second over the last 1.5 s (synced by then): 4 s; scheduling delays either end's arrival by
    # less than the exchange's 0.1 s cycle, so the ratio is within 4 x (1 +- 2 x 0.1 / 1.5)
    gps = [(t, m.time_week_ms) for t, m, _ in seen if m.get_type() == "GPS_INPUT" and t > end - 1.5]
    rate = (gps[-1][1] - gps[0][1]) / 1000.0 / (gps[-1][0] - gps[0][0])
    assert speedup * (1 - 0.2 / 1.5) < rate < speedup * (1 + 0.2 / 1.5), rate
    last = [m for _, m, _ in seen if m.get_type() == "GPS_INPUT"][-1]
    # the demo's estimate noise is 0.5 m per axis: 5 sigma is 2.3e-5 deg of latitude, 2.8e-5 of longitude
    assert last.lat / 1e7 == pytest.approx(lat, abs=2.5e-5) and last.lon / 1e7 == pytest.approx(lon, abs=3e-5)
    assert last.alt == pytest.approx(684.0, abs=0.01)       # the truth's altitude (ground 584 m + 100 m)


def test_vehicle_state_units_and_placeholder():
    from aerial_loc_env.mavlink.sender import vehicle_state

    ap = mavlink2.MAVLink(None, srcSystem=7, srcComponent=1)
    # degE7 (ArduPilot: int32 extensions, exact) or degrees in the float32 fields (the documented unit: float32
    # resolves 149 deg to 1.5e-5 deg)
    for ardupilot, tol in ((True, 1e-7), (False, 1.6e-5)):
        m = ap.decode(bytearray(_sim_state(-35.3632608, 149.1652299, 584.09, -0.12, ardupilot=ardupilot).pack(ap)))
        v = vehicle_state(m, 5.0)
        assert (v.lat_deg, v.lon_deg) == (pytest.approx(-35.3632608, abs=tol), pytest.approx(149.1652299, abs=tol))
        assert (v.alt_amsl_m, v.heading_rad, v.vel_ned_mps, v.system_id) == (
            pytest.approx(584.09, abs=1e-4), pytest.approx(-0.12), pytest.approx((1.0, 2.0, -0.5)), 7)
    assert vehicle_state(ap.decode(bytearray(_sim_state(0.0, 0.0, 0.0, 0.0).pack(ap))), 5.0) is None


def test_origin_on_udpin_is_sent_as_soon_as_the_autopilot_speaks():
    """On udpin nothing can be sent before the peer speaks: the origin must follow its first HEARTBEAT at once
    (not 5 s later) and target that autopilot."""
    port = free_udp_port()
    cfg = SenderConfig(connect=f"udpin:127.0.0.1:{port}", messages=("odometry",), origin_period_s=5.0)
    sock = _udp_socket()
    ap = mavlink2.MAVLink(None, srcSystem=3, srcComponent=1)
    beat = mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              0, 0, mavlink2.MAV_STATE_STANDBY, 3)
    with MavlinkSender(cfg, origin=GeoOrigin(-35.0, 149.0, 584.0)) as sender:
        time.sleep(1.2)                                     # the sender's first origins went nowhere
        t_spoke = time.monotonic()
        sock.sendto(beat.pack(ap), ("127.0.0.1", port))
        frames = _collect(sock, 0.6)
        assert sender.autopilot_sysid == 3
    sock.close()
    origins = [(t, m) for t, m, _ in frames if m.get_type() == "SET_GPS_GLOBAL_ORIGIN"]
    assert origins and origins[0][0] - t_spoke < 0.3
    assert origins[0][1].target_system == 3 and origins[0][1].altitude == 584_000


def test_origin_message_targets_and_repeats():
    sock = _udp_socket()
    port = sock.getsockname()[1]
    cfg = SenderConfig(connect=f"udpout:127.0.0.1:{port}", messages=("odometry",), origin_period_s=0.2,
                       target_system=1)
    with MavlinkSender(cfg, origin=GeoOrigin(-35.0, 149.0, 584.0)):
        frames = _collect(sock, 0.7)
    sock.close()
    origins = [m for _, m, _ in frames if m.get_type() == "SET_GPS_GLOBAL_ORIGIN"]
    assert len(origins) >= 3 and {o.target_system for o in origins} == {1}
    assert "ODOMETRY" not in _names(frames)         # no estimate published yet: nothing but heartbeats/origin
