"""Unit tests of the MAVLink bridge without sockets: time, frames, covariances, ageing, resets, configs."""

from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.mavlink import messages as msgs
from aerial_loc_env.mavlink.bridge import EstimateBridge
from aerial_loc_env.mavlink.fix import FixPolicy, FixSlot, PoseFix, assess
from aerial_loc_env.mavlink.link import parse_connection
from aerial_loc_env.mavlink.sender import SenderConfig, signing_secret
from aerial_loc_env.mavlink.timebase import Schedule, SimClock, gps_to_unix_s, gps_week_ms, signing_timestamp


def _fix(**kw) -> PoseFix:
    base = dict(time_s=0.0, lat_deg=47.0, lon_deg=8.0, alt_amsl_m=600.0, east_m=10.0, north_m=20.0,
                up_m=200.0, vel_enu_mps=(3.0, 4.0, -0.5), yaw_rad=0.3, cov_en_m2=(4.0, 1.5, 9.0), v_std_m=0.5)
    base.update(kw)
    return PoseFix(**base)


@pytest.mark.parametrize("utc", ["2017-01-01T00:00:00", "2024-02-29T13:45:10.250", "2026-11-21T08:00:00.999"])
def test_gps_week_ms_matches_calendar(utc):
    t = dt.datetime.fromisoformat(utc).replace(tzinfo=dt.timezone.utc)
    gps = t + dt.timedelta(seconds=18) - dt.datetime(1980, 1, 6, tzinfo=dt.timezone.utc)
    week, ms = gps_week_ms(t.timestamp())
    assert week == gps.days // 7
    assert ms == ((gps.days % 7) * 86400 + gps.seconds) * 1000 + gps.microseconds // 1000
    assert gps_to_unix_s(week, ms) == pytest.approx(t.timestamp(), abs=1e-3)


def test_gps_week_rollover_and_epoch():
    assert gps_week_ms(315_964_800 - 18) == (0, 0)
    week, ms = gps_week_ms(315_964_800 - 18 + 7 * 86400 - 0.0005)
    assert (week, ms) in ((0, 7 * 86400 * 1000 - 1), (1, 0))
    with pytest.raises(ConfigError, match="before the GPS epoch"):
        gps_week_ms(0.0)


def test_signing_timestamp_units():
    assert signing_timestamp(1_420_070_400 + 1.0) == 100_000   # 10 us units since 2015-01-01


@pytest.mark.parametrize("yaw_enu, heading", [(0.0, math.pi / 2), (math.pi / 2, 0.0), (math.pi, -math.pi / 2),
                                              (-math.pi / 2, -math.pi), (0.25, math.pi / 2 - 0.25)])
def test_yaw_enu_to_mavlink_heading(yaw_enu, heading):
    assert msgs.yaw_enu_to_heading(yaw_enu) == pytest.approx(heading, abs=1e-12)
    assert -math.pi <= msgs.yaw_enu_to_heading(yaw_enu) < math.pi


def test_heading_cdeg_range():
    assert msgs.heading_to_cdeg(0.0) == 36000          # north is 36000, 0 means "not available"
    assert msgs.heading_to_cdeg(math.pi / 2) == 9000    # east
    assert msgs.heading_to_cdeg(-math.pi / 2) == 27000  # west


def test_enu_to_ned_and_body_frd():
    assert msgs.enu_to_ned(1.0, 2.0, 3.0) == (2.0, 1.0, -3.0)
    # nose east (heading +90 deg): moving east is forward, moving north is to the left (negative y in FRD)
    fwd = msgs.ned_to_body_frd((0.0, 5.0, 1.0), math.pi / 2)
    left = msgs.ned_to_body_frd((5.0, 0.0, 0.0), math.pi / 2)
    np.testing.assert_allclose(fwd, (5.0, 0.0, 1.0), atol=1e-12)
    np.testing.assert_allclose(left, (0.0, -5.0, 0.0), atol=1e-12)
    q = msgs.quaternion_from_heading(math.pi / 2)
    assert q[0] ** 2 + q[3] ** 2 == pytest.approx(1.0) and q[1] == q[2] == 0.0
    assert 2 * math.atan2(q[3], q[0]) == pytest.approx(math.pi / 2)


def test_pose_covariance_layout_is_ned_upper_triangle():
    fix = _fix()
    q = assess(fix, 0.0, FixPolicy())
    cov = msgs.pose_covariance(fix, q)
    tri = msgs.upper_triangle(cov)
    assert len(tri) == 21
    assert tri[0] == pytest.approx(9.0)    # var_x = var_north
    assert tri[1] == pytest.approx(1.5)    # cov_xy = cov_north_east
    assert tri[6] == pytest.approx(4.0)    # var_y = var_east
    assert tri[11] == pytest.approx(0.25)  # var_z
    assert tri[20] == pytest.approx(msgs.UNKNOWN_ANGLE_VAR_RAD2)  # no yaw std given
    lost = assess(_fix(status="lost"), 0.0, FixPolicy())
    assert math.isnan(msgs.upper_triangle(msgs.pose_covariance(fix, lost))[0])


