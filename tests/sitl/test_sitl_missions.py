"""The missions: the autopilot's parameters for each feed, the flight plan over the map, every input checked
before SITL starts, a death of SITL or of the bridge reported at once, and the missions flown in ArduPilot SITL
(../shared/sitl/, loopback only; skipped with the reason where it is absent) with the camera rendered at SITL's
truth. Every time and figure is on SITL's clock (its dataflash log, SYSTEM_TIME), so the missions fly sped up:
SITL's --speedup, the bridge's send rate and the camera's frames all follow SITL's clock."""

from __future__ import annotations

import math

import numpy as np
import pytest

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.sitl.missions import (
    MISSION_CAMERA_HZ,
    MISSIONS,
    PLANE_APPROACH_ALT_M,
    PLANE_GLIDE_M,
    PLANE_MISSIONS,
    check_map_fits,
    check_scenario,
    fly_mission,
    mission_items,
    mission_spec,
    sitl_home,
)
from aerial_loc_env.sitl.report import summary

# SITL's --speedup in the default run (CI): the highest that held every figure below, run after run, on a loaded
# 2-core machine (docs/mavlink.md, Verification). A stall of the bridge lasts `speedup` times longer on SITL's
# clock: ArduPilot's 245 ms GPS limit is 122 ms of real time at 2
COPTER_SPEEDUP = 2.0
PLANE_SPEEDUP = 2.0


def test_home_is_the_map_centre():
    gym = pytest.importorskip("gymnasium")
    import aerial_loc_env.env  # noqa: F401

    env = gym.make("AerialLoc/Small-v3")
    om = env.unwrapped.database
    lat, lon, alt, hdg = (float(v) for v in sitl_home(om, 30.0, 90.0).split(","))
    x, y = (float(np.ravel(v)[0]) for v in om.latlon_to_world(lat, lon))
    assert math.hypot(x - om.width_m / 2, y - om.height_m / 2) < 0.01 and (alt, hdg) == (30.0, 90.0)
    env.close()


def test_mission_parameters_follow_ardupilots_external_nav_recipe():
    """ExternalNav: no GNSS, MAVLink visual odometry, EKF position from ExternalNav; the denial keeps ArduPilot's
    GPS sources in set 1 and puts ExternalNav in set 2 (GPS / non-GPS transitions); an unknown mission is a
    clear error before anything starts."""
    ext, den, gps = (MISSIONS[k].params for k in ("external-nav", "gnss-denial", "gps-input"))
    assert (ext["GPS1_TYPE"], ext["VISO_TYPE"], ext["EK3_SRC1_POSXY"], ext["EK3_SRC1_VELXY"]) == (0, 1, 6, 0)
    assert "GPS1_TYPE" not in den and (den["VISO_TYPE"], den["EK3_SRC2_POSXY"]) == (1, 6) and MISSIONS[
        "gnss-denial"].deny_gnss
    assert gps["GPS1_TYPE"] == 14 and "VISO_TYPE" not in gps
    assert {m.message for m in MISSIONS.values()} == {"gps_input", "vision_position_estimate"}
    with pytest.raises(ConfigError, match="external-nav"):
        fly_mission("AerialLoc/Small-v3", "template-ncc", ground_amsl_m=30.0, mission="optical-flow")
    with pytest.raises(ConfigError, match="--mission 'external-nav' for --vehicle plane: use one of gps-input"):
        mission_spec("plane", "external-nav")


