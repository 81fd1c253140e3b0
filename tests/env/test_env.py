"""AerialLocEnv: the contract (spaces, time line, reward, info, briefing), determinism, bad input, pickling."""

from __future__ import annotations

import dataclasses
import math
import pickle

import cv2
import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env import (
    AerialLocEnv,
    Briefing,
    InvalidActionError,
    OdometryNoise,
    action_to_world,
    world_to_action,
)
from aerial_loc_env.errors import AerialLocError, ConfigError

SMALL = "AerialLoc/Small-v3"
SHORT = {"duration_s": 5.0}          # 20 steps: enough for every property, fast


def make(**overrides) -> AerialLocEnv:
    return gym.make(SMALL, **{**SHORT, **overrides}).unwrapped


def rollout(env: gym.Env, seed: int, actions: np.ndarray | None = None):
    obs, info = env.reset(seed=seed)
    out = [(obs, info)]
    i = 0
    while True:
        a = np.zeros(2, np.float32) if actions is None else actions[i % len(actions)]
        obs, r, term, trunc, info = env.step(a)
        out.append((obs, r, term, trunc, info))
        i += 1
        if term or trunc:
            return out


def test_spaces_follow_the_contract():
    env = make()
    space = env.observation_space
    assert isinstance(space, gym.spaces.Dict) and set(space.spaces) == {"image", "odometry", "yaw", "altitude"}
    assert space["image"].shape == (64, 64, 3) and space["image"].dtype == np.uint8
    for key, n in (("odometry", 3), ("yaw", 1), ("altitude", 1)):
        assert space[key].shape == (n,) and space[key].dtype == np.float32
    assert np.isclose(space["yaw"].high[0], math.pi, atol=1e-6)
    assert env.action_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    obs, info = env.reset(seed=0)
    assert space.contains(obs)


def test_observation_size_is_configurable_on_one_code_path():
    big = make(observation={"width_px": 120, "height_px": 80})
    obs, _ = big.reset(seed=1)
    assert obs["image"].shape == (80, 120, 3)
    # the same footprint: a resized camera, not another camera
    cam, small_cam = big.briefing.camera, make().camera
    assert cam.footprint_m(100.0) == pytest.approx(small_cam.footprint_m(100.0))


def test_action_helpers_round_trip():
    env = make()
    om = env.orthomap
    x, y = 0.3 * om.width_m, 0.8 * om.height_m
    a = world_to_action(om, x, y)
    assert a.dtype == np.float32 and a == pytest.approx([-0.4, 0.6], abs=1e-6)
    assert action_to_world(om, a) == pytest.approx((x, y), abs=1e-3)
    np.testing.assert_allclose(world_to_action(om, [0.0, om.width_m], [0.0, om.height_m]), [[-1, -1], [1, 1]])
    xs, ys = action_to_world(om, np.array([[-1.0, -1.0], [1.0, 1.0]]))
    np.testing.assert_allclose(xs, [0.0, om.width_m])


def test_time_line_reward_and_info():
    env = make()
    scale = env.scenario.reward.scale_m
    obs, info = env.reset(seed=3)
    steps = env.scenario.flight.steps
    for k in range(steps):
        truth = info["true_pose"]
        guess = world_to_action(env.orthomap, truth[0] + 30.0, truth[1] - 40.0)
        obs, r, term, trunc, info = env.step(guess)
        # the action is scored against the pose of the frame it answered
        assert info["position_error_m"] == pytest.approx(50.0, abs=0.05)
        assert r == pytest.approx(-50.0 / scale, abs=1e-3)
        assert not term
        assert trunc == (k == steps - 1)
        assert info["step"] == k + 1 and info["time_s"] == pytest.approx((k + 1) * env.briefing.dt_s)
    for key in ("true_pose", "prior", "shadow_fraction", "sun_azimuth_deg", "sun_elevation_deg"):
        assert key in info
    with pytest.raises(AerialLocError, match="episode is over"):
        env.step(np.zeros(2, np.float32))


def test_failure_terminates():
    env = make(failure_error_m=100.0, failure_steps=3)
    obs, info = env.reset(seed=0)
    corners = np.array([[-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]], np.float32)
    here = world_to_action(env.orthomap, *info["true_pose"][:2])
    far = corners[np.argmax(np.abs(corners - here).sum(axis=1))]   # >= half the map away in x and y
    results = [env.step(far) for _ in range(3)]
    assert [r[2] for r in results] == [False, False, True]
    assert "failure" in results[-1][4]


