"""Training the learned measurement model's encoder (``estimators.mcl.learned``): contrastive, on simulated pairs.

The encoder (``TorchEncoder``: a few convolutions, one of them strided, ReLU between, unit vectors out) embeds
the frame and the map with the same weights. A training pair is a camera frame and the map database at its true
pose (``learning.embedding_data``: simulated worlds of the train split across the realistic gap: epochs,
seasons, suns, map sensors, camera errors), locally normalized as at inference; a batch takes the same random
window of both (and the same quarter turn and flip). Two InfoNCE terms:

- **cells**: each of ``query_cells`` random cells of the frame's embedding against every cell of the map's
  (the same ground is the positive; every other cell, the nearest ones included, a negative), and back;
- **offsets**: the frame's central part correlated over the map's embedding (mean cosine per offset, as the
  measurement model scores particles), a softmax over the offsets with the true one as the target, at a
  learned temperature.

The recipe (``EmbeddingRecipe``, the ``[train]`` table of ``agents/mcl-learned.toml``) fixes the data, the
network, the budget and the seed; ``train_embedding`` runs it (deterministic for a seed and a thread count),
calibrates the likelihood's temperature on validation worlds (the one that maximizes the mean log-likelihood of
the true offset over the offsets' softmax) and writes the weights ``.npz`` the NumPy encoder reads, never over an
existing file unless asked. ``python -m aerial_loc_env.learning.embedding`` runs a recipe.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from aerial_loc_env.config import build_config, read_toml, rng
from aerial_loc_env.errors import ConfigError, require_extra
from aerial_loc_env.estimators.mcl.learned import WEIGHTS_FORMAT, local_normalize, write_archive
from aerial_loc_env.learning.embedding_data import PairSet, PairSpec, load_pairs, make_pairs, save_pairs

PURPOSE = "Training the learned MCL encoder (aerial_loc_env.learning.embedding)"


@dataclass(frozen=True)
class EmbeddingRecipe:
    """Data, network, budget and seed of one encoder (see the module doc)."""

    seed: int = field(default=0, metadata=rng(0, 2**31 - 1))
    n_train: int = field(default=2000, metadata=rng(1, 1_000_000, doc="training pairs"))
    n_train_worlds: int = field(default=24, metadata=rng(1, 10_000))
    n_val: int = field(default=200, metadata=rng(1, 100_000, doc="validation pairs (temperature, curves)"))
    n_val_worlds: int = field(default=4, metadata=rng(1, 10_000))
    city_size_m: float = field(default=400.0, metadata=rng(300.0, 8000.0))
    altitude_min_m: float = field(default=150.0, metadata=rng(50.0, 1000.0))
    altitude_max_m: float = field(default=250.0, metadata=rng(50.0, 1000.0))
    gsd_m: float = field(default=1.25, metadata=rng(0.1, 10.0, doc="the encoder's ground sampling"))
    norm_sigma_px: float = field(default=4.0, metadata=rng(0.5, 50.0, doc="local normalization window"))
    channels: tuple[int, ...] = (16, 16, 16, 8)
    kernels: tuple[int, ...] = (5, 3, 3, 1)
    strides: tuple[int, ...] = (2, 1, 1, 1)
    window_px: int = field(default=56, metadata=rng(4, 4096, doc="side of the square training windows"))
    steps: int = field(default=3000, metadata=rng(1, 10_000_000))
    batch: int = field(default=32, metadata=rng(1, 4096))
    learning_rate: float = field(default=2e-3, metadata=rng(0.0, 1.0, lo_open=True))
    query_cells: int = field(default=256, metadata=rng(1, 100_000))
    cell_temperature: float = field(default=0.1, metadata=rng(0.0, 10.0, lo_open=True))
    offset_weight: float = field(default=1.0, metadata=rng(0.0, 100.0))
    threads: int = field(default=2, metadata=rng(1, 256, doc="torch threads"))
    workers: int = field(default=2, metadata=rng(1, 64, doc="processes drawing the pairs"))
    max_wall_s: float = field(default=1680.0, metadata=rng(1.0, 1e7, doc="stop training past this"))

    def validate(self, where: str) -> None:
        n = len(self.channels)
        if n == 0 or len(self.kernels) != n or len(self.strides) != n:
            raise ConfigError(f"{where}: channels, kernels and strides must be lists of one length, got "
                              f"{list(self.channels)}, {list(self.kernels)}, {list(self.strides)}")
        if any(k % 2 != 1 or k < 1 for k in self.kernels) or any(s not in (1, 2) for s in self.strides):
            raise ConfigError(f"{where}: kernels must be odd and strides 1 or 2, got {list(self.kernels)}, "
                              f"{list(self.strides)}")
        if self.altitude_min_m > self.altitude_max_m:
            raise ConfigError(f"{where}: altitude_min_m {self.altitude_min_m} exceeds altitude_max_m "
                              f"{self.altitude_max_m}")
        stride = int(np.prod(self.strides))
        if self.window_px % (4 * stride):
            raise ConfigError(f"{where}: window_px {self.window_px} must be a multiple of {4 * stride}")

    def pair_spec(self, split: str) -> PairSpec:
        n, nw = (self.n_train, self.n_train_worlds) if split == "train" else (self.n_val, self.n_val_worlds)
        return PairSpec(split, n, nw, self.city_size_m, self.seed, (self.altitude_min_m, self.altitude_max_m),
                        self.gsd_m)


def recipe_path(name: str | Path) -> Path:
    """The spec file of a recipe: a TOML path, or a name in the package's ``agents/``."""
    from aerial_loc_env.paths import spec_dir

    p = Path(name)
    if not p.suffix:
        p = spec_dir("agents") / f"{name}.toml"
    if not p.is_file():
        raise ConfigError(f"embedding recipe: '{name}' is neither a TOML file nor a spec in agents/ ({p})")
    return p