@pytest.mark.parametrize("bad", [
    dict(lat_deg=math.nan), dict(vel_enu_mps=(0.0, math.inf, 0.0)), dict(cov_en_m2=(1.0, 5.0, 1.0)),
    dict(status="confused"), dict(lon_deg=200.0), dict(yaw_rad=math.nan)])
def test_posefix_rejects_bad_values_with_clear_errors(bad):
    with pytest.raises(ConfigError, match="PoseFix"):
        _fix(**bad)


def test_bridge_turns_a_broken_estimate_into_a_lost_fix():
    br = EstimateBridge(lambda x, y: (47.0 + y * 1e-5, 8.0 + x * 1e-5), (0.0, 0.0))

    class Est:
        def __init__(self, x, y):
            self.x_m, self.y_m, self.yaw_rad, self.cov_xy_m2, self.status = x, y, math.nan, None, "ok"

    good = br.fix(Est(10.0, 20.0), time_s=0.0, altitude_m=100.0)
    broken = br.fix(Est(math.nan, 20.0), time_s=0.25, altitude_m=100.0)
    assert good.status == "ok" and good.yaw_rad is None
    assert broken.status == "lost" and (broken.east_m, broken.north_m) == (10.0, 20.0)


def test_assess_degrades_with_age_and_status():
    pol = FixPolicy(stale_after_s=0.5, lost_after_s=3.0, stale_growth_mps=2.0)
    fix = _fix()
    fresh = assess(fix, 0.1, pol)
    assert fresh.fix_type == 3 and fresh.satellites == pol.satellites_ok
    assert fresh.h_acc_m == pytest.approx(math.sqrt(13.0))
    accs = [assess(fix, a, pol).h_acc_m for a in (0.5, 1.0, 2.0, 2.9)]
    assert all(b > a for a, b in zip(accs, accs[1:], strict=False))
    assert accs[-1] == pytest.approx(math.hypot(math.sqrt(13.0), 2.0 * 2.4))
    stale = assess(fix, 1.0, pol)
    assert stale.satellites == pol.satellites_degraded and stale.hdop > fresh.hdop
    degraded = assess(_fix(status="degraded"), 0.0, pol)
    assert degraded.h_acc_m == pytest.approx(math.sqrt(13.0) * pol.degraded_factor)
    for q in (assess(fix, 3.1, pol), assess(_fix(status="lost"), 0.0, pol), assess(None, 0.0, pol)):
        assert not q.usable and q.fix_type <= 1 and q.satellites == 0 and q.odometry_quality == -1


def test_fix_slot_reset_counter_counts_jumps_only():
    slot = FixSlot(jump_threshold_m=5.0)
    assert slot.put(_fix(time_s=0.0)).reset_counter == 0
    # consistent with velocity (3, 4) m/s over 1 s: no jump
    assert slot.put(_fix(time_s=1.0, east_m=13.0, north_m=24.0)).reset_counter == 0
    # 4.9 m off the prediction: still no jump; then 50 m: jump
    assert slot.put(_fix(time_s=2.0, east_m=16.0 + 4.9, north_m=28.0)).reset_counter == 0
    item = slot.put(_fix(time_s=3.0, east_m=80.0, north_m=28.0))
    assert item.reset_counter == 1 and item.seq == 3
    slot.put(_fix(time_s=4.0, status="lost"))
    assert slot.get().reset_counter == 1              # losing is not a jump ...
    assert slot.put(_fix(time_s=5.0, east_m=83.0, north_m=32.0)).reset_counter == 2   # ... recovering is


def test_schedule_absolute_deadlines_skip_when_late():
    s = Schedule(10.0, start_s=100.0)
    assert s.due(100.0) and not s.due(99.99)
    s.advance(100.0)
    assert s.deadline_s == pytest.approx(100.1)
    s.advance(100.35)                                 # we were late by 2.5 periods
    assert s.deadline_s == pytest.approx(100.4) and s.skipped == 2
    for _ in range(1000):
        s.advance(s.deadline_s)
    assert s.deadline_s == pytest.approx(100.0 + 1004 * 0.1)   # no accumulated drift