def test_same_seed_same_rollout_other_seed_other_rollout():
    env_a, env_b = make(), make()
    actions = np.random.default_rng(0).uniform(-1, 1, (7, 2)).astype(np.float32)
    a, b = rollout(env_a, 11, actions), rollout(env_b, 11, actions)
    assert len(a) == len(b)
    for ra, rb in zip(a, b, strict=True):
        for key in ra[0]:
            np.testing.assert_array_equal(ra[0][key], rb[0][key])
        assert ra[1:-1] == rb[1:-1]
        np.testing.assert_array_equal(ra[-1]["true_pose"], rb[-1]["true_pose"])
    c = rollout(env_a, 12, actions)
    assert not np.array_equal(a[0][1]["true_pose"], c[0][1]["true_pose"])


def test_shadows_info_and_shadow_mask_option():
    env = make(info_shadow_mask=True, shadows={"strength_range": [1.0, 1.0]})
    _, info = env.reset(seed=5)
    mask = info["shadow_mask"]
    assert mask.shape == (64, 64) and mask.dtype == bool
    assert info["shadow_fraction"] == pytest.approx(mask.mean())
    assert 0.0 <= info["sun_elevation_deg"] <= 90.0
    assert "shadow_mask" not in make().reset(seed=5)[1]
    _, info = make(strength_range=[0.0, 0.0]).reset(seed=5)
    assert info["shadow_fraction"] == 0.0 and info["shadow_strength"] == 0.0


def test_shadows_darken_the_frame_where_the_mask_says():
    kw = {"info_shadow_mask": True, "photometry": {"exposure_std": 0.0, "white_balance_std": 0.0,
                                                    "gamma_std": 0.0, "read_noise_dn": 0.0,
                                                    "shot_noise_gain": 0.0, "vignetting": 0.0}}
    # a low sun (long shadows); the first seed whose frame has a real shadow
    shadows = {"sun_elevation_range_deg": [25.0, 25.0], "shadow_ratio": 0.35, "gamma": 2.2}
    lit_env = make(shadows={**shadows, "strength_range": [0.0, 0.0]}, **kw)
    env = make(shadows={**shadows, "strength_range": [1.0, 1.0]}, **kw)
    for seed in range(20):
        obs, info = env.reset(seed=seed)
        if info["shadow_mask"].sum() >= 50:
            break
    mask = info["shadow_mask"]
    assert mask.sum() >= 50
    lit = lit_env.reset(seed=seed)[0]["image"].astype(float).mean(axis=2)
    dark = obs["image"].astype(float).mean(axis=2)
    # occlusion >= 0.5 removes at least half the direct sun: linear gain <= 1 - 0.5 (1 - 0.35), encoded ^(1/2.2)
    bound = (1.0 - 0.5 * (1.0 - 0.35)) ** (1 / 2.2)
    assert dark[mask].mean() / lit[mask].mean() < bound + 0.02
    assert dark[~mask].mean() / lit[~mask].mean() > 0.9        # outside the mask: at most soft edges


def test_frames_of_a_coarser_pyramid_level_are_the_box_baked_at_that_level():
    """Small renders from pyramid level 1: each frame is one warp of the episode's box baked at that level (its
    quantized occlusion carried in the warped alpha), never the level and the grid warped per frame."""
    env = make()
    env.reset(seed=2)
    for _ in range(6):
        env.step(np.zeros(2, np.float32))
        assert env._frame.pyramid_level == 1 and env._frame.occlusion_q is not None
    baked = env._baked
    assert list(baked.levels) == [1] and baked.levels[1].baked_tiles.any() and not baked.baked_tiles.any()