def test_plane_missions_land_and_deny_through_gps_switching():
    """Both plane missions end in ArduPlane's landing sequence (RTL too: RTL_AUTOLAND 2) and disarm after
    touchdown; the denial keeps SITL's GPS as GPS1, the primary, feeds the vision fix to GPS2 and leaves the switch
    to the autopilot (GPS_AUTO_SWITCH 4: the primary while it has a 3D fix), no source-set command; the plan's
    last items are DO_LAND_START, the approach point north of home at its height, NAV_LAND at home."""
    from pymavlink import mavutil

    gps, den = (PLANE_MISSIONS[k] for k in ("gps-input", "gnss-denial"))
    assert gps.params["GPS1_TYPE"] == 14 and gps.gps_id == 0 and not gps.deny_gnss
    assert "GPS1_TYPE" not in den.params and (den.params["GPS2_TYPE"], den.params["GPS_AUTO_SWITCH"],
                                              den.params["GPS_PRIMARY"]) == (14, 4, 0)
    assert den.deny_gnss and den.gps_id == 1 and den.deny_source_set is None and den.message == "gps_input"
    for m in (gps, den):
        assert (m.params["RTL_AUTOLAND"], m.params["LAND_DISARMDELAY"]) == (2, 5)

    mav = mavutil.mavlink
    items = mission_items("plane", _FlatMap(1200.0, 1400.0), 250e-5, 600e-5, 80.0, 200.0, camera_min_alt_m=40.0)
    assert items[0] == (mav.MAV_CMD_NAV_TAKEOFF, 0.0, 0.0, 100.0, 15.0)     # half the loop's 200 m
    assert [it[0] for it in items[-3:]] == [mav.MAV_CMD_DO_LAND_START, mav.MAV_CMD_NAV_WAYPOINT, mav.MAV_CMD_NAV_LAND]
    _, lat, lon, alt, _ = items[-2]
    assert (lat * 1e5, lon * 1e5, alt) == pytest.approx((250.0 + PLANE_GLIDE_M, 600.0, PLANE_APPROACH_ALT_M))
    assert items[-1][1:4] == (250e-5, 600e-5, 0.0)


def test_copter_leg_is_ground_metres_east_of_home(vincenty_m):
    """The copter's leg east and back: its waypoints the given ground metres due east of home on the WGS84
    ellipsoid (world.maps.geo, the map's own convention), as plain floats for the mission upload."""
    from pymavlink import mavutil

    lat0, lon0 = -35.363261, 149.165230
    items = mission_items("copter", _FlatMap(400.0, 400.0), lat0, lon0, 80.0, 100.0)
    assert [it[0] for it in items] == [mavutil.mavlink.MAV_CMD_NAV_TAKEOFF, *[mavutil.mavlink.MAV_CMD_NAV_WAYPOINT] * 2,
                                       mavutil.mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH]
    for (_, lat, lon, alt, _), east_m in zip(items[1:3], (80.0, 5.0), strict=True):
        assert type(lat) is float and type(lon) is float and alt == 100.0
        assert vincenty_m(lat0, lon0, lat, lon) == pytest.approx(east_m, abs=1e-6)
        assert vincenty_m(lat0, lon0, lat0, lon) == pytest.approx(east_m, abs=1e-6)      # due east


class _FlatMap:
    """1 m = 1e-5 deg around (0, 0): enough for the plan's geometry."""

    def __init__(self, width_m: float, height_m: float) -> None:
        self.width_m, self.height_m = width_m, height_m

    def world_to_latlon(self, x, y):
        return np.array([y * 1e-5]), np.array([x * 1e-5])

    def latlon_to_world(self, lat, lon):
        return np.array([lon * 1e5]), np.array([lat * 1e5])


def test_scenario_is_checked_before_anything_starts():
    """An old version names the current id (gymnasium's DeprecatedEnv was a traceback); a map-file scenario
    (RealMap: gym.make(id, path=...)), an old version of one too, says that sitl takes no map file and which ids
    it flies; short names resolve to the id."""
    pytest.importorskip("gymnasium")
    assert check_scenario("small") == check_scenario("Small") == "AerialLoc/Small-v3"
    with pytest.raises(ConfigError, match="--scenario: scenario 'AerialLoc/Small-v0' is not registered: this "
                                          "version of the package has 'AerialLoc/Small-v3'"):
        check_scenario("AerialLoc/Small-v0")
    with pytest.raises(ConfigError) as exc:
        check_scenario("AerialLoc/RealMap-v2")
    msg = str(exc.value)
    assert "`aerial-loc sitl` takes no map file; it flies the procedural-city scenarios: " in msg
    flies = msg.rsplit(": ", 1)[1].split(", ")
    assert {"AerialLoc/Small-v3", "AerialLoc/PaperShadows-v2"} <= set(flies)
    assert not {"AerialLoc/RealMap-v2", "AerialLoc/RealPair-v2"} & set(flies)     # both fly over the user's files
    with pytest.raises(ConfigError, match=r"^--scenario AerialLoc/RealMap-v1 \(now AerialLoc/RealMap-v2\): flies over "
                                          r"a map file .*takes no map file"):      # not 'use RealMap-v2'
        check_scenario("AerialLoc/RealMap-v1")