def test_sim_clock_runs_on_the_simulators_time_without_jumps_or_steps_back():
    """SITL at --speedup 3: before its time is seen the clock runs 3x from its creation; the first SYSTEM_TIME
    joins on without a jump; then the simulator's own seconds, 3x between messages, from the least delayed of
    the recent ones (a late message does not pull it back); a simulator that falls behind its speedup for longer
    than the window is followed, the clock holding (never backwards) until it catches up; a zero or infinite
    rate is a clear error."""
    now = [10.0]
    c = SimClock(3.0, monotonic=lambda: now[0], anchor_unix_s=1000.0, window=4)
    assert not c.synced and c.unix_s(11.0) == pytest.approx(1003.0)         # 1 real s = 3 sim s
    c.observe(50.0, 11.0)                           # SITL says 50 s since its boot at that instant
    assert c.synced and c.unix_s(11.0) == pytest.approx(1003.0) and c.sim_s(11.0) == pytest.approx(50.0)
    assert c.sim_s(11.5) == pytest.approx(51.5) and c.unix_s(11.5) == pytest.approx(1004.5)
    c.observe(51.2, 11.5)                           # sent at 51.2 (11.4), arrived 0.1 s late: ignored
    assert c.sim_s(11.6) == pytest.approx(51.8)
    seen = [c.sim_s(11.6)]
    for k in range(1, 11):                          # SITL now at half its speedup (1.5 sim s per real s)
        c.observe(51.8 + 1.5 * 0.1 * k, 11.6 + 0.1 * k)
        seen.append(c.sim_s(11.6 + 0.1 * k))
    # followed within the window: ahead of the slower clock by at most its 3 older messages' worth of the
    # difference in rates (3 x 0.1 s x 1.5), and never backwards
    assert 0.0 <= seen[-1] - (51.8 + 1.5 * 1.0) <= 3 * 0.1 * 1.5 + 1e-9 and np.all(np.diff(seen) >= 0)
    for bad in (0.0, math.inf):
        with pytest.raises(ConfigError, match="rate"):
            SimClock(bad)


@pytest.mark.parametrize("text, kind", [
    ("udpout:127.0.0.1:14550", "udpout"), ("udpin:0.0.0.0:14550", "udpin"), ("tcp:localhost:5760", "tcp"),
    ("tcpin:0.0.0.0:5760", "tcpin"), ("/dev/ttyACM0,921600", "serial"),
    ("serial:/dev/ttyUSB0:57600", "serial"),
    ("COM3", "serial")])
def test_parse_connection_accepts_standard_strings(text, kind):
    ep = parse_connection(text)
    assert ep.kind == kind
    if kind == "serial":
        assert ep.baud in (921600, 57600)


@pytest.mark.parametrize("text, words", [
    ("udpout:localhost", "HOST:PORT"), ("udpout:127.0.0.1:99999", "1..65535"), ("tcp:host:abc", "1..65535"),
    ("bogus:1:2", "unknown scheme"), ("", "empty"), ("/dev/ttyACM0,fast", "baud")])
def test_parse_connection_rejects_with_clear_error(text, words):
    with pytest.raises(ConfigError, match="examples") as err:
        parse_connection(text)
    assert words in str(err.value) and "connect" in str(err.value)


def test_sender_config_validation():
    with pytest.raises(ConfigError, match="245 ms"):
        SenderConfig(rate_hz=4.0).validate("cfg")
    SenderConfig(rate_hz=4.0, allow_slow_gps=True).validate("cfg")
    with pytest.raises(ConfigError, match="messages"):
        SenderConfig(messages=("gps",)).validate("cfg")
    assert signing_secret("ab" * 32) == bytes([0xAB] * 32)
    assert len(signing_secret("passphrase")) == 32 and signing_secret("") is None


def test_bridge_georeference_local_frame_and_velocity():
    calls = []

    def to_latlon(x, y):
        calls.append((x, y))
        return 47.0 + y * 1e-5, 8.0 + x * 1e-5

    br = EstimateBridge(to_latlon, (100.0, 50.0), ground_amsl_m=400.0, velocity_tau_s=0.0)
    assert br.origin.lat_deg == pytest.approx(47.0005) and br.origin.alt_amsl_m == 400.0

    class Est:
        def __init__(self, x, y, status="ok"):
            self.x_m, self.y_m, self.yaw_rad, self.status = x, y, None, status
            self.cov_xy_m2 = np.array([[4.0, 1.0], [1.0, 9.0]])

    f0 = br.fix(Est(110.0, 70.0), time_s=0.0, altitude_m=200.0, yaw_fallback_rad=0.5)
    f1 = br.fix(Est(112.0, 73.0), time_s=0.5, altitude_m=200.0)
    assert (f0.east_m, f0.north_m, f0.up_m, f0.alt_amsl_m) == (10.0, 20.0, 200.0, 600.0)
    assert f0.lat_deg == pytest.approx(47.0007) and f0.lon_deg == pytest.approx(8.0011)
    assert f0.yaw_rad == 0.5 and f1.yaw_rad is None
    assert f0.cov_en_m2 == (4.0, 1.0, 9.0)
    assert f1.vel_enu_mps[:2] == pytest.approx((4.0, 6.0))
    f2 = br.fix(Est(412.0, 73.0), time_s=1.0, altitude_m=200.0)        # 600 m/s: a jump, not a velocity
    assert f2.vel_enu_mps[:2] == (0.0, 0.0)
    lost = br.fix(Est(0.0, 0.0, status="lost"), time_s=1.5, altitude_m=200.0)
    assert lost.status == "lost"
    f3 = br.fix(Est(414.0, 73.0), time_s=2.0, altitude_m=200.0)         # velocity from the last good fix
    assert f3.vel_enu_mps[:2] == pytest.approx((2.0, 0.0))


