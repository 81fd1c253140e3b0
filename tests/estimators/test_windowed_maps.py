"""Estimators on a map read by window (estimators/database.py, levels.py): the same estimates as on the same file
loaded whole, bit for bit; windows read again as the flight moves; global searches refused with the map's size;
levels made window by window equal OpenCV's area resize of the whole image."""

from __future__ import annotations

import dataclasses
import pickle
import sys

import cv2
import numpy as np
import pytest

import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env import AerialLocEnv
from aerial_loc_env.env.briefing import Prior
from aerial_loc_env.errors import MapError
from aerial_loc_env.estimators.database import DatabaseWindow, SparseLayer, lazy_zeros, read_by_window
from aerial_loc_env.estimators.levels import area_window, is_area_fast, level_pixels_within, source_box
from aerial_loc_env.estimators.mcl.agent import MCLAgent, MCLParams
from aerial_loc_env.estimators.mcl.measurement import MeasurementModel
from aerial_loc_env.estimators.patches import PatchGeometry, PatchSampler, to_gray
from aerial_loc_env.estimators.registry import make_agent, spec_names
from aerial_loc_env.learning.surface import SurfaceRegistration
from aerial_loc_env.perf.bigmap import SyntheticMap
from aerial_loc_env.world.maps.cog import write_cog
from aerial_loc_env.world.maps.io import open_map
from aerial_loc_env.world.maps.raster import RasterMap

SIZE_PX = 1600          # 400 m at 0.25 m/px: RealMap-v2's 300 m flight crosses several agent windows