def test_map_too_small_for_the_flight_is_refused():
    """The plane's loop sits 300 m inside the map and its final runs 1 km north of home: a map without room for
    them (Small-v3, 400 m) is refused before SITL starts, naming the size needed and a scenario that has it."""
    check_map_fits("AerialLoc/PaperShadows-v2", "plane", _FlatMap(1200.0, 1400.0), 80.0)
    check_map_fits("AerialLoc/Small-v3", "copter", _FlatMap(400.0, 400.0), 80.0)
    with pytest.raises(ConfigError, match=r"--scenario AerialLoc/Small-v3: its map is 400 x 400 m, and the plane's "
                                          r"flight .* needs at least 1000 x 1350 m; .*PaperShadows-v2"):
        check_map_fits("AerialLoc/Small-v3", "plane", _FlatMap(400.0, 400.0), 80.0)
    with pytest.raises(ConfigError, match="copter's flight .*160 m leg east"):
        check_map_fits("AerialLoc/Small-v3", "copter", _FlatMap(400.0, 400.0), 160.0)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"speedup": 0.0}, r"--speedup 0.0: must be in \[0.1, 20\]"),
    ({"speedup": math.nan}, r"--speedup nan: must be in \[0.1, 20\]"),
    ({"speedup": -1.0}, r"--speedup -1.0: must be in \[0.1, 20\]"),
    ({"ground_amsl_m": math.nan}, r"--ground-amsl-m nan: must be a finite height in \[-500, 9000\] m AMSL"),
    ({"ground_amsl_m": 1e9}, r"--ground-amsl-m 1000000000.0: must be a finite height in \[-500, 9000\]"),
    ({"wind": (40.0, 270.0)}, "--wind .*0..30 m/s"),
    ({"scenario": "AerialLoc/Small-v0"}, "has 'AerialLoc/Small-v3'"),
    ({"scenario": "AerialLoc/RealMap-v2"}, "takes no map file"),
    ({"vehicle": "plane", "scenario": "AerialLoc/Small-v3"}, "needs at least 1000 x 1350 m"),
])
def test_fly_mission_refuses_bad_inputs_before_sitl_starts(fake_sitl, kwargs, message):
    """Each of these reached SITL or the bridge's thread before (a floating point exception, a thread traceback
    and a 120 s wait for the EKF, a DeprecatedEnv traceback): now a clear error, and SITL never runs."""
    pytest.importorskip("gymnasium")
    args = {"scenario": "AerialLoc/Small-v3", "ground_amsl_m": 30.0, **kwargs}
    with pytest.raises(ConfigError, match=message):
        fly_mission(args.pop("scenario"), "template-ncc", sitl_dir=fake_sitl, **args)
    assert not (fake_sitl / "runs").exists()


@pytest.mark.timeout(120)
def test_sitl_dying_during_the_mission_is_reported_at_once(fake_sitl):
    """A SITL that dies (here before it ever speaks) ends the mission with its exit status and its last words,
    within the monitor's next look, not after the wait for its heartbeat or a waypoint runs out."""
    pytest.importorskip("aerial_loc_env.estimators.registry", reason="the agents are not available")
    (fake_sitl / "arducopter").write_text("#!/bin/sh\nsleep 1.5\necho 'Floating point exception'\nexit 136\n")
    with pytest.raises(AerialLocError, match=r"SITL \(arducopter\) died: exit code 136; the end of its output:\n"
                                             r"Floating point exception"):
        fly_mission("AerialLoc/Small-v3", "template-ncc", ground_amsl_m=30.0, sitl_dir=fake_sitl, timeout_s=3600.0)


