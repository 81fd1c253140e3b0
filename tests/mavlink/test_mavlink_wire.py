"""The bridge on the wire: real UDP sockets on loopback, decoded by independent MAVLink implementations.

- the reference C library (generated from common.xml by pymavlink's mavgen, compiled with gcc into tmp_path):
  CRC_EXTRA, MAVLink 2 framing and extension fields, signatures (it verifies them with the secret key);
- libmav (Auterion's C++ library, which builds its message set and CRC_EXTRA from the XML at runtime).
Expected values are computed here from the fix by hand (units, NED/FRD conversions), not by the bridge's code.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np
import pytest

from aerial_loc_env.mavlink.fix import FixPolicy, GeoOrigin, PoseFix
from aerial_loc_env.mavlink.selfcheck import DecoderUnavailable, LibmavCollector, build_c_verifier, c_verifier
from aerial_loc_env.mavlink.sender import MavlinkSender, SenderConfig, signing_secret

RATE_HZ = 10.0
SESSION_S = 3.0
JUMP_AT_S = 1.5
SYSID, COMPID, GPS_ID = 42, 197, 1
ORIGIN = GeoOrigin(47.3977419, 8.5455938, 408.5)
FIX_A = PoseFix(time_s=0.0, lat_deg=47.4008, lon_deg=8.5440, alt_amsl_m=608.25, east_m=-120.5,
                north_m=340.25, up_m=200.0, vel_enu_mps=(3.0, -4.0, 0.5), vel_up_valid=True, yaw_rad=2.5,
                cov_en_m2=(4.0, -1.0, 6.25), v_std_m=0.5, yaw_std_rad=0.05, speed_std_mps=0.8)
# 60 m east of where A's velocity predicts B: a jump, so reset_counter must go 0 -> 1
FIX_B = PoseFix(**{**FIX_A.__dict__, "time_s": JUMP_AT_S, "east_m": -120.5 + 4.5 + 60.0,
                   "north_m": 340.25 - 6.0, "lat_deg": 47.40075, "lon_deg": 8.54485})
FRESH = FixPolicy(stale_after_s=30.0, lost_after_s=60.0)   # keep the quality constant for exact field checks
MESSAGES = ("gps_input", "vision_position_estimate", "odometry")


def _config(port: int, **kw) -> SenderConfig:
    base = dict(connect=f"udpout:127.0.0.1:{port}", messages=MESSAGES, rate_hz=RATE_HZ, system_id=SYSID,
                component_id=COMPID, gps_id=GPS_ID, gps_yaw=True, origin_period_s=1.0)
    base.update(kw)
    return SenderConfig(**base)


def _fly(config: SenderConfig, seconds: float, wait=None) -> tuple[float, float]:
    """Stream FIX_A, then FIX_B from JUMP_AT_S; returns the (unix) time window of the session."""
    t_unix0 = time.time()
    with MavlinkSender(config, policy=FRESH, origin=ORIGIN) as sender:
        sender.publish(FIX_A)
        if wait is not None:
            wait()
        t0 = time.monotonic()
        time.sleep(max(0.0, JUMP_AT_S - (time.monotonic() - t0)))
        sender.publish(FIX_B)
        time.sleep(max(0.0, seconds - (time.monotonic() - t0)))
    return t_unix0, time.time()


def _heading(fix: PoseFix) -> float:
    """Compass heading (CW from north, radians) of an ENU yaw, by the definition in ARCHITECTURE.md."""
    return math.atan2(math.cos(fix.yaw_rad), math.sin(fix.yaw_rad))   # = pi/2 - yaw, wrapped


def _which(north: float, east: float) -> PoseFix:
    for fix in (FIX_A, FIX_B):
        if abs(north - fix.north_m) < 1e-3 and abs(east - fix.east_m) < 1e-3:
            return fix
    raise AssertionError(f"position ({north}, {east}) is neither fix A nor fix B")


H_ACC = math.sqrt(4.0 + 6.25)


@pytest.fixture(scope="module")
def c_exe(tmp_path_factory):
    try:
        return build_c_verifier(tmp_path_factory.mktemp("mavlink_c"))
    except DecoderUnavailable as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def c_session(c_exe):
    """One 3 s session at 10 Hz with all messages, decoded by the C library."""
    with c_verifier(c_exe, SESSION_S + 0.6) as run:
        window = _fly(_config(run.port), SESSION_S)
    assert run.returncode == 0
    return run.frames, window


def _of(frames, msgid):
    return [f for f in frames if f["msgid"] == msgid]


def test_c_all_frames_valid_mavlink2_with_our_ids_and_contiguous_seq(c_session):
    frames, _ = c_session
    assert len(frames) > 3 * SESSION_S * RATE_HZ * 0.9
    assert {f["result"] for f in frames} == {"ok"}        # CRC (with CRC_EXTRA from the XML) verified
    assert {f["magic"] for f in frames} == {0xFD}         # MAVLink 2 framing
    assert {(f["sysid"], f["compid"]) for f in frames} == {(SYSID, COMPID)}
    seqs = [f["seq"] for f in frames]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:], strict=False))   # nothing lost or reordered
    assert not any(f["signed"] for f in frames)


def test_c_gps_input_fields_and_units(c_session):
    frames, (t_start, t_end) = c_session
    gps = _of(frames, 232)
    assert gps
    for f in gps:
        fix = FIX_A if f["lat"] == round(FIX_A.lat_deg * 1e7) else FIX_B
        assert (f["lat"], f["lon"]) == (round(fix.lat_deg * 1e7), round(fix.lon_deg * 1e7))     # degE7
        assert f["alt"] == pytest.approx(fix.alt_amsl_m, abs=1e-4)                              # m AMSL
        assert (f["vn"], f["ve"], f["vd"]) == pytest.approx((-4.0, 3.0, -0.5))                  # NED m/s
        assert f["ignore_flags"] == 0                  # a measured vertical speed: nothing ignored
        assert (f["gps_id"], f["fix_type"], f["satellites_visible"]) == (GPS_ID, 3, FRESH.satellites_ok)
        assert f["horiz_accuracy"] == pytest.approx(H_ACC, rel=1e-6)
        assert f["hdop"] == pytest.approx(H_ACC / FRESH.hdop_ref_m, rel=1e-6)
        assert f["vert_accuracy"] == pytest.approx(0.5) and f["speed_accuracy"] == pytest.approx(0.8)
        # extension field: yaw in cdeg, 1..36000, clockwise from north
        assert f["yaw"] == round(math.degrees(_heading(fix)) * 100) % 36000
        # GPS week time agrees with the message's Unix time_usec, and that with the wall clock
        gps_unix = 315_964_800 + f["time_week"] * 604_800 + f["time_week_ms"] / 1000.0 - 18
        assert gps_unix == pytest.approx(f["time_usec"] / 1e6, abs=1e-3)
        assert t_start - 0.01 <= f["time_usec"] / 1e6 <= t_end + 0.01
    usecs = [f["time_usec"] for f in gps]
    assert all(b >= a for a, b in zip(usecs, usecs[1:], strict=False))       # capture times: never backwards


def test_c_send_rate_within_10_percent_and_heartbeats(c_session):
    frames, _ = c_session
    t = np.array([f["t"] for f in _of(frames, 232)])
    rate = (len(t) - 1) / (t[-1] - t[0])
    gaps = np.diff(t)
    print(f"GPS_INPUT: {rate:.3f} Hz over {t[-1] - t[0]:.2f} s; interval std {gaps.std() * 1e3:.2f} ms, "
          f"max {gaps.max() * 1e3:.1f} ms")
    assert rate == pytest.approx(RATE_HZ, rel=0.10)
    beats = _of(frames, 0)
    assert len(beats) in (3, 4)                       # 1 Hz over 3 s
    kinds = {(b["type"], b["autopilot"], b["system_status"], b["mavlink_version"]) for b in beats}
    assert kinds == {(18, 8, 4, 3)}   # ONBOARD_CONTROLLER, AUTOPILOT_INVALID, STATE_ACTIVE, MAVLink 2
    tb = [b["t"] for b in beats]
    assert (tb[-1] - tb[0]) / (len(tb) - 1) == pytest.approx(1.0, rel=0.10)   # 1 Hz


def test_c_vision_position_estimate_ned_covariance_and_reset_counter(c_session):
    frames, _ = c_session
    vpe = _of(frames, 102)
    assert len(vpe) >= SESSION_S * RATE_HZ * 0.9
    for f in vpe:
        fix = _which(f["x"], f["y"])                  # x = north, y = east
        assert f["z"] == pytest.approx(-fix.up_m)     # z down
        assert (f["roll"], f["pitch"]) == (0.0, 0.0)
        assert f["yaw"] == pytest.approx(_heading(fix), abs=1e-6)
        cov = f["covariance"]
        assert (cov[0], cov[1], cov[6], cov[11], cov[20]) == pytest.approx((6.25, -1.0, 4.0, 0.25, 0.05 ** 2))
        assert f["reset_counter"] == (0 if fix is FIX_A else 1)
    counters = [f["reset_counter"] for f in vpe]
    assert counters[0] == 0 and counters[-1] == 1 and counters == sorted(counters)


def test_c_odometry_frames_quaternion_body_velocity(c_session):
    frames, _ = c_session
    odo = _of(frames, 331)
    assert odo
    for f in odo:
        fix = _which(f["x"], f["y"])
        h = _heading(fix)
        assert (f["frame_id"], f["child_frame_id"]) == (20, 12)   # MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD
        assert f["q"] == pytest.approx([math.cos(h / 2), 0.0, 0.0, math.sin(h / 2)], abs=1e-6)
        fwd = np.array([math.cos(h), math.sin(h)])                       # nose direction in (north, east)
        right = np.array([-math.sin(h), math.cos(h)])
        v_ne = np.array([-4.0, 3.0])
        assert (f["vx"], f["vy"], f["vz"]) == pytest.approx((fwd @ v_ne, right @ v_ne, -0.5), abs=1e-5)
        assert all(math.isnan(f[k]) for k in ("rollspeed", "pitchspeed", "yawspeed"))   # not estimated
        assert (f["pose_covariance"][0], f["pose_covariance"][20]) == pytest.approx((6.25, 0.0025))
        assert f["velocity_covariance"][0] == pytest.approx(0.8 ** 2)
        assert f["estimator_type"] == 2                         # MAV_ESTIMATOR_TYPE_VISION (extension)
        assert f["quality"] == round(100 * FRESH.quality_ref_m / (FRESH.quality_ref_m + H_ACC))
        assert f["reset_counter"] == (0 if fix is FIX_A else 1)


def test_c_set_gps_global_origin_degE7_and_mm(c_session):
    frames, (t_start, t_end) = c_session
    origins = _of(frames, 48)
    assert len(origins) in (3, 4)                     # origin_period_s = 1
    for f in origins:
        assert (f["latitude"], f["longitude"], f["altitude"]) == (473977419, 85455938, 408500)
        assert t_start - 0.01 <= f["time_usec"] / 1e6 <= t_end + 0.01   # extension field


def test_c_signed_frames_verify_and_wrong_key_fails(c_exe):
    key = "correct horse battery staple"
    secret = signing_secret(key)
    with c_verifier(c_exe, 1.3, secret) as run:
        _fly(_config(run.port, signing_key=key, signing_link_id=7), 1.0)
    frames = run.frames
    assert len(frames) >= 20
    assert {f["result"] for f in frames} == {"ok"} and all(f["signed"] for f in frames)
    assert {f["link_id"] for f in frames} == {7}
    ts = [f["sign_ts"] for f in frames]
    assert all(b > a for a, b in zip(ts, ts[1:], strict=False))
    assert abs(ts[-1] / 1e5 + 1_420_070_400 - time.time()) < 60.0    # MAVLink's acceptance window

    with c_verifier(c_exe, 0.8, signing_secret("another key")) as bad:
        _fly(_config(bad.port, signing_key=key), 0.5)
    assert bad.frames and {f["result"] for f in bad.frames} == {"bad_signature"}


@pytest.fixture(scope="module")
def libmav_session():
    pytest.importorskip("libmav", reason="libmav (pip install libmav) is the independent C++ decoder")
    collector = LibmavCollector()
    done = threading.Event()

    def wait():
        collector.wait_connection(3.0)
        done.set()

    try:
        _fly(_config(collector.port, signing_key="libmav session key"), 2.5, wait=wait)
    finally:
        collector.close()
    assert done.is_set()
    return collector


def test_libmav_decodes_every_field(libmav_session):
    gps = libmav_session.of("GPS_INPUT")
    odo = libmav_session.of("ODOMETRY")
    vpe = libmav_session.of("VISION_POSITION_ESTIMATE")
    assert len(gps) >= 15 and len(odo) >= 15 and len(vpe) >= 15
    for _, _, header, f in gps:
        assert (header["sysid"], header["compid"]) == (SYSID, COMPID)
        assert header["incompat_flags"] & 1                 # signed frames: libmav must skip the signature
        fix = FIX_A if f["lat"] == round(FIX_A.lat_deg * 1e7) else FIX_B
        assert (f["lat"], f["lon"]) == (round(fix.lat_deg * 1e7), round(fix.lon_deg * 1e7))
        assert (f["vn"], f["ve"], f["vd"]) == pytest.approx((-4.0, 3.0, -0.5))
        assert f["yaw"] == round(math.degrees(_heading(fix)) * 100) % 36000
        assert (f["gps_id"], f["fix_type"], f["ignore_flags"]) == (GPS_ID, 3, 0)
        gps_unix = 315_964_800 + f["time_week"] * 604_800 + f["time_week_ms"] / 1000.0 - 18
        assert gps_unix == pytest.approx(f["time_usec"] / 1e6, abs=1e-3)
    for _, _, _, f in odo:
        fix = _which(f["x"], f["y"])
        assert (f["frame_id"], f["child_frame_id"], f["estimator_type"]) == (20, 12, 2)
        assert f["reset_counter"] == (0 if fix is FIX_A else 1)
        assert len(f["pose_covariance"]) == 21 and f["pose_covariance"][6] == pytest.approx(4.0)
    counters = [f["reset_counter"] for *_, f in vpe]
    assert counters[0] == 0 and counters[-1] == 1 and counters == sorted(counters)
    origin = libmav_session.of("SET_GPS_GLOBAL_ORIGIN")
    assert origin and origin[0][3]["altitude"] == 408500 and origin[0][3]["time_usec"] > 0