class _HoledMap(SyntheticMap):
    """The benchmark's synthetic texture (a no-data wedge in the north-west corner) with a no-data hole in the
    middle, so that the agents' windows hold no-data that the flight flies around."""

    def read(self, u0_px, v0_px, width_px, height_px):
        rgb, nodata = super().read(u0_px, v0_px, width_px, height_px)
        vv, uu = np.mgrid[v0_px:v0_px + height_px, u0_px:u0_px + width_px]
        hole = (np.abs(uu - SIZE_PX // 2) < 10) & (np.abs(vv - SIZE_PX // 2) < 6)
        nodata = hole if nodata is None else nodata | hole
        rgb[nodata] = 0
        return rgb, (nodata if nodata.any() else None)


@pytest.fixture(scope="module")
def cog(tmp_path_factory):
    return write_cog(_HoledMap(SIZE_PX), tmp_path_factory.mktemp("windowed") / "holed.cog.tif")


@pytest.fixture(scope="module")
def episode(cog):
    """One RealMap-v2 episode's frames (rendered from the map loaded whole) and the two briefings of the same
    file: loaded whole, and read by window."""
    env = AerialLocEnv("AerialLoc/RealMap-v2", path=str(cog), map={"read": "whole"},
                       observation={"info_shadow_mask": True})   # (for the oracle)
    obs, info = env.reset(seed=2)
    frames = [(obs, info)]
    while True:
        obs, _, term, trunc, info = env.step(np.zeros(2, np.float32))
        if term or trunc:
            break
        frames.append((obs, info))
    whole = env.briefing
    windowed = dataclasses.replace(whole, orthomap=open_map(cog, read="window"))
    assert not read_by_window(whole.orthomap) and isinstance(windowed.orthomap, RasterMap)
    return frames, whole, windowed


def _run(name, briefing, frames, steps=None):
    agent = make_agent(name)
    out = [agent.reset(briefing, seed=5)]
    out += [agent.step(o, i if agent.uses_ground_truth else None) for o, i in frames[:steps]]
    return agent, out


def _same(a, b) -> bool:
    return (a.x_m, a.y_m, a.yaw_rad, a.status) == (b.x_m, b.y_m, b.yaw_rad, b.status) and \
        np.array_equal(a.cov_xy_m2, b.cov_xy_m2)


def _reads(agent) -> int:
    policy = agent.filter.policy if hasattr(agent, "filter") else agent._policy
    return policy.reads


@pytest.mark.slow
@pytest.mark.parametrize("name", ["mcl-shadow-aware", "template-ncc"])
def test_the_same_estimates_as_on_the_map_loaded_whole_bit_for_bit(episode, name):
    frames, whole, windowed = episode
    _, on_whole = _run(name, whole, frames)
    agent, on_windows = _run(name, windowed, frames)
    assert len(on_whole) == len(on_windows) > 200
    diff = [k for k, (a, b) in enumerate(zip(on_whole, on_windows, strict=True)) if not _same(a, b)]
    assert not diff, f"{name}: estimates differ from step {diff[0]} on"
    assert _reads(agent) >= 3          # the windows moved with the flight (and no-data was in some of them)


@pytest.mark.parametrize("name", ["mcl-ncc", "mcl-mi", "mcl-abbrief", "mcl-shadow-aware-map", "mcl-shadow-weighted",
                                  "features-orb"])
@pytest.mark.slow
def test_every_database_layer_equals_the_whole_maps(episode, name):
    """The models that downsample the database (patch levels, the map-ratio detector's luma, the feature
    matcher's working level): the same estimates over the first 100 frames."""
    frames, whole, windowed = episode
    _, on_whole = _run(name, whole, frames, steps=100)
    agent, on_windows = _run(name, windowed, frames, steps=100)
    assert all(_same(a, b) for a, b in zip(on_whole, on_windows, strict=True))
    assert _reads(agent) >= 2


SHIPPED_NOT_RUN_HERE = {
    "mcl-global": "global localization: refused on a map read by window (test below)",
    "features-sift": "the same windows as features-orb, ten times slower",
    "ppo-map-memorization": "its model is made by training (runs/), not shipped",
    "sac-local-registration": "its model is made by training (runs/), not shipped",
    "ppo-local-registration": "needs stable-baselines3 (test below)",
}


@pytest.mark.slow
@pytest.mark.parametrize("name", [n for n in spec_names() if n not in SHIPPED_NOT_RUN_HERE])
def test_every_shipped_agent_runs_on_a_map_read_by_window(episode, name):
    frames, _, windowed = episode
    _, estimates = _run(name, windowed, frames, steps=30)
    assert all(np.isfinite([e.x_m, e.y_m]).all() for e in estimates)


def test_the_learned_agent_renders_its_database_view_by_window(episode):
    pytest.importorskip("stable_baselines3")
    frames, whole, windowed = episode
    agent, estimates = _run("ppo-local-registration", windowed, frames, steps=60)
    _, on_whole = _run("ppo-local-registration", whole, frames, steps=60)
    assert agent._core._renderer.policy.reads >= 1
    # OpenCV's warp rounds its float32 coordinates at the window's magnitude: a few pixels of the policy's map
    # view differ by one level from the whole map's, so the policy's corrections may differ slightly
    err = max(np.hypot(a.x_m - b.x_m, a.y_m - b.y_m) for a, b in zip(estimates, on_whole, strict=True))
    assert err < 2.0


def test_a_search_over_the_whole_map_is_refused_naming_its_size(episode):
    frames, _, windowed = episode
    uniform = dataclasses.replace(windowed, prior=Prior("uniform"))
    for name, briefing in (("mcl-global", windowed), ("mcl-shadow-aware", uniform), ("template-ncc", uniform)):
        with pytest.raises(MapError) as err:
            make_agent(name).reset(briefing, seed=0)
        msg = str(err.value)
        assert f"{SIZE_PX} x {SIZE_PX} px" in msg and "read by window" in msg and "map.read = 'whole'" in msg, msg
    make_agent("dead-reckoning").reset(uniform, seed=0)       # needs no pixel: fine


class _WholeMapModel(MeasurementModel):
    def reset(self, briefing, rng):
        self.rgb = briefing.orthomap.rgb

    def prepare(self, observation, rng, info=None):
        return None

    def log_likelihood(self, prepared, states, altitude_m):
        return np.zeros(len(states))


def test_a_measurement_model_that_reads_the_whole_map_is_refused_before_the_episode(episode):
    _, _, windowed = episode
    agent = MCLAgent(MCLParams(measurement=f"{__name__}:_WholeMapModel"))
    with pytest.raises(MapError, match="reads_windows = True"):
        agent.reset(windowed, seed=0)


def test_a_particle_outside_the_window_read_is_an_error_not_a_wrong_likelihood(cog, episode):
    _, _, windowed = episode
    frame = windowed.orthomap
    window = DatabaseWindow(frame, (200, 200, 600, 600))      # map pixels 400 +- 200: 100 m +- 50 m
    sampler = PatchSampler(window, windowed.camera, PatchGeometry(30, 20), to_gray(window.rgb), 50.0)
    patches, valid = sampler.sample(np.array([[100.0, 300.0, 0.3]]), 50.0)
    assert valid.all() and np.isfinite(patches).all()
    with pytest.raises(MapError, match="leave the database window"):
        sampler.sample(np.array([[100.0, 300.0, 0.3], [300.0, 100.0, 0.3]]), 50.0)


# --- levels made window by window --------------------------------------------------------------------------

@pytest.mark.parametrize("src,dst", [((913, 700), (342, 262)), ((912, 702), (304, 234)), ((1000, 800), (250, 200)),
                                     ((640, 480), (320, 240)), ((1537, 911), (229, 136)), ((900, 700), (450, 233)),
                                     ((1000, 1000), (999, 1000))])
@pytest.mark.parametrize("dtype,channels", [(np.float32, 1), (np.float32, 2), (np.float32, 4), (np.uint8, 1)])
def test_a_window_of_a_level_equals_opencvs_area_resize_of_the_whole_image(src, dst, dtype, channels):
    rng = np.random.default_rng(src[0] + channels)
    shape = (src[1], src[0]) + ((channels,) if channels > 1 else ())
    img = rng.integers(0, 256, shape).astype(np.uint8) if dtype == np.uint8 else \
        ((rng.random(shape) - 0.3) * 255).astype(np.float32)
    whole = cv2.resize(img, dst, interpolation=cv2.INTER_AREA)
    for box in ((0, 0) + dst, (dst[0] // 5, dst[1] // 3, dst[0] * 3 // 4, dst[1] - 1), (dst[0] - 3, dst[1] - 2) + dst):
        got = area_window(lambda u, v, w, h: img[v:v + h, u:u + w], src, dst, box, dtype)
        assert np.array_equal(got, whole[box[1]:box[3], box[0]:box[2]]), (box, is_area_fast(src, dst))


def test_the_level_pixels_of_a_window_are_those_it_holds_every_source_pixel_of():
    rng = np.random.default_rng(0)
    for _ in range(300):
        src = (int(rng.integers(50, 2000)), int(rng.integers(50, 2000)))
        f = float(rng.choice([1.0001, 1.5, 2, 2.67, 3, 6.7, 13.3]))
        dst = (max(2, round(src[0] / f)), max(2, round(src[1] / f)))
        u0, v0 = int(rng.integers(0, src[0] - 1)), int(rng.integers(0, src[1] - 1))
        win = (u0, v0, int(rng.integers(u0 + 1, src[0] + 1)), int(rng.integers(v0 + 1, src[1] + 1)))
        box = level_pixels_within(src, dst, win)
        if box is None:
            continue

        def inside(b, src=src, dst=dst, win=win):
            s = source_box(src, dst, b)
            return s[0] >= win[0] and s[1] >= win[1] and s[2] <= win[2] and s[3] <= win[3]

        assert inside(box)
        for grown in ((box[0] - 1, box[1], box[2], box[3]), (box[0], box[1] - 1, box[2], box[3]),
                      (box[0], box[1], box[2] + 1, box[3]), (box[0], box[1], box[2], box[3] + 1)):
            if min(grown[:2]) >= 0 and grown[2] <= dst[0] and grown[3] <= dst[1]:
                assert not inside(grown)


# --- layers of the whole map's grid, backed where written -------------------------------------------------

def _rss_bytes() -> int:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * 4096


def test_a_layer_of_the_whole_maps_grid_holds_memory_only_where_written():
    layer = SparseLayer(40000, 40000, 3, np.uint8)           # a 40000 px map's RGB: 4.8 GB of address space
    assert layer.array.shape == (40000, 40000, 3) and not layer.array[:64, :64].any()
    if sys.platform.startswith("linux"):
        before = _rss_bytes()
        layer.write((20000, 20000, 21000, 21000), np.full((1000, 1000, 3), 7, np.uint8))
        grown = _rss_bytes() - before
        assert 3e6 <= grown < 3 * 3e6, grown          # the window's 3 MB (and its rows' pages), not the map
    else:                                           # the system's own lazily zeroed allocation
        layer.write((20000, 20000, 21000, 21000), np.full((1000, 1000, 3), 7, np.uint8))
    assert layer.array[20500, 20500, 1] == 7 and layer.array[19999, 20500, 1] == 0
    back = pickle.loads(pickle.dumps(layer))            # pickles as the written box, not the grid
    assert back.box == layer.box and np.array_equal(back.read(back.box), layer.read(layer.box))
    assert lazy_zeros((3, 5), np.float32).sum() == 0



@pytest.mark.slow
def test_the_learned_registration_embeds_windows_along_the_track(episode):
    """ppo-learned-registration on a map read by window embeds the windows around its surface's reach as it flies
    (windows on the whole map's cell grid), and sees the surfaces it sees on the map loaded whole: cosine
    similarities that differ by resampling and the window's edge only, a small part of the frames' peak (about
    0.5) and of the cosine's range."""
    frames, whole, windowed = episode
    agent, estimates = _run("ppo-learned-registration", windowed, frames)
    assert agent.core.window_policy.reads >= 2 and all(np.isfinite([e.x_m, e.y_m]).all() for e in estimates)
    cores = [SurfaceRegistration(), SurfaceRegistration()]
    for core, briefing in zip(cores, (windowed, whole), strict=True):
        core.reset(briefing)
    diffs = []
    for obs, _ in frames[:60]:
        on_window, on_whole = (core.observe(obs)[0] for core in cores)
        diffs.append(float(np.abs(on_window - on_whole).max()))
        for core in cores:
            core.correct(np.zeros(2))          # both dead-reckon the same track
    assert max(diffs) < 0.1 and np.mean(diffs) < 0.05, diffs
