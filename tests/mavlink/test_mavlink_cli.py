"""``aerial-loc mavlink`` end to end on a real scenario: env, agent, bridge and sender over UDP."""

from __future__ import annotations

import io
import math
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from aerial_loc_env.mavlink import cli as mav_cli

gym = pytest.importorskip("gymnasium")


def test_scenario_agent_stream_lands_on_the_map(run_mavlink_cli):
    pytest.importorskip("aerial_loc_env.estimators.registry", reason="the agents are not available")
    from aerial_loc_env.env import world_to_action  # noqa: F401  (registers the scenarios)

    env = gym.make("AerialLoc/Small-v3")
    env.reset(seed=3)
    om = env.unwrapped.briefing.orthomap
    corners = np.array([om.world_to_latlon(x, y) for x in (0.0, om.width_m) for y in (0.0, om.height_m)])
    centre = om.world_to_latlon(om.width_m / 2, om.height_m / 2)
    env.close()

    rc, printed, msgs = run_mavlink_cli([
        "--scenario", "AerialLoc/Small-v3", "--agent", "dead-reckoning", "--seed", "3", "--speed", "10",
        "--message", "gps,odometry", "--ground-amsl-m", "400"])
    assert rc == 0
    assert printed.strip().splitlines()[-1].startswith("done:")
    gps = [m for m in msgs if m.get_type() == "GPS_INPUT"]
    odo = [m for m in msgs if m.get_type() == "ODOMETRY"]
    origin = [m for m in msgs if m.get_type() == "SET_GPS_GLOBAL_ORIGIN"]
    assert len(gps) >= 5 and len(odo) == len(gps) and origin
    lat = np.array([m.lat for m in gps]) / 1e7
    lon = np.array([m.lon for m in gps]) / 1e7
    assert corners[:, 0].min() <= lat.min() and lat.max() <= corners[:, 0].max()
    assert corners[:, 1].min() <= lon.min() and lon.max() <= corners[:, 1].max()
    assert (origin[0].latitude, origin[0].longitude) == (round(float(np.ravel(centre[0])[0]) * 1e7),
                                                         round(float(np.ravel(centre[1])[0]) * 1e7))
    assert origin[0].altitude == 400_000                                     # ground at 400 m AMSL, in mm
    assert all(m.alt > 400.0 for m in gps)                                   # flying above it
    # the local frame about the map centre agrees with lat/lon: north offset in metres vs latitude offset
    north = np.array([m.x for m in odo])
    dlat_m = (lat - float(np.ravel(centre[0])[0])) * 111_132.0
    assert np.allclose(north, dlat_m, atol=0.02 * max(1.0, float(np.abs(north).max())) + 1.0)


@pytest.mark.slow
def test_follow_renders_at_the_simulators_truth_and_localizes():
    """A fake SITL streams SIM_STATE: on the ground at the map centre, then climbing and flying east, then down
    at 10 m. The bridge sends the take-off pad while the camera sees nothing, then the agent's estimates from
    frames rendered at the truth: the GPS_INPUT positions follow the true vehicle; below the agent's lowest
    altitude (template-ncc on Small-v3: 20 m) GPS_INPUT reports no fix."""
    pytest.importorskip("aerial_loc_env.estimators.registry", reason="the agents are not available")
    from aerial_loc_env.env import world_to_action  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.mavlink.selfcheck import free_udp_port

    env = gym.make("AerialLoc/Small-v3")
    om = env.unwrapped.orthomap
    env.close()
    ground = 30.0
    port = free_udp_port()
    args = mav_cli.build_parser().parse_args([
        "--scenario", "AerialLoc/Small-v3", "--agent", "template-ncc", "--follow", "--ground-amsl-m", str(ground),
        "--connect", f"udpin:127.0.0.1:{port}", "--duration-s", "11", "--quiet"])
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("rc", mav_cli.run(args, out=io.StringIO())))
    runner.start()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.01)
    ap = mavlink2.MAVLink(None, srcSystem=1, srcComponent=1)
    parser = mavlink2.MAVLink(None)
    beat = mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                              0, 0, mavlink2.MAV_STATE_STANDBY, 3)
    cx, cy = om.width_m / 2, om.height_m / 2

    def truth(t):       # 3 s on the ground, a 1 s jump to 100 m (a test, not a copter), 10 m/s east, then 10 m
        if t < 3.0:
            return cx, cy, 0.0
        return cx + 10.0 * max(0.0, t - 4.0), cy, 100.0 * min(1.0, t - 3.0) if t < 9.5 else 10.0

    gps = []
    t0 = time.monotonic()
    next_send = t0
    while runner.is_alive() and time.monotonic() - t0 < 20:
        now = time.monotonic()
        if now >= next_send:
            x, y, up = truth(now - t0)
            lat, lon = (float(np.ravel(v)[0]) for v in om.world_to_latlon(x, y))
            sock.sendto(beat.pack(ap) + mavlink2.MAVLink_sim_state_message(
                1.0, 0.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2, 0.0, 0.0, -9.8, 0.0, 0.0, 0.0, lat * 1e7, lon * 1e7,
                ground + up, 0.0, 0.0, 0.0, 10.0, 0.0, round(lat * 1e7), round(lon * 1e7)).pack(ap),
                ("127.0.0.1", port))
            next_send += 0.05
        try:
            data, _ = sock.recvfrom(65536)
        except TimeoutError:
            continue
        for m in parser.parse_buffer(data) or []:
            if m.get_type() == "GPS_INPUT":
                gps.append((time.monotonic() - t0, m))
    runner.join(10)
    sock.close()
    assert result.get("rc") == 0
    xy = [(t, *(float(np.ravel(v)[0]) for v in om.latlon_to_world(m.lat / 1e7, m.lon / 1e7)), m) for t, m in gps]
    pad = [(x, y) for t, x, y, m in xy if t < 2.9]    # (the bridge may take a second to start on a busy machine)
    assert pad and all(math.hypot(x - cx, y - cy) < 0.2 for x, y in pad)     # the take-off point
    flying = [(t, x, y, m) for t, x, y, m in xy if 6.0 < t < 9.4]
    assert len(flying) > 20
    # template matching at 1 m/px work resolution: within 3 fix sigmas (3 m) plus the 0.25 s frame age at 10 m/s
    errors = [math.hypot(x - truth(t)[0], y - truth(t)[1]) for t, x, y, _ in flying]
    assert np.median(errors) < 9.0 + 2.5 + 1.0, errors
    assert all(m.alt == pytest.approx(ground + 100.0, abs=4.0) for *_, m in flying)
    low = [m for t, _, _, m in xy if t > 10.0]
    assert low and all(m.fix_type < 3 for m in low), [m.fix_type for m in low]


