"""``aerial-loc mavlink`` end to end on a real scenario: env, agent, bridge and sender over UDP."""

from __future__ import annotations

import io
import socket
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink2

from aerial_loc_env.mavlink import cli as mav_cli

gym = pytest.importorskip("gymnasium")


def test_scenario_agent_stream_lands_on_the_map():
    pytest.importorskip("aerial_loc_env.estimators.registry", reason="the agents are not available")
    from aerial_loc_env.env import world_to_action  # noqa: F401  (registers the scenarios)

    env = gym.make("AerialLoc/Small-v0")
    env.reset(seed=3)
    om = env.unwrapped.briefing.orthomap
    corners = np.array([om.world_to_latlon(x, y) for x in (0.0, om.width_m) for y in (0.0, om.height_m)])
    centre = om.world_to_latlon(om.width_m / 2, om.height_m / 2)
    env.close()

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    args = mav_cli.build_parser().parse_args([
        "--scenario", "AerialLoc/Small-v0", "--agent", "dead-reckoning", "--seed", "3", "--speed", "10",
        "--connect", f"udpout:127.0.0.1:{sock.getsockname()[1]}", "--message", "gps,odometry",
        "--ground-amsl-m", "400"])
    out = io.StringIO()
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("rc", mav_cli.run(args, out=out)))
    runner.start()
    parser = mavlink2.MAVLink(None)
    msgs = []
    drain_until = None
    while drain_until is None or time.monotonic() < drain_until:   # until the run ends, then 0.2 s more
        if drain_until is None and not runner.is_alive():
            drain_until = time.monotonic() + 0.2
        try:
            data, _ = sock.recvfrom(65536)
        except TimeoutError:
            continue
        msgs += parser.parse_buffer(data) or []
    runner.join()
    sock.close()
    assert result["rc"] == 0
    assert out.getvalue().strip().splitlines()[-1].startswith("done:")
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
