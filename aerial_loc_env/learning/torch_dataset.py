"""The simulator's supervised examples (``learning.dataset``) as a PyTorch map-style dataset: index -> seed.

``SimulatedPairs(split, n_examples, seed)[i]`` is the example of ``dataset.example_seed(seed, split, i)``,
rendered when asked (no files written): a dict of tensors, images channel-first uint8 (``frame`` (3, H, W),
``map_crops`` (K, 3, H, W)), ``offsets_m`` (K, 2) float32, ``pose`` (4,) float64, ``measured`` (2,) float32,
``gap`` (len(GAP_FIELDS),) float32, and ``meta`` the example's metadata as a JSON string (``default_collate``
makes a batch's a list). Each ``DataLoader`` worker holds its own sampler; the worlds' maps are shared through
the on-disk cache.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from aerial_loc_env.errors import ConfigError, require_extra
from aerial_loc_env.learning.dataset import Example, ExampleSampler, example_seed, meta_json

th = require_extra("torch", "rl", "The PyTorch dataset of simulated examples (aerial_loc_env.learning.torch_dataset)")


def to_tensors(example: Example) -> dict[str, Any]:
    """An ``Example`` as the dataset hands it (see the module doc)."""
    return {
        "frame": th.from_numpy(np.ascontiguousarray(example.frame.transpose(2, 0, 1))),
        "map_crops": th.from_numpy(np.ascontiguousarray(example.map_crops.transpose(0, 3, 1, 2))),
        "offsets_m": th.from_numpy(example.offsets_m.copy()),
        "pose": th.from_numpy(example.pose.copy()),
        "measured": th.from_numpy(example.measured.copy()),
        "gap": th.from_numpy(example.gap.copy()),
        "meta": meta_json(example),
    }


class SimulatedPairs(th.utils.data.Dataset):
    """``n_examples`` examples of ``split`` (``ExampleSampler``'s keyword arguments pass through), the
    ``i``-th drawn from ``example_seed(seed, split, i)``: the same (seed, split, i) always gives the same bytes."""

    def __init__(self, split: str = "train", n_examples: int = 10000, seed: int = 0, **sampler_kwargs: Any) -> None:
        if isinstance(n_examples, bool) or not isinstance(n_examples, int) or n_examples < 1:
            raise ConfigError(f"SimulatedPairs: n_examples = {n_examples!r} must be a positive integer")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"SimulatedPairs: seed = {seed!r} must be a non-negative integer")
        self.sampler = ExampleSampler(split, **sampler_kwargs)
        self.split, self.n_examples, self.seed = split, n_examples, seed

    def __len__(self) -> int:
        return self.n_examples

    def seed_of(self, index: int) -> int:
        """The example seed of ``index``."""
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not -self.n_examples <= index \
                < self.n_examples:
            raise IndexError(f"SimulatedPairs: index {index!r} out of range for {self.n_examples} examples")
        return example_seed(self.seed, self.split, int(index) % self.n_examples)

    def __getitem__(self, index: int) -> dict[str, Any]:
        return to_tensors(self.sampler.sample(self.seed_of(index)))