@pytest.mark.timeout(120)
def test_bridge_failing_during_the_mission_is_reported_at_once(fake_sitl, monkeypatch):
    """The bridge runs in a thread of its own: its error ends the mission at once, named (it was a thread
    traceback, then a two-minute wait for the EKF)."""
    pytest.importorskip("aerial_loc_env.estimators.registry", reason="the agents are not available")
    from aerial_loc_env.mavlink import cli as mav_cli

    def broken(*args, **kwargs):
        raise ConfigError("--connect: the link could not be opened")

    monkeypatch.setattr(mav_cli, "run", broken)
    with pytest.raises(AerialLocError, match="the bridge stopped: --connect: the link could not be opened"):
        fly_mission("AerialLoc/Small-v3", "template-ncc", ground_amsl_m=30.0, sitl_dir=fake_sitl, timeout_s=3600.0)


def _kept_pace(s: dict, speedup: float) -> None:
    """SITL ran at its --speedup and the camera kept its MISSION_CAMERA_HZ on SITL's clock: frames are due every
    1 / MISSION_CAMERA_HZ s and taken at the next truth sample (SIM_STATE at 20 Hz, 0.05 s later at most)."""
    assert s["speedup_achieved"] > 0.9 * speedup, s["speedup_achieved"]
    assert s["camera_frames"] and s["vision_fix_s"] / s["camera_frames"] <= 1.0 / MISSION_CAMERA_HZ + 0.05, \
        s["frame_interval_s"]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_copter_mission_on_the_vision_fix(mission_sitl):
    """ArduCopter, GPS_INPUT (GPS1_TYPE 14), default arming checks, SITL at COPTER_SPEEDUP: the EKF takes the fix,
    the vehicle arms in AUTO, takes off to 100 m, flies 80 m east and back over the map, returns and lands; the
    camera follows SITL's truth and template matching localizes. Bound on the EKF's horizontal error against the
    truth: the agent's fix sigma (3 m) plus the fix's age at cruise speed (one 0.25 s frame + one 0.1 s send tick
    at 10 m/s = 3.5 m, in SITL's seconds whatever the speedup): RMSE under 2 sigma + 3.5 m, max under
    5 sigma + 3.5 m."""
    sitl_dir = mission_sitl("arducopter")
    r = fly_mission("AerialLoc/Small-v3", "template-ncc", ground_amsl_m=30.0, sitl_dir=sitl_dir,
                    speedup=COPTER_SPEEDUP)
    s = summary(r)
    print(s, [t for _, t in r["texts"]][-12:])
    _kept_pace(s, COPTER_SPEEDUP)
    texts = [t for _, t in r["texts"]]
    assert any("EKF3 IMU0 is using GPS" in t for t in texts), texts
    assert {1, 2, 3} <= set(r["reached"]), r["reached"]          # every waypoint reached, then RTL landed
    horiz_abs = 16      # EKF_STATUS_FLAGS.EKF_POS_HORIZ_ABS
    # on the legs the EKF has an absolute position throughout (landing has no fix: the camera is too low)
    assert r["leg_flags"] and all(f & horiz_abs for _, f in r["leg_flags"]), "the EKF lost its position"
    errors = np.array(r["leg_errors_m"])      # the AUTO legs on the vision fix (take-off and landing: pad/none)
    assert len(errors) > 100
    rmse = float(np.sqrt(np.mean(errors ** 2)))
    assert rmse < 2 * 3.0 + 3.5 and errors.max() < 5 * 3.0 + 3.5, (rmse, errors.max())
    # ArduPilot's own interval between GPS updates (GPA.Delta) through its own health rule, from arming (its
    # pre-arm check gates arming on the same rule) to the end: never unhealthy in flight (the fixes carry their
    # frame's capture time, so a resend's interval is 0 and a frame's its camera interval)
    assert len(r["gps_gaps_ms"]) > 100 and s["gps_unhealthy"] == 0, s["gps_fix_interval_ms"]




