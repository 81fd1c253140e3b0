"""Training pairs for the learned measurement model (``estimators.mcl.learned``): the camera frame and the map
database at the same pose, both as luma at the encoder's ground sampling.

Each pair comes from one supervised example of the simulator (``learning.dataset.ExampleSampler``: a world of the
split, the realistic gap drawn from every preset's ranges): the frame and the database crop at its true pose
(``map_crops[0]``: the same camera geometry, so co-registered pixel for pixel) are reduced to luma and box-filtered
to ``gsd_m`` metres per pixel. The pairs of a (split, worlds, count, seed) are a pure function of those numbers;
``make_pairs`` draws them over ``workers`` processes (each its own sampler) and ``PairSet`` holds them padded to
one shape with their sizes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.patches import to_gray
from aerial_loc_env.learning.dataset import ExampleSampler, example_seed


@dataclass(frozen=True)
class PairSpec:
    """Which pairs: ``n`` examples of ``split`` over its first ``n_worlds`` worlds (cities of ``city_size_m``),
    drawn from ``seed``, frames flown at ``altitude_m`` (lo, hi), reduced to ``gsd_m``."""

    split: str = "train"
    n: int = 1000
    n_worlds: int = 16
    city_size_m: float = 400.0
    seed: int = 0
    altitude_m: tuple[float, float] = (150.0, 250.0)
    gsd_m: float = 1.25

    def sampler_kwargs(self) -> dict[str, Any]:
        return {"n_worlds": self.n_worlds, "city_size_m": self.city_size_m, "n_offsets": 0,
                "randomization": {"altitude_m": tuple(self.altitude_m)}}


@dataclass(frozen=True, eq=False)
class PairSet:
    """Pairs padded to one shape: ``frames`` and ``maps`` (n, H, W) float32 luma, ``sizes`` (n, 2) the valid
    (height, width) of each (from the top-left), ``worlds`` the world names."""

    frames: np.ndarray
    maps: np.ndarray
    sizes: np.ndarray
    worlds: tuple[str, ...]

    def __len__(self) -> int:
        return int(self.frames.shape[0])


def reduce_pair(frame: np.ndarray, crop: np.ndarray, altitude_m: float, hfov_deg: float,
                gsd_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Frame and crop (H, W, 3) uint8 of one camera geometry -> luma box-filtered to ``gsd_m`` (float32)."""
    h, w = frame.shape[:2]
    cam_gsd = 2.0 * altitude_m * math.tan(math.radians(hfov_deg) / 2.0) / w
    size = (max(8, int(round(w * cam_gsd / gsd_m))), max(8, int(round(h * cam_gsd / gsd_m))))
    return tuple(cv2.resize(to_gray(img), size, interpolation=cv2.INTER_AREA) for img in (frame, crop))


_SAMPLER: dict[str, ExampleSampler] = {}


def _work(args: tuple[PairSpec, list[int]]) -> list[tuple[np.ndarray, np.ndarray, str]]:
    spec, indices = args
    key = repr(spec)
    if key not in _SAMPLER:
        _SAMPLER.clear()
        _SAMPLER[key] = ExampleSampler(spec.split, **spec.sampler_kwargs())
    sampler = _SAMPLER[key]
    out = []
    for i in indices:
        ex = sampler.sample(example_seed(spec.seed, spec.split, i))
        hfov = float(ex.meta["scenario"]["camera"]["hfov_deg"])
        f, m = reduce_pair(ex.frame, ex.map_crops[0], float(ex.pose[3]), hfov, spec.gsd_m)
        out.append((f, m, ex.meta["world"]))
    return out


def make_pairs(spec: PairSpec, workers: int = 1) -> PairSet:
    """The ``spec.n`` pairs of ``spec`` in index order (the same for any ``workers``)."""
    if spec.n < 1 or workers < 1:
        raise ConfigError(f"make_pairs: n = {spec.n} and workers = {workers} must be positive")
    chunks = [list(range(k, spec.n, workers)) for k in range(workers)]
    if workers == 1:
        parts = [_work((spec, chunks[0]))]
    else:
        import multiprocessing as mp

        with mp.get_context("spawn").Pool(workers) as pool:
            parts = pool.map(_work, [(spec, c) for c in chunks])
    items: list[Any] = [None] * spec.n
    for chunk, part in zip(chunks, parts, strict=True):
        for i, item in zip(chunk, part, strict=True):
            items[i] = item
    hmax = max(f.shape[0] for f, _, _ in items)
    wmax = max(f.shape[1] for f, _, _ in items)
    frames = np.zeros((spec.n, hmax, wmax), np.float32)
    maps = np.zeros_like(frames)
    sizes = np.zeros((spec.n, 2), np.int32)
    for i, (f, m, _) in enumerate(items):
        frames[i, :f.shape[0], :f.shape[1]] = f
        maps[i, :m.shape[0], :m.shape[1]] = m
        sizes[i] = f.shape[:2]
    return PairSet(frames, maps, sizes, tuple(w for _, _, w in items))


def save_pairs(pairs: PairSet, path: str) -> None:
    """Write ``pairs`` to an ``.npz`` (a cache between runs of a recipe)."""
    np.savez_compressed(path, frames=pairs.frames.astype(np.float16), maps=pairs.maps.astype(np.float16),
                        sizes=pairs.sizes, worlds=np.array(pairs.worlds))


def load_pairs(path: str) -> PairSet:
    """Read what ``save_pairs`` wrote."""
    with np.load(path, allow_pickle=False) as z:
        return PairSet(z["frames"].astype(np.float32), z["maps"].astype(np.float32), z["sizes"],
                       tuple(str(w) for w in z["worlds"]))
