"""learning/dataset.py, learning/splits.py and learning/torch_dataset.py: examples are a pure function of their
seed (same bytes), drawn only from their split's worlds; the splits are disjoint in worlds, stable, and keep the
benchmark's cities and the held-out preset in test."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.learning import splits
from aerial_loc_env.learning.dataset import GAP_FIELDS, ExampleSampler, Randomization, example_seed
from aerial_loc_env.learning.splits import WorldRef, split_of, worlds

# a 300 m city, small frames and two offsets: one world builds in a few seconds
SMALL = {"n_worlds": 1, "city_size_m": 300.0, "frame_px": (96, 64), "n_offsets": 2, "max_offset_m": 10.0,
         "randomization": {"altitude_m": [100.0, 120.0]}}


@pytest.fixture(scope="module")
def sampler() -> ExampleSampler:
    return ExampleSampler("train", **SMALL)


def _bytes(example) -> dict[str, bytes]:
    return {name: array.tobytes() for name, array in example.arrays().items()}


# ------------------------------------------------------------------------------------------- splits
def test_splits_are_disjoint_in_worlds_and_each_world_is_in_its_own_split():
    drawn = {split: set(worlds(split, 60)) for split in splits.SPLITS}
    assert not drawn["train"] & drawn["val"] and not drawn["train"] & drawn["test"] and not drawn["val"] & drawn["test"]
    seeds = {split: {w.city_seed for w in drawn[split]} for split in splits.SPLITS}
    assert not seeds["train"] & seeds["val"] and not seeds["train"] & seeds["test"] and not seeds["val"] & seeds["test"]
    for split, refs in drawn.items():
        assert all(split_of(w.preset, w.city_seed) == split for w in refs)
    assert {w.preset for w in drawn["train"]} == {w.preset for w in drawn["val"]} == {"paper"}
    assert {w.preset for w in drawn["test"]} == set(splits.PRESETS)


def test_split_of_is_stable():
    # the documented rule, pinned: a change of hash, salt or thresholds must bump SPLIT_VERSION
    assert splits.SPLIT_VERSION == 1
    assert [splits.seed_bucket(s) for s in range(2, 8)] == [_bucket(s) for s in range(2, 8)]
    assert [split_of("paper", s) for s in range(2, 14)] == ["test", "test", "train", "test", "train", "train",
                                                           "train", "test", "train", "val", "train", "test"]
    assert [split_of("downtown", s) for s in range(2, 8)] == ["test", "test", "unused", "test", "unused", "unused"]
    assert worlds("train", 3) == (WorldRef("paper", 4), WorldRef("paper", 6), WorldRef("paper", 7))
    assert worlds("test", 4) == (WorldRef("paper", 0), WorldRef("downtown", 0), WorldRef("paper", 1),
                                 WorldRef("downtown", 1))


def _bucket(seed: int) -> int:
    import hashlib

    return int.from_bytes(hashlib.sha256(f"aerial-loc-split-v1:{seed}".encode()).digest()[:8], "big") % 1000


def test_benchmark_cities_and_held_out_presets_are_test(repo_root):
    from aerial_loc_env.config import read_toml

    for spec in sorted((repo_root / "envs").glob("*.toml")):
        raw = read_toml(spec)
        if raw.get("map", {}).get("kind", "city") == "city":
            seed = raw.get("city", {}).get("seed", 0)
            assert seed in splits.BENCHMARK_CITY_SEEDS, f"{spec.name}: city seed {seed} is not reserved for test"
    for preset in splits.PRESETS:
        for seed in splits.BENCHMARK_CITY_SEEDS:
            assert split_of(preset, seed) == "test"
    assert {split_of("downtown", s) for s in range(50)} == {"test", "unused"}
    assert all(split_of("downtown", s) == "test" for s in range(50) if split_of("paper", s) == "test")
    assert sum(split_of("paper", s) == "train" for s in range(1000)) in range(740, 860)


def test_split_errors_name_the_allowed_values():
    with pytest.raises(ConfigError, match="unknown split 'training'.*train, val, test"):
        worlds("training", 3)
    with pytest.raises(ConfigError, match="'downtown'.*no worlds in split 'train'.*held out for test: downtown"):
        worlds("train", 3, presets=("downtown",))
    with pytest.raises(ConfigError, match="unknown preset 'suburb'"):
        split_of("suburb", 5)
    with pytest.raises(ConfigError, match="city seed -1"):
        split_of("paper", -1)


# ------------------------------------------------------------------------------------------- sampler
def test_same_seed_same_example_bytes(sampler):
    a = sampler.sample(11)
    sampler.sample(12)                                         # another example between: no state leaks
    again = sampler.sample(11)
    fresh = ExampleSampler("train", **SMALL).sample(11)        # nor from the sampler's caches
    assert _bytes(a) == _bytes(again) == _bytes(fresh)
    assert a.meta == fresh.meta
    assert _bytes(sampler.sample(13))["frame"] != _bytes(a)["frame"]


def test_example_layout_and_crop_zero_is_at_the_true_pose(sampler):
    ex = sampler.sample(5)
    assert ex.frame.shape == (64, 96, 3) and ex.frame.dtype == np.uint8
    assert ex.map_crops.shape == (3, 64, 96, 3) and ex.map_crops.dtype == np.uint8
    assert ex.offsets_m.shape == (3, 2) and not ex.offsets_m[0].any()
    assert np.all(np.hypot(*ex.offsets_m.T) <= 10.0 + 1e-4)
    assert ex.gap.shape == (len(GAP_FIELDS),) and ex.gap.dtype == np.float32
    gap = dict(zip(GAP_FIELDS, ex.gap.tolist(), strict=True))
    assert gap["altitude_m"] == pytest.approx(ex.pose[3], abs=1e-3)
    assert gap["measured_altitude_m"] == pytest.approx(ex.measured[1])
    assert ex.meta["split"] == ex.meta["world_split"] == "train"
    json.dumps(ex.meta)
    # the frame matches the crop at its true pose better than the crops elsewhere (same ground, same camera)
    def ncc(a, b):
        a, b = a.astype(float).mean(2).ravel(), b.astype(float).mean(2).ravel()
        a, b = a - a.mean(), b - b.mean()
        return float(a @ b / math.sqrt((a @ a) * (b @ b) + 1e-9))
    scores = [ncc(ex.frame, crop) for crop in ex.map_crops]
    far = [s for s, o in zip(scores[1:], ex.offsets_m[1:], strict=True) if np.hypot(*o) > 5.0]
    assert all(scores[0] > s for s in far), scores


def test_examples_come_only_from_the_split_worlds():
    s = ExampleSampler("val", **SMALL)
    assert all(split_of(w.preset, w.city_seed) == "val" for w in s.worlds)
    ex = s.sample(1)
    assert ex.meta["split"] == ex.meta["world_split"] == "val" and ex.meta["world"] == s.worlds[0].name


def test_world_draws_are_the_worlds_own_and_span_the_presets():
    r = Randomization()
    w = WorldRef("paper", 7)
    assert r.draw_world(w, 600.0) == r.draw_world(w, 600.0)
    draws = [r.draw_world(WorldRef("paper", s), 600.0) for s in range(2, 60)]
    assert any(not d["epoch"] for d in draws) and any(d["epoch"] for d in draws)          # PaperShadows .. Realistic
    assert any(not d["database"] for d in draws) and any(d["database"] for d in draws)
    assert any(d["database_sun_deg"] is None for d in draws) and any(d["database_sun_deg"] for d in draws)
    leaf_off = [d["epoch"]["leaf_off"] for d in draws if d["epoch"]]
    assert min(leaf_off) < 0.3 and max(leaf_off) > 0.8                                      # summer .. winter


def test_bad_sampler_arguments_are_clear_errors():
    with pytest.raises(ConfigError, match="city_size_m = 100.0 must be in \\[300, 8000\\]"):
        ExampleSampler("train", city_size_m=100.0)
    with pytest.raises(ConfigError, match="frame_px"):
        ExampleSampler("train", frame_px=(4, 4))
    with pytest.raises(ConfigError, match="'altitude_m' = \\[200.0, 100.0\\] must be a range"):
        ExampleSampler("train", randomization={"altitude_m": [200.0, 100.0]})
    with pytest.raises(ConfigError, match="unknown key.*'altitude'"):
        ExampleSampler("train", randomization={"altitude": [100.0, 200.0]})
    with pytest.raises(ConfigError, match="non-negative integer"):
        ExampleSampler("train", **SMALL).sample(-1)


# ------------------------------------------------------------------------------------------- torch
def test_torch_dataset_is_index_to_seed_and_batches():
    import torch

    from aerial_loc_env.learning.torch_dataset import SimulatedPairs

    kwargs = {k: v for k, v in SMALL.items()}
    ds = SimulatedPairs("train", n_examples=4, seed=3, **kwargs)
    assert isinstance(ds, torch.utils.data.Dataset) and len(ds) == 4
    assert ds.seed_of(1) == example_seed(3, "train", 1) != ds.seed_of(0)
    item = ds[1]
    ex = ds.sampler.sample(ds.seed_of(1))
    assert item["frame"].shape == (3, 64, 96) and item["map_crops"].shape == (3, 3, 64, 96)
    assert np.array_equal(item["frame"].numpy().transpose(1, 2, 0), ex.frame)
    assert json.loads(item["meta"])["world"] == ex.meta["world"]
    batch = next(iter(torch.utils.data.DataLoader(ds, batch_size=2)))
    assert batch["map_crops"].shape == (2, 3, 3, 64, 96) and len(batch["meta"]) == 2
    with pytest.raises(IndexError):
        ds[4]


def test_torch_dataset_without_torch_names_the_extra(monkeypatch):
    import importlib
    import sys

    from aerial_loc_env.errors import MissingExtraError

    monkeypatch.setitem(sys.modules, "torch", None)      # as if torch were not installed
    monkeypatch.delitem(sys.modules, "aerial_loc_env.learning.torch_dataset", raising=False)
    with pytest.raises(MissingExtraError, match=r"PyTorch dataset.*pip install 'aerial-loc-env\[rl\]'"):
        importlib.import_module("aerial_loc_env.learning.torch_dataset")