def test_template_matching_estimates_down_to_its_smallest_template():
    """template-ncc's altitudes: down to where the footprint's short side spans MIN_PX_ACROSS pixels of the map's
    own grid (its fine level, PaperShadows' 0.25 m pixels: 10 m; without it, 1 m working pixels: 40 m), up to
    twice the nominal; a frame outside is a clear error naming the range; agents built for the nominal altitude
    (MCL) keep a factor 2 either way."""
    gym = pytest.importorskip("gymnasium")
    import aerial_loc_env.env  # noqa: F401
    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.estimators.template_matching import TemplateMatchingAgent, TemplateMatchingParams

    env = gym.make("AerialLoc/PaperShadows-v2")
    obs, _ = env.reset(seed=0)
    briefing = env.unwrapped.briefing
    agent = make_agent("template-ncc")
    assert agent.altitude_range_m(briefing) == pytest.approx((10.0, 400.0))
    coarse = TemplateMatchingAgent(TemplateMatchingParams(fine_level=False))
    assert coarse.altitude_range_m(briefing) == pytest.approx((40.0, 400.0))
    assert make_agent("mcl-shadow-aware").altitude_range_m(briefing) == pytest.approx((100.0, 400.0))
    agent.reset(briefing, seed=0)
    agent.step({**obs, "altitude": np.array([45.0], np.float32)})           # in range: estimates
    with pytest.raises(ConfigError, match=r"8.0 m is outside the 10.0-400.0 m"):
        agent.step({**obs, "altitude": np.array([8.0], np.float32)})
    env.close()


def test_template_matching_fine_level_tracks_a_final_below_the_working_floor():
    """A plane's final on PaperShadows-v2 (south at 22 m/s, crabbing 13 deg, 5 Hz, 60 m down to 12 m): the fine
    level (the map's 0.25 m pixels) keeps fixing below the working level's 40 m, each fix within a working
    pixel (1 m) of the truth and reported with fix_std_m scaled to the finer pixel (3 m x 0.25 / 1); a first
    frame below 40 m is not matched (no first fix from a small template)."""
    gym = pytest.importorskip("gymnasium")
    import aerial_loc_env.env  # noqa: F401
    from aerial_loc_env.env.external import ExternalFlight, ExternalPose
    from aerial_loc_env.estimators.registry import make_agent

    env = gym.make("AerialLoc/PaperShadows-v2", flight={"rate_hz": 5.0})
    flight, agent = ExternalFlight(env), make_agent("template-ncc")
    yaw = -math.pi / 2 + math.radians(13.0)
    obs, _ = flight.reset(ExternalPose(600.0, 700.0, yaw, 30.0, 0.0), seed=0)
    agent.reset(flight.briefing, seed=0)
    est = agent.step(obs)
    assert est.status == "dead_reckoning" and "only while tracking" in est.extras["reason"], est
    n = 100                                       # 440 m in 20 s
    poses = [ExternalPose(600.0, 900.0 - 4.4 * i, yaw, 60.0 - 48.0 * i / n, 0.2 * i) for i in range(n)]
    obs, _ = flight.reset(poses[0], seed=0)
    agent.reset(flight.briefing, seed=0)
    low = []                                      # (fix, error m, reported sigma m) below the working floor
    for i, pose in enumerate(poses):
        if i:
            obs, _ = flight.observe(pose)
        est = agent.step(obs)
        if float(obs["altitude"][0]) < 40.0:
            low.append((est.status == "ok", math.hypot(est.x_m - pose.x_m, est.y_m - pose.y_m),
                        math.sqrt(float(np.max(np.linalg.eigvalsh(est.cov_xy_m2))))))
    fixes = [e for ok, e, _ in low if ok]
    assert len(fixes) >= 10 and max(fixes) < 1.0, (len(fixes), fixes)
    assert all(sigma == pytest.approx(0.75) for ok, _, sigma in low if ok)
    env.close()