def test_prior_is_gaussian_around_the_truth_with_the_configured_std():
    env = make(duration_s=2.0)
    z = []
    for seed in range(60):
        _, info = env.reset(seed=seed)
        prior = info["prior"]
        assert prior.kind == "gaussian" and prior.std_xy_m == 15.0
        z.extend((np.array(prior.mean_xy_m) - info["true_pose"][:2]) / 15.0)
    z = np.asarray(z)
    # 120 standard normals: mean within 4/sqrt(120), variance within 4 * sqrt(2/120)
    assert abs(z.mean()) < 4 / math.sqrt(len(z))
    assert abs(z.var() - 1.0) < 4 * math.sqrt(2 / len(z))
    g = make(start="global")
    g.reset(seed=0)
    assert g.briefing.prior.kind == "uniform" and g.briefing.prior.mean_xy_m is None


def test_briefing_is_exactly_the_contract():
    env = make()
    env.reset(seed=0)
    b = env.briefing
    assert isinstance(b, Briefing) and env.get_wrapper_attr("briefing") is b
    assert [f.name for f in dataclasses.fields(Briefing)] == [
        "orthomap", "camera", "prior", "dt_s", "altitude_m", "odometry_noise", "scenario_id"]
    assert b.camera == env.camera and b.scenario_id == SMALL and b.dt_s == 0.25
    assert isinstance(b.odometry_noise, OdometryNoise)
    assert b.orthomap is env.orthomap            # the shadow-free database


def test_odometry_observations_carry_the_configured_noise():
    env = make(duration_s=15.0, odometry={"speed_std_mps": 0.5, "heading_std_rad": 0.05, "lateral_std_mps": 0.3})
    speed_err, yaw_err, lateral_err = [], [], []
    for seed in range(4):
        obs, info = env.reset(seed=seed)
        track = env._track
        for k in range(1, len(track)):
            obs, *_ = env.step(np.zeros(2, np.float32))
            speed_err.append(obs["odometry"][0] - track.speed_mps[k])
            lateral_err.append(obs["odometry"][2] - track.lateral_mps[k])
            yaw_err.append((obs["yaw"][0] - track.yaw_rad[k] + math.pi) % (2 * math.pi) - math.pi)
    n = len(speed_err)
    tol = 5.0 / math.sqrt(2 * n)
    assert np.std(speed_err) == pytest.approx(0.5, rel=tol)
    assert np.std(yaw_err) == pytest.approx(0.05, rel=tol)
    assert np.std(lateral_err) == pytest.approx(0.3, rel=tol)
    assert abs(np.mean(lateral_err)) < 4 * 0.3 / math.sqrt(n)     # unbiased; no wind: the truth is 0
    assert not np.any(track.lateral_mps)


@pytest.mark.parametrize("action, match", [
    (np.zeros(3, np.float32), "shape"),
    (np.zeros((1, 2), np.float32), "shape"),
    (np.zeros(2, np.int64), "dtype"),
    (np.array([True, False]), "dtype"),
    (np.array([np.nan, 0.0], np.float32), "NaN/inf"),
    (np.array([0.0, np.inf]), "NaN/inf"),
    (np.array([1.5, 0.0], np.float32), r"outside \[-1, 1\]"),
    ("0,0", "dtype"),
])
def test_bad_actions_are_clear_errors(action, match):
    env = make()
    env.reset(seed=0)
    with pytest.raises(InvalidActionError, match=match):
        env.step(action)


@pytest.mark.parametrize("action", [
    np.array([0.25, -0.5], np.float32), np.array([1.0, -1.0]), np.array([1.0 + 5e-6, -1.0 - 5e-6]),
    np.array([-1.000004, 0.3], np.float32), np.array([0.5, 0.5], np.float16), [0.1, 0.2], (-0.3, 1.0),
])
def test_actions_within_the_map_are_scored_as_their_clipped_metres(action):
    """The usual action (2 float32 or float64 values in [-1, 1]) is checked in plain Python; every accepted
    action, on that path or the general one (other dtypes, sequences, values up to 1e-5 beyond the map's edge),
    scores the metres of the action clipped to [-1, 1]."""
    env = make()
    env.reset(seed=0)
    _, _, _, _, info = env.step(action)
    expected = action_to_world(env.unwrapped.orthomap, np.clip(np.asarray(action, np.float64), -1.0, 1.0))
    np.testing.assert_array_equal(info["estimate_xy_m"], expected)


def test_step_before_reset_and_reset_options_are_errors():
    env = make()
    with pytest.raises(AerialLocError, match="reset"):
        env.step(np.zeros(2, np.float32))
    with pytest.raises(AerialLocError, match="options"):
        env.reset(seed=0, options={"teleport": True})