def is_embedding_recipe(name: str | Path) -> bool:
    """Whether the spec's ``[train]`` table is an encoder recipe (``kind = "embedding"``), not an SB3 one."""
    try:
        table = read_toml(recipe_path(name), "recipe").get("train")
    except ConfigError:
        return False
    return isinstance(table, dict) and table.get("kind") == "embedding"


def read_recipe(name: str | Path, **overrides: Any) -> EmbeddingRecipe:
    """The ``[train]`` table of an agent spec (a path, or a name in the package's ``agents/``), with overrides."""
    p = recipe_path(name)
    table = read_toml(p, "recipe").get("train")
    if not isinstance(table, dict) or table.get("kind") != "embedding":
        raise ConfigError(f"embedding recipe: {p} has no [train] table with kind = \"embedding\"")
    table = {**{k: v for k, v in table.items() if k != "kind"}, **overrides}
    return build_config(EmbeddingRecipe, table, where=f"{p} [train]")


# ---------------------------------------------------------------------- the network (torch)
def _torch():
    return require_extra("torch", "rl", PURPOSE)


def torch_encoder(recipe: EmbeddingRecipe):
    """The encoder as a torch module (input (B, 1, H, W), output (B, C, h, w) unit vectors along C)."""
    th = _torch()
    nn = th.nn

    class TorchEncoder(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            layers, cin = [], 1
            for cout, k, s in zip(recipe.channels, recipe.kernels, recipe.strides, strict=True):
                layers.append(nn.Conv2d(cin, cout, k, stride=s, padding=k // 2))
                cin = cout
            self.convs = nn.ModuleList(layers)

        def forward(self, x):
            for i, conv in enumerate(self.convs):
                x = conv(x)
                if i < len(self.convs) - 1:
                    x = th.relu(x)
            return th.nn.functional.normalize(x, dim=1, eps=1e-6)

    return TorchEncoder()


def export_weights(net, recipe: EmbeddingRecipe, temperature: float, extra: dict | None = None) -> dict:
    """The arrays of a weights ``.npz`` (what ``estimators.mcl.learned.load_weights`` reads)."""
    arrays: dict[str, np.ndarray] = {}
    for i, conv in enumerate(net.convs):
        arrays[f"layer{i}_w"] = conv.weight.detach().cpu().numpy().astype(np.float32)
        arrays[f"layer{i}_b"] = conv.bias.detach().cpu().numpy().astype(np.float32)
    meta = {"format": WEIGHTS_FORMAT, "gsd_m": recipe.gsd_m, "norm_sigma_px": recipe.norm_sigma_px,
            "strides": list(recipe.strides), "temperature": float(temperature), "recipe": _jsonable(asdict(recipe)),
            **(extra or {})}
    arrays["meta"] = np.array(json.dumps(meta, sort_keys=True))
    return arrays


def _jsonable(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def write_weights(arrays: dict, path: str | Path, overwrite: bool = False) -> Path:
    """Write the weights ``.npz``; an existing file is kept (an error) unless ``overwrite``."""
    return write_archive(arrays, path, overwrite=overwrite, who="embedding")


# ---------------------------------------------------------------------- batches and losses
def normalized(pairs: PairSet, sigma_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Both sides of every pair locally normalized over its valid part (zero beyond)."""
    f, m = np.zeros_like(pairs.frames), np.zeros_like(pairs.maps)
    for i, (h, w) in enumerate(pairs.sizes):
        f[i, :h, :w] = local_normalize(pairs.frames[i, :h, :w], sigma_px)
        m[i, :h, :w] = local_normalize(pairs.maps[i, :h, :w], sigma_px)
    return f, m


def draw_batch(frames: np.ndarray, maps: np.ndarray, sizes: np.ndarray, window: int, batch: int,
               g: np.random.Generator, augment: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """``batch`` square windows (B, 1, window, window) of frames and of maps at the same place: a random pair and
    position, and with ``augment`` the batch's random quarter turn and flip (the central window without)."""
    idx = g.integers(0, len(frames), batch)
    turns = int(g.integers(0, 4)) if augment else 0
    flip = bool(g.integers(0, 2)) if augment else False
    fb = np.empty((batch, 1, window, window), np.float32)
    mb = np.empty_like(fb)
    for j, i in enumerate(idx):
        sh, sw = sizes[i]
        if min(sh, sw) < window:
            raise ConfigError(f"embedding: pair {i} ({sh} x {sw} px) is smaller than the window {window} px; lower "
                              "window_px or raise altitude_min_m")
        r0 = int(g.integers(0, sh - window + 1)) if augment else (sh - window) // 2
        c0 = int(g.integers(0, sw - window + 1)) if augment else (sw - window) // 2
        for src, dst in ((frames, fb), (maps, mb)):
            win = np.rot90(src[i, r0:r0 + window, c0:c0 + window], turns)
            dst[j, 0] = win[:, ::-1] if flip else win
    return fb, mb


def offset_scores(th, ef, em, margin: tuple[int, int]):
    """Mean cosine (B, 2 mh + 1, 2 mw + 1) of the frame embedding's centre (its cells ``margin`` in from each
    side) correlated over the map embedding; the true offset is the centre."""
    b, c, h, w = ef.shape
    mh, mw = margin
    tpl = ef[:, :, mh:h - mh, mw:w - mw].reshape(b, 1, -1)                 # (B, 1, C t)
    cols = th.nn.functional.unfold(em, (h - 2 * mh, w - 2 * mw))          # (B, C t, offsets)
    out = th.bmm(tpl, cols).reshape(b, 2 * mh + 1, 2 * mw + 1)
    return out / float((h - 2 * mh) * (w - 2 * mw))


def losses(th, net, fb, mb, recipe: EmbeddingRecipe, log_tau, g_torch) -> tuple[Any, dict]:
    """The two InfoNCE terms of a batch (see the module doc) and their values."""
    fn = th.nn.functional
    ef, em = net(fb), net(mb)
    b, c, h, w = ef.shape
    f = ef.flatten(2).transpose(1, 2)            # (B, P, C)
    m = em.flatten(2).transpose(1, 2)
    p = h * w
    q = th.randperm(p, generator=g_torch)[:min(recipe.query_cells, p)]
    inv_tau = 1.0 / recipe.cell_temperature
    target = q.expand(b, -1).reshape(-1)
    l_fm = fn.cross_entropy(th.bmm(f[:, q] * inv_tau, m.transpose(1, 2)).reshape(-1, p), target)
    l_mf = fn.cross_entropy(th.bmm(m[:, q] * inv_tau, f.transpose(1, 2)).reshape(-1, p), target)
    cells = 0.5 * (l_fm + l_mf)
    margin = (h // 4, w // 4)
    s = offset_scores(th, ef, em, margin)
    logits = s.flatten(1) / th.exp(log_tau)
    centre = margin[0] * (2 * margin[1] + 1) + margin[1]
    off = fn.cross_entropy(logits, th.full((b,), centre, dtype=th.long))
    with th.no_grad():
        hit = (logits.argmax(1) == centre).float().mean()
    return cells + recipe.offset_weight * off, {"cells": float(cells.detach()), "offsets": float(off.detach()),
                                                   "hit": float(hit)}


def calibrate_temperature(th, net, fv, mv, sizes, recipe: EmbeddingRecipe) -> tuple[float, dict]:
    """The temperature maximizing the mean log-softmax of the true offset on the validation pairs (central
    windows), and the figures at it (the mean log-likelihood, the share whose peak is the true offset)."""
    g = np.random.default_rng(recipe.seed + 1)
    fb, mb = draw_batch(fv, mv, sizes, recipe.window_px, len(fv), g, augment=False)
    with th.no_grad():
        ef, em = net(th.from_numpy(fb)), net(th.from_numpy(mb))
        h, w = ef.shape[2:]
        s = offset_scores(th, ef, em, (h // 4, w // 4)).flatten(1).double()
    centre = (h // 4) * (2 * (w // 4) + 1) + w // 4
    best = (-math.inf, 1.0)
    for t in np.exp(np.linspace(np.log(1e-3), np.log(1.0), 200)):
        ll = float(th.log_softmax(s / t, dim=1)[:, centre].mean())
        best = max(best, (ll, float(t)))
    hit = float((s.argmax(1) == centre).double().mean())
    return best[1], {"val_log_lik": best[0], "val_peak_hit": hit, "val_pairs": len(fv)}


@dataclass
class TrainResult:
    path: Path | None
    temperature: float
    history: list[dict]
    wall_s: float
    figures: dict


def train_embedding(recipe: EmbeddingRecipe, out: str | Path | None = None, *, overwrite: bool = False,
                    pairs: tuple[PairSet, PairSet] | None = None, cache_dir: str | Path | None = None,
                    log_every: int = 100, verbose: bool = False) -> TrainResult:
    """Run ``recipe``: draw (or take ``pairs``, or read from ``cache_dir``) the train and val pairs, train,
    calibrate, and write the weights to ``out`` (an ``.npz``; None: write nothing)."""
    th = _torch()
    t0 = time.perf_counter()
    if out is not None and Path(out).exists() and not overwrite:
        raise ConfigError(f"embedding: {out} exists; choose another --out or pass --overwrite to replace it")
    th.set_num_threads(recipe.threads)
    th.manual_seed(recipe.seed)
    if pairs is None:
        pairs = tuple(_pairs(recipe.pair_spec(split), recipe.workers, cache_dir) for split in ("train", "val"))
    train_pairs, val_pairs = pairs
    t_data = time.perf_counter() - t0
    ft, mt = normalized(train_pairs, recipe.norm_sigma_px)
    fv, mv = normalized(val_pairs, recipe.norm_sigma_px)
    net = torch_encoder(recipe)
    log_tau = th.nn.Parameter(th.tensor(math.log(0.05)))
    opt = th.optim.Adam([*net.parameters(), log_tau], lr=recipe.learning_rate)
    sched = th.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=recipe.steps)
    g = np.random.default_rng(recipe.seed)
    g_torch = th.Generator().manual_seed(recipe.seed)
    history: list[dict] = []
    acc: dict[str, float] = {}
    step = 0
    for step in range(1, recipe.steps + 1):
        fb, mb = draw_batch(ft, mt, train_pairs.sizes, recipe.window_px, recipe.batch, g)
        loss, parts = losses(th, net, th.from_numpy(fb), th.from_numpy(mb), recipe, log_tau, g_torch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        for k, v in parts.items():
            acc[k] = acc.get(k, 0.0) + v
        if step % log_every == 0 or step == recipe.steps:
            n = (step - 1) % log_every + 1
            row = {"step": step, "wall_s": round(time.perf_counter() - t0, 1),
                   **{k: round(v / n, 4) for k, v in acc.items()}}
            history.append(row)
            acc = {}
            if verbose:
                print(json.dumps(row), flush=True)
        if time.perf_counter() - t0 > recipe.max_wall_s:
            break
    net.eval()
    temperature, figures = calibrate_temperature(th, net, fv, mv, val_pairs.sizes, recipe)
    wall = time.perf_counter() - t0
    figures.update({"steps": step, "data_s": round(t_data, 1), "wall_s": round(wall, 1), "threads": recipe.threads})
    path = None
    if out is not None:
        path = write_weights(export_weights(net, recipe, temperature, {"training": figures}), out, overwrite)
    return TrainResult(path, temperature, history, wall, figures)


def _pairs(spec: PairSpec, workers: int, cache_dir: str | Path | None) -> PairSet:
    """The pairs of ``spec`` as the cache stores them (float16 luma), drawn or read from ``cache_dir``: a run with
    a cache and one without train on the same numbers."""
    if cache_dir is None:
        p = make_pairs(spec, workers)
        return PairSet(*(a.astype(np.float16).astype(np.float32) for a in (p.frames, p.maps)), p.sizes, p.worlds)
    key = f"{spec.split}_{spec.n}_{spec.n_worlds}_{spec.seed}_{spec.city_size_m:g}_{spec.altitude_m[0]:g}-" \
          f"{spec.altitude_m[1]:g}_{spec.gsd_m:g}.npz"
    p = Path(cache_dir) / key
    if p.is_file():
        return load_pairs(str(p))
    pairs = make_pairs(spec, workers)
    p.parent.mkdir(parents=True, exist_ok=True)
    save_pairs(pairs, str(p))
    return load_pairs(str(p))      # what a later run reads back (float16), so both runs train alike


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m aerial_loc_env.learning.embedding",
                                 description="Train the learned MCL encoder from a recipe (agents/mcl-learned.toml).")
    ap.add_argument("recipe", nargs="?", default="mcl-learned", help="an agent spec with a [train] table")
    ap.add_argument("--out", required=True, help="the weights .npz to write")
    ap.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    ap.add_argument("--cache", help="a folder keeping the drawn pairs between runs")
    ap.add_argument("--steps", type=int, help="override the recipe's steps")
    ap.add_argument("--history", help="write the training curve (JSON lines) here")
    args = ap.parse_args(argv)
    overrides = {"steps": args.steps} if args.steps else {}
    recipe = read_recipe(args.recipe, **overrides)
    res = train_embedding(recipe, args.out, overwrite=args.overwrite, cache_dir=args.cache, verbose=True)
    if args.history:
        Path(args.history).write_text("".join(json.dumps(r) + "\n" for r in res.history))
    print(json.dumps({"weights": str(res.path), "temperature": res.temperature, **res.figures}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