def test_gps_input_flags_what_the_fix_does_not_carry():
    """The bridge's fixes carry no measured vertical speed: GPS_INPUT must say so (ignore flag VEL_VERT), not send
    vd = 0 as measured (with EK3_SRC1_VELZ 3 the EKF's altitude then lags every climb). The first fix has no
    horizontal velocity either (one position): VEL_HORIZ flagged too, and its speed accuracy sent as the bridge's
    largest speed (ArduPilot keeps the last value of a flagged field, so the accuracy must say 'unknown')."""
    br = EstimateBridge(lambda x, y: (47.0 + y * 1e-5, 8.0 + x * 1e-5), (0.0, 0.0), ground_amsl_m=400.0)

    class Est:
        def __init__(self, x):
            self.x_m, self.y_m, self.yaw_rad, self.status, self.cov_xy_m2 = x, 2.0, None, "ok", np.eye(2)

    first = br.fix(Est(1.0), time_s=0.0, altitude_m=100.0)
    m = msgs.gps_input(first, assess(first, 0.0, FixPolicy()), 1.7e9)
    assert m.ignore_flags == mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_VERT | mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ
    assert m.speed_accuracy == pytest.approx(br.max_speed_mps)
    second = br.fix(Est(3.0), time_s=0.25, altitude_m=100.0)
    m = msgs.gps_input(second, assess(second, 0.0, FixPolicy()), 1.7e9)
    assert m.ignore_flags == mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_VERT and m.ve == pytest.approx(8.0)
    measured = _fix(vel_up_valid=True)
    m = msgs.gps_input(measured, assess(measured, 0.0, FixPolicy()), 1.7e9)
    assert m.ignore_flags == 0 and m.vd == pytest.approx(0.5)


def test_demo_fix_accuracies_are_honest_and_pass_ardupilot_gps_checks():
    """The demo (0.5 m noise per axis, 4 Hz, a 150 m circle at 10 m/s): once the velocity filter has settled
    (2 s), every fix passes ArduPilot's default horizontal checks (EKF3 pre-arm: accuracy < 5 m, arming hdop <
    GPS_HDOP_GOOD 1.4), and the speed accuracy is honest: the velocity's true per-axis RMS error (noise and the
    filter's lag in the turn, 1 s x 0.67 m/s^2) lies between half the median reported and the median reported,
    which passes EKF3's 1 m/s."""
    from aerial_loc_env.mavlink.cli import SITL_HOME, DemoTrack

    demo = DemoTrack(SITL_HOME, seed=0)
    br = EstimateBridge(demo.world_to_latlon, (0.0, 0.0), ground_amsl_m=demo.ground_amsl_m)
    steps = demo.steps()
    qualities, errors = [], []
    for _ in range(400):
        step = next(steps)
        fix = br.fix(step.estimate, time_s=step.time_s, altitude_m=step.altitude_m)
        if step.time_s >= 2.0:
            qualities.append(assess(fix, 0.0, FixPolicy()))
            phase = demo.speed_mps * step.time_s / demo.radius_m
            truth = (-demo.speed_mps * math.sin(phase), demo.speed_mps * math.cos(phase))
            errors.append(np.subtract(fix.vel_enu_mps[:2], truth))
    assert all(q.h_acc_m < 5.0 and q.hdop < 1.4 for q in qualities)
    rms = float(np.sqrt(np.mean(np.square(errors))))
    reported = float(np.median([q.speed_acc_mps for q in qualities]))
    assert 0.5 * reported <= rms <= reported < 1.0, (rms, reported)


def test_scenario_ground_height_is_never_silently_sea_level():
    from aerial_loc_env.mavlink.cli import ground_amsl_m

    class Map:
        pass

    with pytest.raises(ConfigError, match="--ground-amsl-m"):
        ground_amsl_m(None, Map(), "AerialLoc/Small-v3")
    declared = Map()
    declared.ground_amsl_m = 37.5
    assert ground_amsl_m(None, declared, "x") == 37.5 and ground_amsl_m(584.0, declared, "x") == 584.0
    with pytest.raises(ConfigError, match="-500, 9000"):
        ground_amsl_m(float("nan"), Map(), "x")