@pytest.mark.timeout(600)
@pytest.mark.parametrize("mission", ["external-nav", "gnss-denial"])
def test_copter_mission_on_external_nav(mission, long_mission):
    """ExternalNav (VISION_POSITION_ESTIMATE, VISO_TYPE 1): with no GNSS at all, or after SITL's GPS is switched
    off at the top of the climb and the EKF moved to source set 2. Same flight and the same bound as the
    GPS_INPUT mission (the fix sigma 3 m: RMSE < 2 sigma + 3.5 m, max < 5 sigma + 3.5 m on the legs). About
    3.5 min each at real time: run in CI only with AERIAL_LOC_SITL_ALL=1 (keeps CI within its budget)."""
    sitl_dir = long_mission("arducopter", "3.5 min each")
    r = fly_mission("AerialLoc/Small-v3", "template-ncc", ground_amsl_m=30.0, sitl_dir=sitl_dir, mission=mission)
    s = summary(r)
    print(s)
    texts = [t for _, t in r["texts"]]
    assert {1, 2, 3} <= set(r["reached"]), (r["reached"], texts[-12:])
    assert r["leg_flags"] and all(f & 16 for _, f in r["leg_flags"]), "the EKF lost its position on the legs"
    errors = np.array(r["leg_errors_m"])
    assert len(errors) > 100
    rmse = float(np.sqrt(np.mean(errors ** 2)))
    assert rmse < 2 * 3.0 + 3.5 and errors.max() < 5 * 3.0 + 3.5, (rmse, errors.max())
    if mission == "external-nav":
        assert any("is using external nav" in t for t in texts), texts
        assert not r["gps_gaps_ms"]               # no GNSS at all
    else:
        t_d = r["t_denied"]
        assert any("is using GPS" in t for t in texts) and t_d is not None
        # SITL's GPS really went away, the autopilot accepted the source switch, and the legs (all after the
        # denial) kept an absolute position: the EKF navigated on ExternalNav, not on GNSS
        assert any(f < 3 for t, f in r["gps_fix"] if t > t_d + 2.0), "SITL's GPS still had a fix"
        assert (42007, 0) in {(c, res) for _, c, res in r["acks"]}, r["acks"]
        stopped = [t for t, x in r["texts"] if "stopped aiding" in x]
        first_leg = next(t for t, x in r["texts"] if x.startswith("Mission: 2"))
        assert first_leg >= t_d - 1.0 and all(t > first_leg for t in stopped)
        assert s["vision_fix_s"] > 20.0


def _plane_loop(r: dict, s: dict) -> list[str]:
    """The plane kept pace, took its first camera frame before the loop, started every mission item in order and
    flew the loop with an absolute position within the tracking bound (``_plane_loop_and_landing``); returns the
    autopilot's messages."""
    _kept_pace(s, PLANE_SPEEDUP)
    texts = [t for _, t in r["texts"]]
    loop_start = next(t for t, x in r["texts"] if x.startswith(f"Mission: {r['loop_start']}"))
    first_frame = next(st[0] for st in r["steps"] if st[1] == "camera")
    assert first_frame < loop_start, (first_frame, loop_start)
    # every item started, in order (STATUSTEXT "Mission: k ..."; MISSION_ITEM_REACHED is not enough: ArduPlane
    # reported the loop's last waypoint as item 6, the DO_LAND_START run right after it)
    started = list(dict.fromkeys(int(x.split()[1]) for x in texts if x.startswith("Mission: ")))
    assert started == list(range(1, r["last_wp"] + 1)), (started, texts[-12:])     # (a cut's resume repeats one)
    loop = [f for _, f in r["leg_flags"]]
    assert loop and all(f & 16 for f in loop), sorted(set(loop))
    errors = np.array(r["leg_errors_m"])
    assert len(errors) > 500
    rmse = float(np.sqrt(np.mean(errors ** 2)))
    assert rmse < 2 * 3.0 + 7.7 and errors.max() < 5 * 3.0 + 7.7, (rmse, errors.max())
    return texts


