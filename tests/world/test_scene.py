"""The world a scenario flies over (world/scene.py): built by one function, cached by content."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.city import small_city_config
from aerial_loc_env.world.city.epochs import EpochConfig
from aerial_loc_env.world.maps.acquisition import AcquisitionConfig
from aerial_loc_env.world.scene import MapConfig, WorldSpec, build_world
from aerial_loc_env.world.shadows import ShadowConfig


def _spec(**kw) -> WorldSpec:
    parts = {"map": MapConfig(), "city": small_city_config(seed=5, width_m=200.0, height_m=200.0),
             "epoch": EpochConfig(), "shadows": ShadowConfig(), "database": AcquisitionConfig()}
    parts.update(kw)
    return WorldSpec(**parts)


def test_identity_sections_give_the_surveyed_map_everywhere():
    world = build_world(_spec())
    assert world.ground is world.surveyed and world.database is world.surveyed
    assert world.dsm_max_m == float(np.max(world.surveyed.dsm_m))


def test_equal_specs_share_one_world_and_specs_that_differ_share_their_common_parts():
    """Keys are content: a spec built again (new config objects) finds the same world; a spec that changes only
    the database keeps the surveyed map and the ground."""
    a, b = build_world(_spec()), build_world(_spec())
    assert a is b
    acquired = build_world(_spec(database=AcquisitionConfig(haze=0.2)))
    assert acquired is not a
    assert acquired.surveyed is a.surveyed and acquired.ground is a.ground
    assert acquired.database is not a.database


def test_an_epoch_changes_the_ground_not_the_database():
    world = build_world(_spec(epoch=EpochConfig(leaf_off=0.5)))
    assert world.ground is not world.surveyed and world.database is world.surveyed
    assert not np.array_equal(np.asarray(world.ground.rgb), np.asarray(world.surveyed.rgb))


def test_derived_products_are_made_once_per_world():
    world = build_world(_spec())
    assert world.coarse_dsm(2) is world.coarse_dsm(2)
    assert world.coarse_dsm(2).shape == tuple(-(-n // 2) for n in world.ground.dsm_m.shape)
    assert np.max(world.coarse_dsm(2)) == world.dsm_max_m
    region = world.flyable_region(30.0, name="test")
    assert world.flyable_region(30.0, name="test") is region
    assert region.clearance_m == 30.0 and region.area_m2 > 0.0


def test_a_map_file_changed_on_disk_is_read_again(tmp_path):
    path = tmp_path / "tile.png"
    rng = np.random.default_rng(0)
    cv2.imwrite(str(path), rng.integers(0, 256, (200, 300, 3), dtype=np.uint8))
    spec = _spec(map=MapConfig(kind="file", path=str(path), gsd_m=0.5))
    first = build_world(spec)
    assert build_world(spec) is first
    cv2.imwrite(str(path), rng.integers(0, 256, (200, 300, 3), dtype=np.uint8))
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))   # a new modification time, as an edit
    second = build_world(spec)
    assert second is not first
    assert not np.array_equal(np.asarray(second.surveyed.rgb), np.asarray(first.surveyed.rgb))


def test_a_missing_map_file_names_the_field_and_the_path(tmp_path):
    spec = _spec(map=MapConfig(kind="file", path=str(tmp_path / "nope.tif")), where="AerialLoc/RealMap-v2")
    with pytest.raises(MapError, match=r"AerialLoc/RealMap-v2: map.path '.*nope.tif' does not exist"):
        build_world(spec)
