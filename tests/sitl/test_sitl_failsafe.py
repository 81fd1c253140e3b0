"""The vision-cut missions without a flight: where a cut starts and every bad --vision-cut a clear error before
SITL starts, ArduPilot's GPS health rule on logged update intervals, the failsafe timeline read from a record,
and the plane's Lua failsafe shipped and wired into its parameters."""

from __future__ import annotations

import math

import pytest

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.sitl.cli import parse_vision_cut
from aerial_loc_env.sitl.missions import (
    CUT_LEG_DELAY_S,
    PLANE_MISSIONS,
    PLANE_SCRIPTS,
    check_vision_cut,
    cut_start,
    fly_mission,
)
from aerial_loc_env.sitl.report import failsafe_timeline, gps_unhealthy, summary


def test_vision_cut_points_and_bad_values():
    """'loop' starts a few seconds into the loop's first leg, 'approach' at the final (plane: NAV_LAND; copter:
    RTL), a number at that item; a bad point, a duration outside (0, 120] s or a malformed option is one clear
    error naming the form."""
    assert cut_start("plane", "loop", 3, 8) == (3, CUT_LEG_DELAY_S["plane"])
    assert cut_start("plane", "approach", 3, 8) == (8, 0.0) and cut_start("copter", "approach", 2, 4) == (4, 0.0)
    assert cut_start("plane", 5, 3, 8) == (5, 0.0)
    assert check_vision_cut(("loop", 20)) == ("loop", 20.0) and check_vision_cut(("4", 5)) == (4, 5.0)
    assert parse_vision_cut("approach,12.5") == ("approach", 12.5) and parse_vision_cut(None) is None
    for bad in (("takeoff", 20), ("loop", 0), ("loop", 500), ("loop", math.nan), ("0", 5)):
        with pytest.raises(ConfigError, match="--vision-cut .*AT,SECONDS"):
            check_vision_cut(bad)
    for text in ("loop", "loop,x", "loop,1,2"):
        with pytest.raises(ConfigError, match="--vision-cut .*AT,SECONDS"):
            parse_vision_cut(text)


def test_vision_cut_beyond_the_mission_is_refused_before_sitl_starts(fake_sitl):
    pytest.importorskip("gymnasium")
    with pytest.raises(ConfigError, match="the copter's mission has items 1 to 4"):
        fly_mission("AerialLoc/Small-v3", "template-ncc", ground_amsl_m=30.0, sitl_dir=fake_sitl,
                    vision_cut=(9, 20.0))
    assert not (fake_sitl / "runs").exists()


def test_gps_health_follows_ardupilots_rule():
    """AP_GPS::is_healthy's timing: two update intervals over 245 ms in a row, or a running average (0.98/0.02)
    of intervals over 215 ms; a negative interval (a stamp earlier than the last) wraps and counts as delayed.
    Capture-stamped resends (0 ms) between 4 Hz frames (250-300 ms), after the pad's 10 Hz fixes, are healthy."""
    frames = [(0.1 * k, 100) for k in range(50)] + [(5.0 + 0.1 * k, 280 if k % 3 == 2 else 0) for k in range(300)]
    assert gps_unhealthy(frames) == []
    two_late = frames[:60] + [(6.0, 300), (6.1, 260)] + frames[60:]
    assert [why for _, why in gps_unhealthy(two_late)][:1] == ["2 delayed updates in a row (260 ms)"]
    wrapped = frames[:50] + [(5.0, 280), (5.1, -12), (5.2, 100)]
    assert gps_unhealthy(wrapped) == [(5.1, "2 delayed updates in a row (-12 ms)")]
    slow = [(0.25 * k, 230) for k in range(100)]               # a 4.3 Hz GPS, every frame sent once
    assert gps_unhealthy(slow) and "average" in gps_unhealthy(slow)[0][1]


def test_failsafe_timeline_from_a_record():
    """A made-up record on SITL's clock: camera fixes to 100 s, the cut 100-120 s, back at 120.25 s; the plane
    switches to LOITER (mode 12) at 101.2 s and back to AUTO (10) at 122.4 s; the timeline counts from the first
    withheld fix and reads the drift each second since the last fix, with the claimed accuracy."""
    steps = ([(100.0 - 0.25 * k, "camera", 1.0) for k in range(40, 0, -1)] + [(100.0, "camera", 1.0)]
             + [(100.25 + 0.25 * k, "cut", 1.0) for k in range(80)] + [(120.25, "camera", 1.0)])
    record = {"vehicle": "plane", "steps": sorted(steps),
              "modes": [(50.0, 10, 0), (101.2, 12, 0), (122.4, 10, 0)],
              "log_messages": [(101.2, "Vision failsafe: fix lost, LOITER"), (122.4, "Vision failsafe: fix back, AUTO"),
                               (122.4, "Mission: 4 WP")],
              "gps_status": [(99.0, 3), (100.3, 1), (120.3, 3)], "ekf_status": [(99.0, 1), (104.0, 5), (121.0, 1)],
              "timed_errors": [(100.0 + 0.1 * k, 0.5 + 0.1 * k) for k in range(220)],
              "ekf_var_m2": [(100.0 + k, 1.0 + k) for k in range(25)]}
    tl = failsafe_timeline(record)
    assert tl["reaction_s"] == pytest.approx(0.95) and tl["modes"][0] == (0.95, "LOITER")
    assert tl["fix_back_s"] == pytest.approx(20.0) and tl["resumed_s"] == pytest.approx(22.15)
    assert tl["gps_no_fix_s"] == pytest.approx(0.05) and tl["gps_fix_back_s"] == pytest.approx(20.05)
    assert tl["ekf_status_changes"] == [(3.75, "+vert_vel"), (20.75, "-vert_vel")]
    assert tl["last_fix_before_s"] == pytest.approx(-0.25)
    assert tl["drift_m"][10] == (10, pytest.approx(10.5), pytest.approx(math.sqrt(11.0), abs=0.01))
    assert tl["messages"][0] == (pytest.approx(0.95), "Vision failsafe: fix lost, LOITER")


