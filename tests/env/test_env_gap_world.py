"""The env's world and database under the appearance-gap sections: [database] (acquisition) and [epoch].

Off by default: the existing ids keep their episodes bit for bit (the database *is* the scene, the camera world
*is* the cached city); turned on, the database differs from the camera's world as the section says.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import aerial_loc_env  # noqa: F401  (registers the scenarios)

SMALL = "AerialLoc/Small-v3"
SHORT = {"duration_s": 3.0}


def _episode(env, seed: int) -> list[np.ndarray]:
    obs, _ = env.reset(seed=seed)
    frames = [obs["image"].copy()]
    while True:
        obs, _, term, trunc, _ = env.step(np.zeros(2, np.float32))
        frames.append(obs["image"].copy())
        if term or trunc:
            return frames


def test_defaults_keep_the_scene_as_database_and_world():
    env = gym.make(SMALL, **SHORT).unwrapped
    city = env.world.surveyed
    assert env.database is city and env.orthomap is city
    explicit = gym.make(SMALL, **SHORT, database={"lean_deg": 0.0, "haze": 0.0, "georef_bias_m": [0.0, 0.0]}).unwrapped
    assert explicit.database is city
    for a, b in zip(_episode(env, 3), _episode(explicit, 3), strict=True):
        assert np.array_equal(a, b)


def test_acquisition_section_changes_only_the_database():
    plain = gym.make(SMALL, **SHORT).unwrapped
    acq = gym.make(SMALL, **SHORT, database={"gsd_m": 1.0, "jpeg_quality": 60, "haze": 0.15,
                                             "georef_bias_m": [3.0, -2.0], "lean_deg": 12.0,
                                             "lean_azimuth_deg": 250.0}).unwrapped
    assert acq.orthomap is plain.orthomap                     # the camera's world is untouched
    assert acq.database is not acq.orthomap
    assert acq.database.rgb.shape == acq.orthomap.rgb.shape
    assert acq.database.georef.to_dict() == acq.orthomap.georef.to_dict()       # the *stated* georeference
    diff = np.abs(acq.database.rgb.astype(np.int16) - acq.orthomap.rgb.astype(np.int16)).mean()
    assert diff > 5.0
    # the layers carry the same bias: at 0.5 m/px, 6 px east and 4 px south of the truth
    c0, c1 = acq.orthomap.classes, acq.database.classes
    assert np.array_equal(c1[40:-40, 40:-40], c0[36:-44, 34:-46])
    for a, b in zip(_episode(plain, 5), _episode(acq, 5), strict=True):   # same camera frames
        assert np.array_equal(a, b)
    assert acq.briefing.orthomap is acq.database


def test_acquisition_errors_name_the_field():
    from aerial_loc_env.errors import ConfigError

    with pytest.raises(ConfigError, match=r"database.*lean_deg"):
        gym.make(SMALL, database={"lean_deg": 75.0})


EPOCH = {"seed": 2, "car_turnover": 0.5, "car_arrivals": 0.5, "leaf_off": 0.6, "grass_dryness": 0.5,
         "roof_change": 0.3, "demolished": 0.2, "built": 0.2, "construction_per_km2": 20.0,
         "marking_renewal": 0.5, "water_change": 0.5}


def test_epoch_section_changes_the_camera_world_not_the_database():
    from aerial_loc_env.world.city.epochs import epoch_cache_path

    plain = gym.make(SMALL, **SHORT).unwrapped
    env = gym.make(SMALL, **SHORT, epoch=EPOCH).unwrapped
    city = env.world.surveyed
    assert env.database is city and env.orthomap is not city
    assert epoch_cache_path(env.scenario.city, env.scenario.epoch).is_dir()      # cached beside the city
    assert env._renderer.orthomap is env.orthomap
    assert not np.array_equal(env.orthomap.dsm_m, city.dsm_m)                   # buildings came and went
    assert np.mean(np.any(env.orthomap.rgb != city.rgb, axis=-1)) > 0.05
    env.reset(seed=4)
    plain.reset(seed=4)
    assert np.array_equal(plain._track.x_m, env._track.x_m)                     # same flight, other ground
    grid_b, grid_a = env._cast_shadows(), plain._cast_shadows()
    assert not np.array_equal(grid_b.data, grid_a.data)                         # shadows of epoch B's DSM
    frames_b, frames_a = _episode(env, 4), _episode(plain, 4)
    assert any(not np.array_equal(a, b) for a, b in zip(frames_a, frames_b, strict=True))
    again = gym.make(SMALL, **SHORT, epoch=EPOCH).unwrapped                      # same spec, same episode
    for a, b in zip(frames_b, _episode(again, 4), strict=True):
        assert np.array_equal(a, b)


def test_epoch_and_acquisition_together():
    env = gym.make(SMALL, **SHORT, epoch={"leaf_off": 0.5}, database={"haze": 0.2, "gsd_m": 1.0}).unwrapped
    city = env.world.surveyed
    assert env.database is not city and env.orthomap is not city
    assert np.array_equal(env.database.classes, city.classes)       # epoch A's layers (no georeference bias)
    obs, _ = env.reset(seed=0)
    assert env.observation_space.contains(obs)


def test_city_database_comes_from_the_disk_cache_whatever_the_epoch():
    """The acquired database of a city map is built once and memory-mapped by every process after
    (world/maps/acquisition.database_city); it is epoch A's, so the flown epoch shares it, and it is the map that
    acquire_map builds in memory, bit for bit."""
    from aerial_loc_env.world.maps.acquisition import acquire_map, database_cache_path

    db = {"gsd_m": 1.0, "haze": 0.2, "lean_deg": 8.0}
    env = gym.make(SMALL, **SHORT, database=db, shadows={"database_sun_deg": [150.0, 50.0]}).unwrapped
    sc = env.scenario
    assert env.database.bundle_path == database_cache_path(sc.city, sc.shadows, sc.database)
    flown = gym.make(SMALL, **SHORT, database=db, shadows={"database_sun_deg": [150.0, 50.0]},
                     epoch={"leaf_off": 0.5}).unwrapped
    assert flown.database.bundle_path == env.database.bundle_path and flown.orthomap is not env.orthomap
    fresh = acquire_map(env.world.surveyed, sc.shadows, sc.database)
    for name in ("rgb", "dsm_m", "classes"):
        assert np.array_equal(np.asarray(getattr(env.database, name)), getattr(fresh, name)), name
