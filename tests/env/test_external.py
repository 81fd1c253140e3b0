"""The env driven by an external pose stream (env/external.py): frames where the vehicle is, shadows valid
anywhere on the map, the scenario's camera rate, odometry from the stream, clear errors off the map."""

from __future__ import annotations

import math

import numpy as np
import pytest

gym = pytest.importorskip("gymnasium")

from aerial_loc_env.env.external import ExternalFlight, ExternalPose  # noqa: E402
from aerial_loc_env.errors import AerialLocError, MapError  # noqa: E402

SCENARIO = "AerialLoc/Small-v3"    # 400 m city, 100 m altitude, 4 Hz camera, footprint 75 m x 50 m


def _env():
    import aerial_loc_env  # noqa: F401  (registers the scenarios)

    return gym.make(SCENARIO, observation={"info_shadow_mask": True})


def test_frame_at_the_envs_own_pose_matches_the_env():
    env = _env()
    _, info = env.reset(seed=3)
    truth = info["true_pose"]
    flight = ExternalFlight(_env())
    _, ext = flight.reset(ExternalPose(*truth, 0.0), seed=3)
    np.testing.assert_allclose(ext["true_pose"], truth)
    # same sun and field; the env sweeps a box, we sweep the whole map: shadow edges may move one grid pixel
    agree = np.mean(ext["shadow_mask"] == info["shadow_mask"])
    assert agree > 0.97 and ext["sun_azimuth_deg"] == info["sun_azimuth_deg"]


def test_shadows_are_valid_wherever_the_vehicle_goes():
    """The same pose renders the same shadows whatever the flight's start: shadows cover the whole map, not
    a track's box. (The env's own box leaves the far corner shadow-free.)"""
    far = ExternalPose(200.0, 210.0, 0.3, 100.0, 10.0)
    masks = []
    for start in ((60.0, 60.0), (340.0, 300.0)):
        flight = ExternalFlight(_env())
        flight.reset(ExternalPose(*start, 0.0, 100.0, 0.0), seed=5)
        masks.append(flight.observe(far)[1]["shadow_mask"])
    assert masks[0].any()                                     # downtown (the map centre) has shadows
    assert np.array_equal(masks[0], masks[1])


def test_camera_rate_and_odometry_come_from_the_stream():
    flight = ExternalFlight(_env())
    assert flight.period_s == pytest.approx(0.25)             # Small-v3: 4 Hz
    speed, alt = 10.0, 100.0
    stream = [ExternalPose(100.0 + speed * t, 200.0, 0.0, alt, t) for t in np.arange(0.0, 5.0, 0.05)]  # 20 Hz
    frames = []
    for k, pose in enumerate(stream):
        if k == 0:
            frames.append(flight.reset(pose, seed=1))
        elif flight.due(pose.t_s):
            frames.append(flight.observe(pose))
    assert len(frames) == 20                                  # 5 s at 4 Hz
    times = np.array([info["true_pose"][0] for _, info in frames])
    assert np.allclose(np.diff(times), speed * 0.25)          # a frame every 0.25 s of stream time
    noise = flight.briefing.odometry_noise
    odo = np.array([obs["odometry"] for obs, _ in frames[1:]])
    n = len(odo)
    # means within 4 standard errors of the scenario's noise; heading and altitude likewise
    assert abs(odo[:, 0].mean() - speed) < 4 * noise.speed_std_mps / math.sqrt(n) + 1e-6
    assert abs(odo[:, 1].mean()) < 4 * noise.yaw_rate_std_radps / math.sqrt(n)
    yaw = np.array([obs["yaw"][0] for obs, _ in frames])
    altitude = np.array([obs["altitude"][0] for obs, _ in frames])
    assert abs(yaw.mean()) < 4 * noise.heading_std_rad / math.sqrt(len(yaw))
    assert abs(altitude.mean() - alt) < 4 * noise.altitude_std_m / math.sqrt(len(altitude))
    assert flight.briefing.dt_s == pytest.approx(0.25) and flight.briefing.prior.kind == "gaussian"
    assert math.hypot(flight.briefing.prior.mean_xy_m[0] - 100.0, flight.briefing.prior.mean_xy_m[1] - 200.0) \
        < 5 * flight.briefing.prior.std_xy_m


def test_same_seed_same_stream_same_frames():
    poses = [ExternalPose(150.0 + 5 * k, 150.0, 0.1 * k, 100.0, 0.25 * k) for k in range(4)]
    runs = []
    for _ in range(2):
        flight = ExternalFlight(_env())
        out = [flight.reset(poses[0], seed=9)[0]["image"]]
        out += [flight.observe(p)[0]["image"] for p in poses[1:]]
        runs.append(out)
    assert all(np.array_equal(a, b) for a, b in zip(*runs, strict=True))


def test_off_the_map_and_on_the_ground_are_clear_errors():
    flight = ExternalFlight(_env())
    with pytest.raises(AerialLocError, match="reset"):
        flight.observe(ExternalPose(200.0, 200.0, 0.0, 100.0, 0.0))
    flight.reset(ExternalPose(200.0, 200.0, 0.0, 100.0, 0.0), seed=0)
    assert not flight.footprint_inside(ExternalPose(10.0, 200.0, 0.0, 100.0, 1.0))
    with pytest.raises(MapError, match="leaves the map"):
        flight.observe(ExternalPose(10.0, 200.0, 0.0, 100.0, 1.0))
    with pytest.raises(AerialLocError, match="above the ground"):
        flight.observe(ExternalPose(200.0, 200.0, 0.0, 0.0, 1.0))
    with pytest.raises(AerialLocError, match="non-finite"):
        ExternalPose(math.nan, 0.0, 0.0, 100.0, 0.0)


def test_a_crabbing_stream_gives_the_lateral_speed():
    """A plane flying due east with its nose 13 deg left of its track (crabbing into a wind from the north): the
    odometry measures the ground velocity in the body frame, forward v cos 13 deg
    and lateral -v sin 13 deg (to the right), each within 4 standard errors of the scenario's noise."""
    flight = ExternalFlight(_env())
    speed, crab = 22.0, math.radians(13.0)
    stream = [ExternalPose(80.0 + speed * t, 200.0, crab, 100.0, t) for t in np.arange(0.0, 10.0, 0.25)]
    frames = [flight.reset(stream[0], seed=2)] + [flight.observe(p) for p in stream[1:]]
    odo = np.array([obs["odometry"] for obs, _ in frames[1:]], dtype=np.float64)
    noise = flight.briefing.odometry_noise
    n = len(odo)
    assert abs(odo[:, 0].mean() - speed * math.cos(crab)) < 4 * noise.speed_std_mps / math.sqrt(n)
    assert abs(odo[:, 2].mean() + speed * math.sin(crab)) < 4 * noise.lateral_std_mps / math.sqrt(n)
    assert np.std(odo[:, 2]) == pytest.approx(noise.lateral_std_mps, rel=5.0 / math.sqrt(2 * n))