def test_env_pickles_mid_episode_and_continues_identically():
    env = make()
    env.reset(seed=4)
    for _ in range(3):
        env.step(np.zeros(2, np.float32))
    clone = pickle.loads(pickle.dumps(env))
    for _ in range(3):
        a, b = env.step(np.full(2, 0.1, np.float32)), clone.step(np.full(2, 0.1, np.float32))
        np.testing.assert_array_equal(a[0]["image"], b[0]["image"])
        assert a[1] == b[1]


def test_render_overview_and_overlay():
    env = gym.make(SMALL, render_mode="rgb_array", **SHORT)
    env.reset(seed=0)
    frame0 = env.render()
    assert frame0.shape == (512, 512, 3) and frame0.dtype == np.uint8
    env.step(np.zeros(2, np.float32))
    base = env.unwrapped
    pts = np.column_stack([np.full(50, base._track.x_m[1] + 10.0), np.linspace(0, 400, 50)])
    base.set_overlay(pts, weights=np.ones(50))
    with_overlay = env.render()
    base.set_overlay()
    assert (np.abs(with_overlay.astype(int) - env.render().astype(int)).sum(axis=2) > 0).sum() > 20
    with pytest.raises(AerialLocError, match="points_xy_m"):
        base.set_overlay(np.zeros(5))


def test_record_video_wrapper(tmp_path):
    pytest.importorskip("moviepy", reason="gymnasium's RecordVideo needs moviepy (pip install moviepy)")
    from gymnasium.wrappers import RecordVideo

    env = RecordVideo(gym.make(SMALL, render_mode="rgb_array", duration_s=2.0), str(tmp_path / "videos"),
                      episode_trigger=lambda ep: True, disable_logger=True)
    env.reset(seed=0)
    done = False
    while not done:
        _, _, term, trunc, _ = env.step(np.zeros(2, np.float32))
        done = term or trunc
    env.close()
    assert list((tmp_path / "videos").glob("*.mp4"))


def test_async_vector_env_runs():
    envs = gym.vector.AsyncVectorEnv([lambda: gym.make(SMALL, duration_s=2.0)] * 2)
    try:
        obs, info = envs.reset(seed=[1, 2])
        assert obs["image"].shape == (2, 64, 64, 3)
        assert not np.array_equal(info["true_pose"][0], info["true_pose"][1])
        for _ in range(10):
            obs, r, term, trunc, info = envs.step(np.zeros((2, 2), np.float32))
        assert r.shape == (2,)
    finally:
        envs.close()