def test_ekf_status_changes_in_words():
    """XKF4.SS bits as ArduPilot names them: the plane's EKF3 in the cut went from glitching GPS to dead
    reckoning without an absolute position, then back to using the GPS."""
    from aerial_loc_env.sitl.report import ekf_status_change

    assert ekf_status_change(115519, 377135) == "-horiz_pos_abs -pred_horiz_pos_abs +dead_reckoning"
    assert ekf_status_change(377135, 123711) == ("+horiz_pos_abs +pred_horiz_pos_abs +using_gps -dead_reckoning")


def test_plane_runs_the_shipped_lua_failsafe():
    """The plane's missions enable scripting and carry the failsafe script, which switches to LOITER and back to
    AUTO and leaves the landing sequence alone."""
    assert all(m.params["SCR_ENABLE"] == 1 for m in PLANE_MISSIONS.values())
    (script,) = PLANE_SCRIPTS
    text = script.read_text()
    assert script.suffix == ".lua" and "MODE_LOITER = 12" in text and "MODE_AUTO = 10" in text
    assert "DO_LAND_START = 189" in text and "gps:status(gps:primary_sensor())" in text


def test_summary_reports_the_cut_and_the_latency():
    record = {"horizontal_errors_m": [1.0], "gps_gaps_ms": [0, 250], "leg_errors_m": [1.0], "texts": [],
              "ekf_flags": [], "fix_to_arm_s": 1.0, "flight_s": 10.0, "vision_cut": ("loop", 20.0), "reached": [],
              "fix_latency_s": [0.01, 0.02, 0.03], "gps_deltas_ms": [(0.9, 100), (1.0, 0), (1.1, 250)],
              "external_position": {"sent": 5, "acks": {0: 3, 4: 2}}}
    s = summary(record)
    assert s["vision_cut"] == {"at": "loop", "seconds": 20.0} and s["gps_unhealthy"] == 0
    assert s["fix_latency_ms"]["median"] == pytest.approx(20.0) and s["external_position"]["acks"] == {0: 3, 4: 2}


def test_wind_with_gusts_sets_sitl_turbulence():
    """--wind SPEED,FROM_DEG[,GUST]: the gusts' std goes to SIM_WIND_TURB (SITL's turbulence, m/s); two values
    keep the steady wind of before."""
    from aerial_loc_env.sitl.cli import parse_wind

    assert parse_wind("8,270,1.5") == (8.0, 270.0, 1.5) and parse_wind("5,90") == (5.0, 90.0)


def test_track_picture_marks_the_cut_and_names_the_wind(tmp_path):
    """The report of a windy run with a vision cut writes its picture (matplotlib present) and its summary carries
    the cut's timeline."""
    pytest.importorskip("matplotlib")
    from test_sitl_report import _record

    from aerial_loc_env.sitl.report import write_outputs

    record = _record()
    record["steps"] = record["steps"][:4] + [(s[0], "cut", *s[2:]) for s in record["steps"][4:7]] \
        + record["steps"][7:]
    record.update(wind=(5.0, 270.0, 1.5), vision_cut=("loop", 0.75))
    paths = write_outputs(record, tmp_path / "run")
    assert (tmp_path / "run" / "track.png") in paths and (tmp_path / "run" / "track.png").stat().st_size > 1000
    assert summary(record)["vision_cut"]["fix_back_s"] == pytest.approx(0.75)


def test_gps_health_runs_its_average_from_the_first_update_and_reports_from_the_window():
    """ArduPilot's running average runs from boot: a window that starts on a long interval (the pad fix's last to
    the first camera fix) after a run of 100 ms updates is healthy, where an average started at the window would
    take that one interval for it and call the next dozens of updates unhealthy; delays before the window are not
    reported, those inside are."""
    pad = [(0.1 * k, 100) for k in range(100)]
    camera = [(10.0, 261)] + [(10.1 + 0.1 * k, 0 if k % 2 == 0 else 200) for k in range(200)]
    assert gps_unhealthy(pad + camera, 10.0) == []
    assert gps_unhealthy(camera, 10.0)[:1] == [(10.0, "average update interval 261 ms")]
    stalled = pad[:50] + [(5.0, 400), (5.1, 300)] + pad[52:] + camera
    assert gps_unhealthy(stalled, 10.0) == [] and gps_unhealthy(stalled)[:1] == [(5.1, "2 delayed updates in a row "
                                                                                    "(300 ms)")]
