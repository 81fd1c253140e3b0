"""The monitor of SITL's SERIAL0: what arrives during a mission upload is kept, arrivals map onto SITL's clock,
and every wait hands over to the watchdog (SITL or the bridge dead) instead of running out its timeout."""

from __future__ import annotations

import socket
import threading

import pytest

from aerial_loc_env.errors import AerialLocError
from aerial_loc_env.mavlink.selfcheck import free_udp_port
from aerial_loc_env.sitl.monitor import Monitor, sim_clock


def test_monitor_keeps_what_arrives_during_a_mission_upload():
    """The mission protocol reads the link itself: a STATUSTEXT (and the truth) arriving between its messages
    is recorded, not dropped (an upload once swallowed "EKF3 IMU0 is using GPS")."""
    from pymavlink.dialects.v20 import ardupilotmega as apm

    port = free_udp_port()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(0.2)
    ap = apm.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = apm.MAVLink(None)
    done = threading.Event()

    def autopilot() -> None:          # a fake ArduPilot: heartbeats; answers the upload with a text between
        while not done.is_set():
            sock.sendto(ap.heartbeat_encode(2, 3, 0, 0, 3).pack(ap), ("127.0.0.1", port))
            try:
                data = sock.recv(4096)
            except TimeoutError:
                continue
            for m in parser.parse_buffer(data) or []:
                if m.get_type() == "MISSION_COUNT":
                    sock.sendto(ap.statustext_encode(6, b"EKF3 IMU0 is using GPS").pack(ap), ("127.0.0.1", port))
                    for seq in range(m.count):
                        sock.sendto(ap.mission_request_int_encode(250, 0, seq).pack(ap), ("127.0.0.1", port))
                    sock.sendto(ap.mission_ack_encode(250, 0, 0).pack(ap), ("127.0.0.1", port))

    fake = threading.Thread(target=autopilot, daemon=True)
    fake.start()
    monitor = Monitor(port)
    try:
        monitor.start(timeout_s=10.0)
        monitor.upload_mission([(16, 1.0, 2.0, 50.0, 0.0)])
        assert "EKF3 IMU0 is using GPS" in [t for _, t in monitor.track.texts]
    finally:
        done.set()
        fake.join(2)
        monitor.stop()
        sock.close()


def test_monitor_times_map_onto_sitls_clock():
    """Arrivals -> SITL's seconds through (arrival, time_boot_ms) pairs of a SITL at speedup 3 that paused for
    0.5 s real: linear between pairs, extended at the measured rate beyond them; one pair is a clear error."""
    pairs = [(10.0, 100.0), (11.0, 103.0), (11.5, 103.0), (12.5, 106.0)]
    to_sim = sim_clock(pairs)
    assert to_sim(10.5) == pytest.approx(101.5) and to_sim(11.25) == pytest.approx(103.0)
    rate = 6.0 / 2.5                                       # measured over all the pairs
    assert to_sim(9.0) == pytest.approx(100.0 - rate) and to_sim(13.5) == pytest.approx(106.0 + rate)
    with pytest.raises(AerialLocError, match="clock"):
        sim_clock(pairs[:1])


class _Died:
    """A watchdog whose process dies at its ``n``-th look."""

    def __init__(self, n: int) -> None:
        self.n, self.looks = n, 0

    def __call__(self) -> None:
        self.looks += 1
        if self.looks >= self.n:
            raise AerialLocError("SITL (arducopter) died: killed by signal 9 (SIGKILL)")


@pytest.mark.timeout(60)
def test_waits_report_the_watchdogs_error_not_their_timeout():
    """A wait for something that never comes (an hour's timeout) ends at the watchdog's first complaint, and so
    does waiting for SITL's first heartbeat: a dead SITL is said to be dead, not late."""
    monitor = Monitor(free_udp_port(), _Died(3))
    try:
        with pytest.raises(AerialLocError, match="died: killed by signal 9"):
            monitor.wait(lambda track: False, 3600.0, "the mission's last waypoint")
        assert monitor.watchdog.looks == 3
        monitor.watchdog = _Died(2)
        with pytest.raises(AerialLocError, match="died"):
            monitor.start(timeout_s=3600.0)
    finally:
        monitor.stop()
    quiet = Monitor(free_udp_port())          # no watchdog: the timeout, naming what was awaited
    try:
        with pytest.raises(AerialLocError, match="timed out after 0 s waiting for the landing"):
            quiet.wait(lambda track: False, 0.3, "the landing")
        with pytest.raises(AerialLocError, match="did not speak within 1 s"):
            quiet.start(timeout_s=1.0)
    finally:
        quiet.stop()