def test_speed_zero_delivers_every_frame(run_mavlink_cli):
    """'--speed 0' (replay into a logger) must hand every frame's fix to the wire, not only the last one."""
    pytest.importorskip("aerial_loc_env.estimators.registry", reason="the agents are not available")
    rc, _, msgs = run_mavlink_cli([
        "--scenario", "AerialLoc/Small-v3", "--agent", "dead-reckoning", "--seed", "1", "--speed", "0",
        "--rate-hz", "200", "--ground-amsl-m", "30", "--quiet"])
    assert rc == 0
    # Small-v3: 15 s at 4 Hz = 60 steps, 61 frames; each frame's fix carries its own GPS time
    times = {(m.time_week, m.time_week_ms) for m in msgs if m.get_type() == "GPS_INPUT"}
    positions = {(m.lat, m.lon) for m in msgs if m.get_type() == "GPS_INPUT"}
    assert len(positions) >= 61, (len(positions), len(times))


def test_demo_track_is_ground_metres_on_the_wgs84_tangent_plane(vincenty_m):
    """The demo's world metres are east and north on the WGS84 tangent plane at its centre (world.maps.geo, the
    synthetic maps' convention): its 150 m circle is 150 ground metres from the centre, and lat/lon go back to the
    same metres (follow mode places the truth through them)."""
    demo = mav_cli.DemoTrack(mav_cli.SITL_HOME, seed=0)
    for x, y in ((150.0, 0.0), (0.0, -150.0), (106.066, 106.066), (-600.0, 420.0)):
        lat, lon = demo.world_to_latlon(x, y)
        assert type(lat) is float and type(lon) is float
        assert vincenty_m(demo.lat0, demo.lon0, lat, lon) == pytest.approx(math.hypot(x, y), abs=1e-5)
        assert demo.latlon_to_world(lat, lon) == pytest.approx((x, y), abs=1e-8)


def test_set_overrides_the_flown_scenario_and_is_refused_with_demo():
    """``--set KEY=VALUE`` reaches the env the bridge flies (the SITL missions set their camera's rate this way);
    with --demo (no scenario) it is refused, and an unknown key names itself."""
    from aerial_loc_env.errors import ConfigError

    run = mav_cli.ScenarioRun("AerialLoc/Small-v3", "dead-reckoning", 0, {"flight.rate_hz": 5})
    try:
        assert run.env.unwrapped.scenario.flight.rate_hz == 5.0
    finally:
        run.env.close()
    args = mav_cli.build_parser().parse_args(["--demo", "--set", "flight.rate_hz=5", "--duration-s", "0.1"])
    with pytest.raises(ConfigError, match="--demo flies no scenario"):
        mav_cli.run(args, out=io.StringIO())
    with pytest.raises(ConfigError, match="no_such_field"):
        mav_cli.ScenarioRun("AerialLoc/Small-v3", "dead-reckoning", 0, {"flight.no_such_field": 1})