def _plane_loop_and_landing(r: dict, s: dict) -> None:
    """What both plane missions must show: the loop on the established vision fix, the landing, touchdown.

    The camera gives frames from the agent's lowest altitude (template-ncc on PaperShadows-v2: 10 m, its fine level; a
    first fix only from the working level's 40 m); the take-off climbs on to 100 m and the first leg climbs out to the
    loop's 200 m (about 40 s in all): the agent's acquisition from the scenario's 15 m prior (seed 0 puts it 20.5 m
    off, and before a first fix a match within 3 prior sigmas is taken, false ones too; the first frame must come on
    time: a reset that made the map's level again there once put it 2 s late and the estimator 50-100 m off,
    docs/mavlink.md) happens there. The loop (from its first corner, at 200 m, to DO_LAND_START) is tracking, and its
    bound is the copter's: the agent's fix sigma (3 m) plus the fix's age at cruise speed (0.25 s frame + 0.1 s tick
    at 22 m/s = 7.7 m): RMSE under 2 sigma + 7.7 m, max under 5 sigma + 7.7 m. (Until this mission the camera started
    at 120 m after a 15 s climb with no fix, the acquisition fell into the legs, and their max, 25-52 m against a
    bound of 3 prior sigmas + 7.7 m, was that start's error plus the EKF's drift over the climb: not a tracking
    figure, and not bounded by the prior's sigma.)
    Touchdown, after about 6 s of dead reckoning below the camera's range: the EKF's error within 3 times the
    horizontal accuracy it claims there (sqrt of its north + east position variances, XKV1: a consistent
    Gaussian error exceeds that with probability e^-9 = 0.01 % if circular, 0.27 % if all along one axis;
    measured 1-5 m against 7-10 m), and the touchdown within that of the final's line across it (the autopilot
    steers the line it believes it is on; along the line the point is the flare's, about 30 m short, and where it
    stops, within a few metres)."""
    texts = _plane_loop(r, s)
    # the landing sequence flown to touchdown and the autopilot's own disarm; the camera down to the agent's
    # lowest altitude (within the altimeter's noise), then dead reckoning to the ground
    assert any(x.startswith(f"Mission: {r['last_wp']} Land") for x in texts), texts[-12:]
    assert any("Auto disarmed" in x for x in texts), texts[-12:]
    td = s["touchdown"]
    assert s["mission_completed"] and td["landed"], td
    assert abs(td["last_fix_alt_m"] - r["camera_min_alt_m"]) < 5.0, td
    # the EKF on dead reckoning from the last fix to touchdown (no wind): within 3 x its own claimed accuracy
    assert td["ekf_error_m"] < 3 * td["ekf_sigma_m"] and abs(td["cross_m"]) < 3 * td["ekf_sigma_m"], td


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_plane_mission_on_the_vision_fix(mission_sitl):
    """ArduPlane, GPS_INPUT as GPS1, plane.parm's airframe (22 m/s cruise), the paper city at 200 m: arms in AUTO
    on the pad fix, takes off north with no fix from leaving the pad until the camera is in range (the agent's
    lowest altitude, 10 m, matching from 40 m), flies a 600 m x 800 m loop over the map, then the landing
    sequence (DO_LAND_START, an approach point 1 km north at 100 m, NAV_LAND at home heading south: the vision
    fix down to 10 m, about 6 s of dead reckoning below) to touchdown and disarm; SITL at PLANE_SPEEDUP, every
    figure on its clock.

    With a vision cut in the loop (issue 27's target): 5 s into the loop's first leg the fix is withheld for 20 s
    of SITL's clock (GPS_INPUT: no fix). The plane's vision failsafe (the shipped Lua script) must act within 5 s,
    from SITL's own log: its mode to LOITER; and when the fix is back the mission resumes (AUTO) within 5 s, the
    loop then flown to the end with the bounds below (the cut and the 10 s after the fix came back are the
    failsafe's, not the loop's tracking)."""
    sitl_dir = mission_sitl("arduplane")
    r = fly_mission("AerialLoc/PaperShadows-v2", "template-ncc", ground_amsl_m=30.0, sitl_dir=sitl_dir,
                    vehicle="plane", speedup=PLANE_SPEEDUP, vision_cut=("loop", 20.0))
    s = summary(r)
    print(s)
    texts = [t for _, t in r["texts"]]
    assert any("EKF3 IMU0 is using GPS" in t for t in texts), texts
    _plane_loop_and_landing(r, s)
    assert s["vision_fix_s"] > 130.0          # the loop (less the cut) and the approach on the camera fix
    # GPS_INPUT flows throughout, with no fix during the climb and the cut: ArduPilot's GPS health rule on its own
    # update intervals never fails in flight (from arming, which its pre-arm check gates on the same rule)
    assert len(r["gps_gaps_ms"]) > 500 and s["gps_unhealthy"] == 0, s["gps_fix_interval_ms"]
    # the failsafe timeline, seconds from the first fix withheld, from SITL's log
    cut = s["vision_cut"]
    assert 19.0 <= cut["fix_back_s"] <= 21.0 and cut["gps_no_fix_s"] < 1.0, cut
    assert cut["modes"][0][1] == "LOITER" and cut["reaction_s"] < 5.0, cut
    assert any(x.startswith("Vision failsafe: fix lost") for _, x in cut["messages"]), cut["messages"]
    back_to_auto = [t for t, m in cut["modes"] if m == "AUTO" and t >= cut["fix_back_s"]]
    assert back_to_auto and back_to_auto[0] - cut["fix_back_s"] < 5.0, cut
    assert cut["drift_m"] and all(math.isfinite(e) for _, e, _ in cut["drift_m"])


