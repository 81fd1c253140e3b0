"""The fix as the autopilot prefers it: velocity accuracy from the estimator's own covariance through the bridge's
velocity filter (not a constant), and message stamps at the frame's capture time, not the send time."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from aerial_loc_env.mavlink import messages as msgs
from aerial_loc_env.mavlink.bridge import MIN_SPEED_STD_MPS, EstimateBridge
from aerial_loc_env.mavlink.fix import FixPolicy, PoseFix, SlotItem, assess
from aerial_loc_env.mavlink.sender import MavlinkSender, SenderConfig
from aerial_loc_env.mavlink.timebase import gps_to_unix_s


class _Est:
    def __init__(self, x: float, y: float, sigma_m: float, status: str = "ok") -> None:
        self.x_m, self.y_m, self.yaw_rad, self.status = x, y, None, status
        self.cov_xy_m2 = np.eye(2) * sigma_m ** 2


def _bridge(**kw) -> EstimateBridge:
    return EstimateBridge(lambda x, y: (47.0 + y * 1e-5, 8.0 + x * 1e-5), (0.0, 0.0), **kw)


def test_speed_accuracy_is_the_covariance_through_the_filter():
    """A straight line at constant speed (no acceleration, so no lag): the reported speed accuracy is the position
    sigma through the difference and the low-pass, per axis sqrt((a/dt)^2 * 2 sigma^2 / (2 - a)) with gain
    a = dt / (tau + dt), worked by hand here for dt 0.25 s, tau 1 s (a = 0.2): 0.8 * sigma * sqrt(2 / 1.8); it
    scales with the estimator's own sigma (not a constant), and the first difference (no filter yet) reports
    sqrt(2) sigma / dt."""
    for sigma in (1.0, 3.0):
        br = _bridge(velocity_tau_s=1.0)
        fixes = [br.fix(_Est(22.0 * 0.25 * k, 5.0, sigma), time_s=0.25 * k, altitude_m=100.0) for k in range(40)]
        assert not fixes[0].vel_horiz_valid and fixes[1].vel_horiz_valid
        assert fixes[1].speed_std_mps == pytest.approx(math.sqrt(2.0) * sigma / 0.25)
        assert fixes[-1].speed_std_mps == pytest.approx(0.8 * sigma * math.sqrt(2.0 / 1.8), rel=1e-6)
        assert fixes[-1].vel_enu_mps[:2] == pytest.approx((22.0, 0.0))


def test_speed_accuracy_covers_the_velocity_error_of_a_noisy_estimator():
    """White position noise of a known sigma (fixed seed, 2000 fixes at 4 Hz, still vehicle): the velocity's true
    per-axis RMS error is within the reported accuracy and not below half of it (the filter's noise formula is
    exact for white noise; the lag term adds what the noise makes of the measured acceleration). A sigma claimed
    near zero still reports the floor."""
    rng = np.random.default_rng(7)
    br = _bridge()
    sigma = 2.0
    errors, reported = [], []
    for k in range(2000):
        nx, ny = rng.normal(0.0, sigma, 2)
        fix = br.fix(_Est(nx, ny, sigma), time_s=0.25 * k, altitude_m=100.0)
        if k >= 20:
            errors.append(fix.vel_enu_mps[:2])
            reported.append(fix.speed_std_mps)
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert 0.5 * np.median(reported) <= rms <= np.median(reported), (rms, np.median(reported))
    exact = _bridge()
    last = [exact.fix(_Est(0.0, 0.0, 1e-6), time_s=0.25 * k, altitude_m=100.0) for k in range(10)][-1]
    assert last.speed_std_mps == MIN_SPEED_STD_MPS


def test_velocity_restarts_after_a_gap_or_a_jump():
    """After fixes stop for longer than ``max_gap_s`` (a vision cut) the velocity is not the average over the gap:
    the filter starts again and the next fix carries no velocity (flagged), as after a jump."""
    br = _bridge(max_gap_s=2.0)
    for k in range(8):
        br.fix(_Est(10.0 * k, 0.0, 1.0), time_s=0.5 * k, altitude_m=100.0)
    br.fix(_Est(0.0, 0.0, 1.0, "lost"), time_s=5.0, altitude_m=100.0)
    after = br.fix(_Est(300.0, 0.0, 1.0), time_s=24.0, altitude_m=100.0)
    assert not after.vel_horiz_valid and after.speed_std_mps == br.max_speed_mps
    m = msgs.gps_input(after, assess(after, 0.0, FixPolicy()), 1.7e9)
    assert m.ignore_flags & msgs.mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ
    again = br.fix(_Est(310.0, 0.0, 1.0), time_s=24.5, altitude_m=100.0)
    assert again.vel_horiz_valid and again.vel_enu_mps[0] == pytest.approx(20.0)


def _item(time_s: float, published_mono_s: float, seq: int = 0) -> SlotItem:
    fix = PoseFix(time_s=time_s, lat_deg=47.0, lon_deg=8.0, alt_amsl_m=600.0, east_m=0.0, north_m=0.0, up_m=200.0)
    return SlotItem(fix, seq, 0, published_mono_s)


def test_messages_are_stamped_at_the_frames_capture_time_on_the_simulators_clock():
    """Following SITL at speedup 2: a fix whose frame was taken at SITL time 99.5 s and is sent at 100.3 s carries
    99.5 s (on the message clock), in GPS_INPUT's week time and time_usec, on every resend; without a known
    simulator clock the stamp is the fix's publication, never the send time; a capture time that is not on the
    clock (older than MAX_CAPTURE_AGE_S before publication, or in the future) falls back to the publication."""
    sender = MavlinkSender(SenderConfig(connect="udpout:127.0.0.1:9", request_vehicle_hz=20.0, sim_speedup=2.0))
    clock = sender.clock
    mono0 = clock.monotonic()
    clock.observe(100.0, mono0)                    # SITL's clock read 100.0 s at mono0
    capture = clock.unix_of_sim_s(99.5)
    assert clock.unix_s(mono0) - capture == pytest.approx(0.5)
    item = _item(99.5, mono0 + 0.1)
    for send_mono in (mono0 + 0.15, mono0 + 0.2):  # resends keep the capture time
        stamp = sender.capture_unix_s(item, send_mono)
        assert stamp == pytest.approx(capture)
        m = msgs.gps_input(item.fix, assess(item.fix, 0.0, FixPolicy()), stamp)
        assert gps_to_unix_s(m.time_week, m.time_week_ms) == pytest.approx(capture, abs=1e-3)
        assert m.time_usec / 1e6 == pytest.approx(capture, abs=1e-6)
    stale = _item(90.0, mono0 + 0.1)               # 10 s before its publication: not a capture time
    assert sender.capture_unix_s(stale, mono0 + 0.2) == pytest.approx(clock.unix_s(mono0) + 0.1 * 2.0)
    wall = MavlinkSender(SenderConfig(connect="udpout:127.0.0.1:9"))
    published = wall.clock.monotonic()
    later = published + 0.08
    assert wall.capture_unix_s(_item(5.0, published), later) == pytest.approx(wall.clock.unix_s(published))


def test_external_position_estimate_is_a_global_command_without_altitude():
    """MAV_CMD_EXTERNAL_POSITION_ESTIMATE (43003) as COMMAND_INT in the global frame: lat/lon degE7, no altitude
    (NaN: ArduPilot accepts only that), param1 the send time, param2 the processing time (capture to send, so
    the autopilot dates the fix that much earlier), param3 the horizontal accuracy; it survives encoding and
    decoding; a fix withheld from the position feed is no GPS fix (GPS_INPUT fix_type 1) but the command still
    carries it."""
    from pymavlink.dialects.v20 import common as mavlink2

    fix = PoseFix(time_s=0.0, lat_deg=47.1234567, lon_deg=8.7654321, alt_amsl_m=600.0, east_m=0.0, north_m=0.0,
                  up_m=200.0, cov_en_m2=(4.0, 0.0, 9.0), withheld=True)
    assert not assess(fix, 0.0, FixPolicy()).usable
    assert msgs.gps_input(fix, assess(fix, 0.0, FixPolicy()), 1.7e9).fix_type == 1
    quality = assess(dataclasses.replace(fix, withheld=False), 0.0, FixPolicy())
    cmd = msgs.external_position_estimate(fix, quality, 12.5, 0.08, target_system=1)
    mav = mavlink2.MAVLink(None, srcSystem=1, srcComponent=197)
    decoded = mavlink2.MAVLink(None).parse_buffer(cmd.pack(mav))[0]
    assert decoded.command == mavlink2.MAV_CMD_EXTERNAL_POSITION_ESTIMATE == 43003
    assert decoded.frame == mavlink2.MAV_FRAME_GLOBAL and math.isnan(decoded.z) and math.isnan(decoded.param4)
    assert (decoded.x, decoded.y) == (471234567, 87654321)
    assert decoded.param1 == pytest.approx(12.5) and decoded.param2 == pytest.approx(0.08, rel=1e-6)
    assert decoded.param3 == pytest.approx(math.sqrt(13.0), rel=1e-6)


def test_a_resend_separates_new_fixes_so_ardupilot_never_sees_two_frame_intervals_in_a_row():
    """Capture-stamped GPS_INPUT: ArduPilot's update interval is 0 on a resend and a frame's interval (4 Hz:
    250 ms, over its 245 ms) between new fixes; two of those in a row make its GPS unhealthy. After a stall the
    slot can hold a newer fix at every tick: the sender then resends the last fix first, and the newest goes at
    the next tick (the slot keeps only the latest: fix 1 here was replaced before a tick could take it)."""
    sender = MavlinkSender(SenderConfig(connect="udpout:127.0.0.1:9"))
    sent = []
    sender._send = lambda kind, message: sent.append(message.time_usec)     # the wire is not under test here
    t0 = sender.clock.monotonic()
    fixes = []
    for k in range(4):                       # a new fix at every tick (a backlog), then two ticks with none new
        fix = PoseFix(time_s=0.25 * k, lat_deg=47.0, lon_deg=8.0, alt_amsl_m=600.0, east_m=0.0, north_m=0.0,
                      up_m=200.0)
        fixes.append(sender.publish(fix))
        sender._tick(t0 + 0.1 * k)
    sender._tick(t0 + 0.4)
    sender._tick(t0 + 0.5)
    stamps = [sender.clock.unix_s(item.received_mono_s) for item in fixes]
    order = [min(range(4), key=lambda i, u=u: abs(stamps[i] * 1e6 - u)) for u in sent]
    assert order == [0, 0, 2, 2, 3, 3], order
    assert not any(b > a and c > b for a, b, c in zip(order, order[1:], order[2:], strict=False))
