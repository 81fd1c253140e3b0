"""Train / validation / test splits of the procedural worlds, by world and never by frame (as Procgen splits
by level).

A world is a city style (a *preset*, ``PRESETS``) and a city seed. The seed decides the split, so that a
city's street layout (drawn from its seed) is in one split whatever its style:

- the city seeds that the registered scenarios fly (``BENCHMARK_CITY_SEEDS``) are ``test``: the benchmark's own
  worlds are never trained on;
- any other seed goes by the SHA-256 of ``"aerial-loc-split-v<SPLIT_VERSION>:<seed>"``: its first 8 bytes as an
  integer modulo 1000, below 800 ``train``, below 900 ``val``, else ``test`` (80 / 10 / 10 %).

A held-out preset (``HELD_OUT_PRESETS``: the tower city of ``Downtown``) has worlds in ``test`` only, on the
test seeds: a model is judged on a kind of city it never saw. Its worlds on train or val seeds are ``"unused"``
(they would share their streets with a training world).

Splits are stable: the same world lands in the same split on every machine and in every release of the same
``SPLIT_VERSION``; changing any of the rules above means bumping it.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from aerial_loc_env.errors import ConfigError

SPLIT_VERSION = 1
SPLITS = ("train", "val", "test")
#: the city styles of the simulator's scenarios (their parameters: ``learning.dataset.PRESET_CITIES``)
PRESETS = ("paper", "downtown")
#: presets whose every world is in ``test``
HELD_OUT_PRESETS = ("downtown",)
#: the city seeds of the registered scenarios (envs/*.toml): test in every preset
BENCHMARK_CITY_SEEDS = frozenset({0, 1, 3})
#: per mille of the hashed seeds in train and in train + val
TRAIN_PER_MILLE, VAL_PER_MILLE = 800, 100
MAX_SEED = 2**63 - 1


@dataclass(frozen=True, order=True)
class WorldRef:
    """One procedural world of the splits: a city style and a city seed."""

    preset: str
    city_seed: int

    @property
    def name(self) -> str:
        return f"{self.preset}-{self.city_seed}"


def _check(preset: str, city_seed: int) -> None:
    if preset not in PRESETS:
        raise ConfigError(f"splits: unknown preset {preset!r}; use one of {', '.join(PRESETS)}")
    if isinstance(city_seed, bool) or not isinstance(city_seed, int) or not 0 <= city_seed <= MAX_SEED:
        raise ConfigError(f"splits: city seed {city_seed!r} must be an integer in [0, 2**63 - 1]")


def check_split(split: str) -> str:
    """``split`` itself, or a ConfigError naming the allowed ones."""
    if split not in SPLITS:
        raise ConfigError(f"splits: unknown split {split!r}; use one of {', '.join(SPLITS)}")
    return split


def seed_bucket(city_seed: int) -> int:
    """The seed's hash bucket in [0, 1000) (see the module doc)."""
    digest = hashlib.sha256(f"aerial-loc-split-v{SPLIT_VERSION}:{int(city_seed)}".encode()).digest()
    return int.from_bytes(digest[:8], "big") % 1000


def seed_split(city_seed: int) -> str:
    """The split of a city seed: ``"test"`` for the benchmark's seeds, else by its hash bucket."""
    if city_seed in BENCHMARK_CITY_SEEDS:
        return "test"
    bucket = seed_bucket(city_seed)
    return "train" if bucket < TRAIN_PER_MILLE else "val" if bucket < TRAIN_PER_MILLE + VAL_PER_MILLE else "test"


def split_of(preset: str, city_seed: int) -> str:
    """The split (``"train"``, ``"val"`` or ``"test"``) of the world ``(preset, city_seed)``, or ``"unused"`` for
    a held-out preset's world on a train or val seed (see the module doc)."""
    _check(preset, city_seed)
    split = seed_split(city_seed)
    return "unused" if preset in HELD_OUT_PRESETS and split != "test" else split


def split_presets(split: str) -> tuple[str, ...]:
    """The presets that have worlds in ``split`` (a held-out preset only in test)."""
    check_split(split)
    return PRESETS if split == "test" else tuple(p for p in PRESETS if p not in HELD_OUT_PRESETS)


def worlds(split: str, n: int, presets: tuple[str, ...] | None = None) -> tuple[WorldRef, ...]:
    """The first ``n`` worlds of ``split``: the presets in turn (``presets``, default every one the split has),
    each with its next seed in ascending order that falls in the split. The same call gives the same worlds."""
    check_split(split)
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ConfigError(f"splits: the number of worlds must be a positive integer, got {n!r}")
    allowed = split_presets(split)
    chosen = tuple(presets) if presets is not None else allowed
    bad = [p for p in chosen if p not in allowed]
    if bad or not chosen:
        raise ConfigError(f"splits: preset(s) {bad or chosen!r} have no worlds in split {split!r}; "
                          f"its presets are {', '.join(allowed)} (held out for test: {', '.join(HELD_OUT_PRESETS)})")
    out: list[WorldRef] = []
    next_seed = dict.fromkeys(chosen, 0)
    while len(out) < n:
        for preset in chosen:
            seed = next_seed[preset]
            while split_of(preset, seed) != split:
                seed += 1
            out.append(WorldRef(preset, seed))
            next_seed[preset] = seed + 1
            if len(out) == n:
                break
    return tuple(out)