@pytest.mark.timeout(600)
def test_plane_gnss_denial(long_mission):
    """ArduPlane on SITL's GPS (GPS1, the primary) with the vision fix as GPS2 (GPS_INPUT, gps_id 1,
    GPS_AUTO_SWITCH 4): SITL's GPS is switched off at the loop's first corner and the autopilot takes GPS2 by
    itself; the loop, approach and landing as in the GPS_INPUT mission, with its bounds. About 2.2 min at
    PLANE_SPEEDUP: in CI only with AERIAL_LOC_SITL_ALL=1."""
    sitl_dir = long_mission("arduplane", "2.2 min")
    r = fly_mission("AerialLoc/PaperShadows-v2", "template-ncc", ground_amsl_m=30.0, sitl_dir=sitl_dir,
                    vehicle="plane", mission="gnss-denial", speedup=PLANE_SPEEDUP)
    s = summary(r)
    print(s)
    t_d = r["t_denied"]
    assert t_d is not None and any("is using GPS" in t for _, t in r["texts"])
    # SITL's GPS (GPS_RAW_INT: the first GPS) really went, and the loop after it kept an absolute position
    assert any(f < 3 for t, f in r["gps_fix"] if t > t_d + 2.0), "SITL's GPS still had a fix"
    _plane_loop_and_landing(r, s)
    assert s["denied_ekf_max_m"] < 5 * 3.0 + 7.7 and s["vision_fix_s"] > 100.0, s


@pytest.mark.timeout(600)
@pytest.mark.parametrize("wind", [(5.0, 270.0), (8.0, 270.0, 1.5)], ids=["5-steady", "8-gusting"])
def test_plane_crosswind_mission(wind, long_mission):
    """ArduPlane's GPS_INPUT mission in a crosswind from the west (SITL's SIM_WIND_SPD / DIR, and its turbulence
    SIM_WIND_TURB for the gusts), across the loop's long legs and the final: the plane crabs, the env's odometry
    carries the lateral speed (from SITL's stream), the agent keeps its track. The loop is held to the no-wind
    bounds (fix sigma 3 m, the fix's age at cruise speed: RMSE < 2 sigma + 7.7 m, max < 5 sigma + 7.7 m) and the
    mission completes (touchdown, disarm), the camera fix going on below the working level's 40 m (the fine
    level) so that the dead reckoning under SITL's wind gradient is short. In the steady wind the touchdown lies
    within issue 27's 5 m across the line; in the gusts it is recorded, not bounded: ArduPlane's own glide in
    gusts can float the flare far past the point with the EKF on track (docs/mavlink.md, the crosswind
    touchdown).
    About 2.4 min each at PLANE_SPEEDUP: in CI only with AERIAL_LOC_SITL_ALL=1."""
    sitl_dir = long_mission("arduplane", "2.4 min each")
    r = fly_mission("AerialLoc/PaperShadows-v2", "template-ncc", ground_amsl_m=30.0, sitl_dir=sitl_dir,
                    vehicle="plane", speedup=PLANE_SPEEDUP, wind=wind)
    s = summary(r)
    print(s)
    assert s["wind"] == wind
    texts = _plane_loop(r, s)
    assert not any(x.startswith("Vision failsafe: fix lost, LOITER") for x in texts), texts
    assert any("Auto disarmed" in x for x in texts) and s["touchdown"]["landed"], s["touchdown"]
    assert s["touchdown"]["last_fix_alt_m"] < 20.0, s["touchdown"]
    if len(wind) == 2:      # steady
        assert abs(s["touchdown"]["cross_m"]) < 5.0, s["touchdown"]

