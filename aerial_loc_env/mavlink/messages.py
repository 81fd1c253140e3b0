"""Frame conversions and the MAVLink messages the bridge sends, built from a fix and its assessed quality.

World frame (ARCHITECTURE.md) is ENU: x east, y north, z up, yaw CCW from east. MAVLink's local frames are NED
(x north, y east, z down) and body FRD, yaw clockwise from north. Every conversion between the two lives here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from aerial_loc_env.mavlink.fix import FixQuality, GeoOrigin, PoseFix
from aerial_loc_env.mavlink.timebase import gps_week_ms

MESSAGE_KINDS = ("gps_input", "vision_position_estimate", "odometry", "external_position")
ODOMETRY_FRAMES = {  # name -> (frame_id, child_frame_id)
    "local_frd": (mavlink2.MAV_FRAME_LOCAL_FRD, mavlink2.MAV_FRAME_BODY_FRD),   # ArduPilot and PX4
    "local_ned": (mavlink2.MAV_FRAME_LOCAL_NED, mavlink2.MAV_FRAME_BODY_FRD),   # PX4 only
}
UNKNOWN_ANGLE_VAR_RAD2 = math.pi ** 2   # variance reported for an attitude component nobody estimates
TILT_VAR_RAD2 = math.radians(5.0) ** 2  # nadir gimbal: roll/pitch are not estimated; level flight assumed


def wrap_pi(angle_rad: float) -> float:
    """Wrap to [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def enu_to_ned(east: float, north: float, up: float) -> tuple[float, float, float]:
    return north, east, -up


def yaw_enu_to_heading(yaw_rad: float) -> float:
    """ENU yaw (CCW from east) -> MAVLink yaw / compass heading (CW from north), wrapped to [-pi, pi)."""
    return wrap_pi(math.pi / 2.0 - yaw_rad)


def heading_to_cdeg(heading_rad: float) -> int:
    """GPS_INPUT.yaw: centidegrees in 1..36000 (36000 = north; 0 means 'not available')."""
    cdeg = int(round(math.degrees(heading_rad) * 100.0)) % 36000
    return 36000 if cdeg == 0 else cdeg


def deg_e7(deg: float) -> int:
    return int(round(deg * 1e7))


def cov_en_to_ne(cov_en_m2: tuple[float, float, float]) -> np.ndarray:
    """(var_e, cov_en, var_n) -> 2x2 covariance in (north, east) order."""
    var_e, cov_en, var_n = cov_en_m2
    return np.array([[var_n, cov_en], [cov_en, var_e]])


def upper_triangle(cov: np.ndarray) -> list[float]:
    """Row-major upper-right triangle of a 6x6 covariance: the 21 floats of MAVLink's covariance fields."""
    rows, cols = np.triu_indices(6)
    return [float(v) for v in np.asarray(cov, dtype=np.float64)[rows, cols]]


def pose_covariance(fix: PoseFix, quality: FixQuality) -> np.ndarray:
    """6x6 covariance of (x_north, y_east, z_down, roll, pitch, yaw) with the quality's inflation applied.

    An unusable (lost) fix gets MAVLink's 'unknown' marker: NaN in the first element.
    """
    if not quality.usable:
        cov = np.zeros((6, 6))
        cov[0, 0] = math.nan
        return cov
    k2 = quality.inflation ** 2
    cov = np.zeros((6, 6))
    cov[:2, :2] = cov_en_to_ne(fix.cov_en_m2) * k2
    cov[2, 2] = quality.v_acc_m ** 2
    cov[3, 3] = cov[4, 4] = TILT_VAR_RAD2
    cov[5, 5] = UNKNOWN_ANGLE_VAR_RAD2 if fix.yaw_std_rad is None else fix.yaw_std_rad ** 2 * k2
    return cov


def heading_of(fix: PoseFix) -> float:
    """The fix's MAVLink heading, 0 (north) when the estimator has none (its variance then says so)."""
    return 0.0 if fix.yaw_rad is None else yaw_enu_to_heading(fix.yaw_rad)


def ned_to_body_frd(vec_ned: Sequence[float], heading_rad: float) -> tuple[float, float, float]:
    """Rotate an NED vector into body FRD for a level vehicle with the given heading (CW from north)."""
    c, s = math.cos(heading_rad), math.sin(heading_rad)
    n, e, d = vec_ned
    return c * n + s * e, -s * n + c * e, d


def quaternion_from_heading(heading_rad: float) -> list[float]:
    """(w, x, y, z) of a level attitude with the given NED yaw."""
    return [math.cos(heading_rad / 2.0), 0.0, 0.0, math.sin(heading_rad / 2.0)]


# --- message builders ---------------------------------------------------------------------------------------

def heartbeat() -> mavlink2.MAVLink_heartbeat_message:
    """An onboard controller (not an autopilot): what a vision companion computer announces at 1 Hz."""
    return mavlink2.MAVLink_heartbeat_message(
        mavlink2.MAV_TYPE_ONBOARD_CONTROLLER, mavlink2.MAV_AUTOPILOT_INVALID, 0, 0,
        mavlink2.MAV_STATE_ACTIVE, 3)


def gps_input(fix: PoseFix, quality: FixQuality, unix_s: float, *, gps_id: int = 0,
              send_yaw: bool = False) -> mavlink2.MAVLink_gps_input_message:
    """GPS_INPUT for ArduPilot's MAVLink GPS driver, stamped ``unix_s``: the fix's capture time (the frame's), not
    the send time (the sender resends a fix between frames with its own stamp). ArduPilot reads only the GPS week
    time (``time_usec`` is not used), corrects it for transport jitter and fuses the fix that much in the past,
    minus ``GPSn_DELAY_MS``. Ignore flags say what the fix does not carry: the vertical speed unless measured
    (``vel_up_valid``: a vd of 0 sent as measured makes an EKF fusing GPS vertical velocity lag every climb),
    the horizontal velocity while the bridge has none (``vel_horiz_valid``; its speed accuracy is then sent as
    huge, since ArduPilot keeps the last velocity and accuracy of a field flagged ignored)."""
    week, week_ms = gps_week_ms(unix_s)
    ignore = 0 if fix.vel_up_valid else mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_VERT
    if not fix.vel_horiz_valid:
        ignore |= mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_HORIZ | mavlink2.GPS_INPUT_IGNORE_FLAG_VEL_VERT
    vn, ve, vd = enu_to_ned(*fix.vel_enu_mps)
    yaw_cdeg = heading_to_cdeg(yaw_enu_to_heading(fix.yaw_rad)) if send_yaw and fix.yaw_rad is not None else 0
    return mavlink2.MAVLink_gps_input_message(
        int(unix_s * 1e6), gps_id, ignore, week_ms, week, quality.fix_type,
        deg_e7(fix.lat_deg), deg_e7(fix.lon_deg), float(fix.alt_amsl_m),
        quality.hdop, quality.vdop, vn, ve, vd,
        quality.speed_acc_mps, quality.h_acc_m, quality.v_acc_m, quality.satellites, yaw_cdeg)


def vision_position_estimate(fix: PoseFix, quality: FixQuality, time_usec: int,
                             reset_counter: int) -> mavlink2.MAVLink_vision_position_estimate_message:
    x, y, z = enu_to_ned(fix.east_m, fix.north_m, fix.up_m)
    return mavlink2.MAVLink_vision_position_estimate_message(
        time_usec, x, y, z, 0.0, 0.0, heading_of(fix), upper_triangle(pose_covariance(fix, quality)),
        reset_counter)


def odometry(fix: PoseFix, quality: FixQuality, time_usec: int, reset_counter: int,
             frames: str = "local_frd") -> mavlink2.MAVLink_odometry_message:
    """ODOMETRY: pose in the local frame (north-aligned), velocity in body FRD (the child frame).

    Angular rates are not estimated: NaN (PX4 skips non-finite rates; ArduPilot reads none of them).
    """
    frame_id, child_frame_id = ODOMETRY_FRAMES[frames]
    x, y, z = enu_to_ned(fix.east_m, fix.north_m, fix.up_m)
    heading = heading_of(fix)
    v_body = ned_to_body_frd(enu_to_ned(*fix.vel_enu_mps), heading)
    vel_cov = np.diag([quality.speed_acc_mps ** 2] * 3 + [UNKNOWN_ANGLE_VAR_RAD2] * 3)
    return mavlink2.MAVLink_odometry_message(
        time_usec, frame_id, child_frame_id, x, y, z, quaternion_from_heading(heading), *v_body,
        math.nan, math.nan, math.nan,
        upper_triangle(pose_covariance(fix, quality)), upper_triangle(vel_cov), reset_counter,
        mavlink2.MAV_ESTIMATOR_TYPE_VISION, quality.odometry_quality)


def external_position_estimate(fix: PoseFix, quality: FixQuality, sent_s: float, processing_s: float,
                               target_system: int = 1,
                               target_component: int = 1) -> mavlink2.MAVLink_command_int_message:
    """MAV_CMD_EXTERNAL_POSITION_ESTIMATE (COMMAND_INT, global frame): a low-rate global fix for an autopilot that
    is dead reckoning. param1 the send time in the sender's time domain (seconds, as small as it can be kept: the
    autopilot corrects it for transport jitter), param2 the processing time (capture to send, seconds: the
    autopilot dates the fix that much earlier), param3 the horizontal accuracy (1 sigma, m), x/y lat/lon degE7,
    z NaN (no altitude: ArduPilot accepts only the global frame without one)."""
    return mavlink2.MAVLink_command_int_message(
        target_system, target_component, mavlink2.MAV_FRAME_GLOBAL, mavlink2.MAV_CMD_EXTERNAL_POSITION_ESTIMATE,
        0, 0, float(sent_s), float(max(0.0, processing_s)), float(quality.h_acc_m), math.nan,
        deg_e7(fix.lat_deg), deg_e7(fix.lon_deg), math.nan)


def set_gps_global_origin(origin: GeoOrigin, time_usec: int,
                          target_system: int = 0) -> mavlink2.MAVLink_set_gps_global_origin_message:
    """EKF origin for a vehicle without GNSS: degE7 and millimetres AMSL."""
    return mavlink2.MAVLink_set_gps_global_origin_message(
        target_system, deg_e7(origin.lat_deg), deg_e7(origin.lon_deg), int(round(origin.alt_amsl_m * 1000.0)),
        time_usec)