def _png_map(path, size_px: int) -> str:
    import cv2

    rng = np.random.default_rng(0)
    img = cv2.resize(rng.integers(0, 255, (size_px // 8, size_px // 8, 3), dtype=np.uint8), (size_px, size_px),
                     interpolation=cv2.INTER_CUBIC)
    cv2.imwrite(str(path), img)
    return str(path)


def test_file_map_shortens_the_track_and_rejects_a_map_too_small(tmp_path):
    from aerial_loc_env.errors import MapError

    path = _png_map(tmp_path / "tile.png", 400)                    # 100 m x 100 m at 0.25 m/px
    env = gym.make("AerialLoc/RealMap-v2", path=path, altitude_m=40.0, speed_mps=8.0, map={"gsd_m": 0.25},
                   turn_rate_deg_s=5.0).unwrapped
    lengths = []
    for seed in range(3):
        env.reset(seed=seed)
        lengths.append(len(env._track) - 1)
        assert env.region.contains(env._track.x_m, env._track.y_m).all()
    # 8 m/s with a 92 m turn radius cannot stay 60 s over a ~40 m flyable square: shortened, not refused
    assert all(env.scenario.flight.min_steps <= n < env.scenario.flight.steps for n in lengths)
    with pytest.raises(MapError, match="too small"):
        gym.make("AerialLoc/RealMap-v2", map={"path": path, "gsd_m": 0.25}, altitude_m=200.0)


def test_database_with_another_suns_shadows():
    env = make(shadows={"database_sun_deg": [120.0, 30.0]})
    env.reset(seed=0)
    db, scene = env.briefing.orthomap, env.orthomap
    assert db is not scene and db.rgb.shape == scene.rgb.shape
    assert (db.width_m, db.height_m) == (scene.width_m, scene.height_m)
    darker = db.rgb.astype(int).sum(axis=2) < scene.rgb.astype(int).sum(axis=2)
    assert 0.01 < darker.mean() < 0.9                      # some ground is in the baked shadows, not all
    plain = make()
    plain.reset(seed=0)
    assert plain.briefing.orthomap is plain.orthomap       # default: the shadow-free scene


def test_env_reset_refuses_a_boolean_seed():
    env = gym.make("AerialLoc/Small-v3")
    with pytest.raises((ConfigError, ValueError), match="seed"):
        env.reset(seed=True)
    env.close()


def test_realmap_clouds_cover_the_flown_window_not_the_whole_map(tmp_path):
    """RealMap-v2 on a 1 km map: the episode's cloud field spans the track's window plus the drift (no repeat
    while the episode flies), at cells matched to the cloud scale, instead of the whole map at 0.5 m."""
    from aerial_loc_env.sensors.flight import footprint_radius_m
    from aerial_loc_env.world.shadows import CloudField

    g = np.random.default_rng(0)
    tex = cv2.GaussianBlur(g.integers(0, 255, (2000, 2000, 3)).astype(np.uint8), (0, 0), 3)
    png = tmp_path / "km.png"
    cv2.imwrite(str(png), cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX))
    env = gym.make("AerialLoc/RealMap-v2", path=str(png), **{"map.gsd_m": 0.5})
    for seed in range(3):
        env.reset(seed=seed)
        u = env.unwrapped
        clouds = [o for o in u._occlusion if isinstance(o, CloudField)]
        assert len(clouds) == 1
        c = clouds[0]
        sc = u.scenario.shadows
        assert c.cell_m == sc.cloud_cell_m >= sc.cloud_scale_m / 32
        x0, y0, x1, y1 = u._track.bounds_m()
        pad = 2.0 * footprint_radius_m(*u.camera.footprint_m(float(u._track.altitude_m.max())))
        t_end = float(u._track.t_s[-1])
        ny, nx = c.shape
        vx, vy = c.drift_mps
        assert nx * c.cell_m >= min(1000.0, x1 - x0 + pad) + abs(vx) * t_end - c.cell_m
        assert ny * c.cell_m >= min(1000.0, y1 - y0 + pad) + abs(vy) * t_end - c.cell_m
        assert nx * ny * c.cell_m ** 2 < 0.8 * 1000.0 ** 2          # not the whole map
    env.close()


def test_wind_comes_from_its_own_stream_and_the_vehicle_crabs():
    """The same seed with and without wind: the same start, sun and prior (the wind's generator is a child of the
    seed's sequence), the wind in info, the lateral odometry carrying the crosswind; reset(seed) repeats the wind,
    a reset without a seed draws another."""
    calm = make(duration_s=5.0)
    windy = make(duration_s=5.0, wind={"speed_range_mps": [6.0, 6.0], "gust_std_mps": 0.5})
    _, info_c = calm.reset(seed=4)
    _, info_w = windy.reset(seed=4)
    np.testing.assert_array_equal(info_c["true_pose"][[0, 1, 3]], info_w["true_pose"][[0, 1, 3]])  # the start
    assert info_c["true_pose"][2] != info_w["true_pose"][2]         # its heading: crabbed into the wind
    assert info_c["prior"] == info_w["prior"] and info_c["sun_azimuth_deg"] == info_w["sun_azimuth_deg"]
    assert "wind_en_mps" not in info_c and math.hypot(*info_w["wind_en_mps"]) > 3.0
    first = windy.wind
    windy.reset(seed=4)
    assert np.array_equal(windy.wind.east_mps, first.east_mps)
    windy.reset()
    assert not np.array_equal(windy.wind.east_mps, first.east_mps)
    windy.reset(seed=4)
    t = windy._track
    lateral = np.array([windy.step(np.zeros(2, np.float32))[0]["odometry"][2] for _ in range(len(t) - 1)])
    assert np.all(t.lateral_mps[1:] != 0.0)                      # the wind is never exactly along the heading
    noise = windy.briefing.odometry_noise.lateral_std_mps
    assert abs(np.mean(lateral - t.lateral_mps[1:])) < 4 * noise / math.sqrt(len(lateral))
