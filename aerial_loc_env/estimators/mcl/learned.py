"""A learned measurement model for the MCL: dense embeddings of the camera frame and the map, compared by
correlation (``mcl-learned``).

A small convolutional encoder (trained contrastively on simulated two-epoch pairs, ``learning.embedding``) maps
a gray image, resampled to a fixed ground sampling and locally normalized, to a dense field of unit vectors (a
few channels, one per ``stride`` pixels) in which the same ground at two epochs, under two suns or from two
sensors has similar vectors. Inference needs NumPy, OpenCV and numba only: the weights are a small ``.npz`` (shipped
as package data) and the convolutions and correlations run as compiled kernels (``learned_kernels``); torch is for
training only.

The model, per episode and per frame:

- **the map** (``reset``): the database's luma resampled to the encoder's ground sampling (``cv2.INTER_AREA``),
  embedded once and kept (``_MAP_CACHE``, by the map's pixels and the weights), zero-padded so that footprints
  reaching past the map's edge score the part they overlap; a window of a map read by window is embedded alone;
- **the frame** (``prepare``): the camera luma reduced to about the encoder's sampling, warped north-up by the
  measured heading and altitude onto the map level's pixel grid (``frame_canvas``: the same ground per pixel as
  the map's level), embedded once; cells outside the footprint are masked out;
- **the particles** (``log_likelihood``): one correlation surface of the frame's embedding over the map's, over
  the box that holds the particles, computed at the cells the particles' lookups read only (summed over the
  channels and the footprint's cells: ``learned_kernels.correlate_cells``), or over the whole box by
  ``cv2.matchTemplate`` where most of it is read (``CELLS_PER_REGION_CELL``), normalized by the frame's valid cells
  (the mean cosine similarity, in [-1, 1]); each particle reads it at its position by a bilinear lookup.
  The log-likelihood is ``score / temperature``, the temperature calibrated on simulated validation worlds and
  stored with the weights (``temperature`` overrides it).

The particle's own yaw does not enter the score: the frame is aligned by the measured heading (as the compass
likelihood of the core weighs the particles' yaw), so a heading error of a degree turns the frame about its
centre, which leaves the position of the correlation peak in place.
"""

from __future__ import annotations

import hashlib
import json
import math
import zipfile
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import cv2
import numpy as np

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators.database import DatabaseWindow
from aerial_loc_env.estimators.mcl import learned_kernels as _kern
from aerial_loc_env.estimators.mcl.measurement import MeasurementModel, register_model
from aerial_loc_env.estimators.patches import to_gray
from aerial_loc_env.estimators.protocol import parse_observation
from aerial_loc_env.paths import find_model_file

DEFAULT_WEIGHTS = "models/mcl-learned/weights.npz"
#: the weights file's format version (``meta["format"]``)
WEIGHTS_FORMAT = 1
#: what a weights file's ``meta`` must hold
META_KEYS = ("format", "gsd_m", "norm_sigma_px", "strides", "temperature")


# ---------------------------------------------------------------------- the encoder
def local_normalize(gray: np.ndarray, sigma_px: float, mask: np.ndarray | None = None) -> np.ndarray:
    """``(g - mean) / std`` over a Gaussian window of ``sigma_px`` (float32): invariant to a local gain and offset,
    as seasons, suns and sensors change them. With ``mask`` (bool), the moments average the valid pixels only
    and invalid pixels come out 0."""
    g = np.asarray(gray, dtype=np.float32) / np.float32(255.0)
    blur = lambda a: cv2.GaussianBlur(a, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)  # noqa: E731
    if mask is None:
        mu = blur(g)
        var = blur(np.square(g - mu))
        return (g - mu) / np.sqrt(var + np.float32(1e-4))
    m = mask.astype(np.float32)
    w = np.maximum(blur(m), np.float32(1e-3))
    mu = blur(g * m) / w
    d = (g - mu) * m
    var = blur(np.square(d)) / w
    return d / np.sqrt(var + np.float32(1e-4))


class _Layer(NamedTuple):
    """One convolution as ``learned_kernels.conv_terms`` sums it: a term per (input channel, tap), read from the
    input's phase plane ``plane`` (``ci s^2 + (dy % s) s + dx % s``) at the row / column shift (``dy // s``,
    ``dx // s``); weights (outputs padded to ``OUT_GROUP``, terms to ``TERM_GROUP``, padding 0)."""

    weight: np.ndarray      # (O, T) float32
    bias: np.ndarray        # (O,) float32
    plane: np.ndarray       # (T,) int64
    shift: np.ndarray       # (T, 2) int64: (row, column) in phase-plane cells
    k: int
    stride: int
    cin: int
    cout: int


class Encoder:
    """The encoder's forward pass: zero-padded convolutions (``padding = k // 2``), ReLU between layers, none
    after the last, then unit vectors along the channels (torch's ``Conv2d`` / ``F.normalize`` layout: weights
    (out, in, k, k)). Input (H, W) float32; output (h, w, C) float32.

    Each layer runs as one compiled pass (``learned_kernels.conv_terms``) over channel planes: the padded input
    split into its ``stride**2`` phases (every ``stride``-th row and column from each offset), all planes on the
    output's row pitch plus the kernel's reach, so that each tap is a shift of one plane."""

    def __init__(self, weights: list[np.ndarray], biases: list[np.ndarray], strides: list[int]) -> None:
        if not (len(weights) == len(biases) == len(strides) > 0):
            raise ConfigError("Encoder: weights, biases and strides must have the same positive length")
        self.layers: list[_Layer] = []
        for w, b, s in zip(weights, biases, strides, strict=True):
            w = np.asarray(w, np.float32)
            if w.ndim != 4 or w.shape[2] != w.shape[3] or w.shape[2] % 2 != 1 or b.shape != (w.shape[0],):
                raise ConfigError(f"Encoder: a layer's weights {w.shape} / bias {b.shape} are not (out, in, k, k) "
                                  "with an odd k and (out,)")
            if int(s) < 1:
                raise ConfigError(f"Encoder: strides must be >= 1, got {s}")
            self.layers.append(self._layer(w, np.asarray(b, np.float32), int(s)))
        for prev, layer in zip(self.layers[:-1], self.layers[1:], strict=True):
            if layer.cin != prev.cout:
                raise ConfigError("Encoder: a layer's input channels differ from the previous layer's outputs")
        if self.layers[0].cin != 1:
            raise ConfigError("Encoder: the first layer must take one (gray) channel")
        self.stride = int(np.prod(strides))
        self.channels = self.layers[-1].cout

    @staticmethod
    def _layer(w: np.ndarray, b: np.ndarray, s: int) -> _Layer:
        cout, cin, k, _ = w.shape
        ci, dy, dx = (a.ravel() for a in np.meshgrid(np.arange(cin), np.arange(k), np.arange(k), indexing="ij"))
        n_out = -(-cout // _kern.OUT_GROUP) * _kern.OUT_GROUP
        n_terms = -(-len(ci) // _kern.TERM_GROUP) * _kern.TERM_GROUP
        weight = np.zeros((n_out, n_terms), np.float32)
        weight[:cout, :len(ci)] = w.reshape(cout, -1)             # (ci, dy, dx) order, as ci, dy, dx above
        bias = np.zeros(n_out, np.float32)
        bias[:cout] = b
        plane = np.zeros(n_terms, np.int64)
        plane[:len(ci)] = ci * s * s + (dy % s) * s + dx % s
        shift = np.zeros((n_terms, 2), np.int64)
        shift[:len(ci)] = np.stack([dy // s, dx // s], axis=1)
        return _Layer(weight, bias, plane, shift, int(k), s, int(cin), int(cout))

    def __call__(self, image: np.ndarray) -> np.ndarray:
        x = np.asarray(image, np.float32)[None]
        last = len(self.layers) - 1
        for i, layer in enumerate(self.layers):
            k, s, cin = layer.k, layer.stride, layer.cin
            p = k // 2
            h, w = x.shape[1:]
            ho, wo = (h - 1) // s + 1, (w - 1) // s + 1
            q = (k - 1) // s                       # the farthest shift in phase-plane cells
            rows, pitch = ho + q, wo + q
            src = np.zeros((cin * s * s, rows * pitch + q), np.float32)
            phases = src[:, :rows * pitch].reshape(cin, s, s, rows, pitch)
            if s == 1:
                phases[:, 0, 0, p:p + h, p:p + w] = x
            else:
                xp = np.zeros((cin, max(s * rows, p + h), max(s * pitch, p + w)), np.float32)
                xp[:, p:p + h, p:p + w] = x
                for a in range(s):
                    for c in range(s):
                        phases[:, a, c] = xp[:, a::s, c::s][:, :rows, :pitch]
            offset = layer.shift[:, 0] * pitch + layer.shift[:, 1]
            out = np.empty((len(layer.bias), ho * pitch), np.float32)
            _kern.conv_terms(src, layer.plane, offset, layer.weight, layer.bias, ho * pitch, i < last, out)
            x = out[:layer.cout].reshape(layer.cout, ho, pitch)[:, :, :wo]
        e = np.empty((ho, wo, self.channels), np.float32)
        _kern.unit_cells(out, self.channels, ho, wo, pitch, e)
        return e


class Weights(NamedTuple):
    """A loaded weights file: the encoder, its metadata and the file's digest (the map cache's key)."""

    encoder: Encoder
    meta: dict
    digest: str


_WEIGHTS: dict[str, Weights] = {}


def resolve_weights(path: str) -> Path:
    """The weights file: absolute, else under the package folder, else under the current directory."""
    return find_model_file(path, "mcl-learned: weights file", "give measurement_params.weights the .npz that "
                           "`aerial-loc train mcl-learned --out W.npz` wrote, or leave it at the shipped "
                           f"'{DEFAULT_WEIGHTS}'")


def archive_bytes(file: Path) -> tuple[bytes, str, str]:
    """A weights file's bytes, their digest (16 hex digits) and its cache key (the path and the digest)."""
    raw = file.read_bytes()
    digest = hashlib.sha256(raw).hexdigest()[:16]
    return raw, digest, f"{file}:{digest}"


def read_archive(raw: bytes) -> tuple[dict[str, np.ndarray], dict]:
    """The arrays and the ``meta`` JSON of an ``.npz`` archive's bytes (no pickles allowed)."""
    import io

    with np.load(io.BytesIO(raw), allow_pickle=False) as z:
        arrays = {name: z[name] for name in z.files}
    return arrays, json.loads(str(arrays.pop("meta")))


def write_archive(arrays: Mapping[str, np.ndarray], path: str | Path, *, overwrite: bool, who: str) -> Path:
    """Write an ``.npz`` archive (its arrays and a ``meta`` JSON array, what ``read_archive`` reads) through a
    temporary file beside it; an existing file only with ``overwrite``: a user's model is never replaced by
    accident."""
    p = Path(path)
    if p.exists() and not overwrite:
        raise ConfigError(f"{who}: {p} exists; choose another --out or pass --overwrite to replace it")
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(p.name + ".partial.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(p)
    return p


def checked_archive(raw: bytes, why: str, kind: str, remedy: str) -> tuple[dict[str, np.ndarray], dict]:
    """``read_archive``, a damaged or foreign file reported as a ``ConfigError`` naming it (``why``), what it should
    be (``kind``) and how to write it again (``remedy``)."""
    try:
        return read_archive(raw)
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        raise ConfigError(f"{why} is not a {kind} archive ({type(exc).__name__}: {exc}); write it again with "
                          f"{remedy}") from exc


def load_weights(path: str) -> Weights:
    """Read and check a weights ``.npz`` (``layer{i}_w``, ``layer{i}_b``, ``meta`` JSON); cached by path and
    content."""
    file = resolve_weights(path)
    raw, digest, key = archive_bytes(file)
    if key in _WEIGHTS:
        return _WEIGHTS[key]
    why = f"mcl-learned: weights file '{file}'"
    arrays, meta = checked_archive(raw, why, "weights", "`python -m aerial_loc_env.learning.embedding`")
    missing = [k for k in META_KEYS if k not in meta]
    if missing or meta.get("format") != WEIGHTS_FORMAT:
        raise ConfigError(f"{why}: metadata lacks {missing} or has format {meta.get('format')!r} (expected "
                          f"{WEIGHTS_FORMAT}); write it again with `python -m aerial_loc_env.learning.embedding`")
    n = len(meta["strides"])
    try:
        ws = [arrays[f"layer{i}_w"] for i in range(n)]
        bs = [arrays[f"layer{i}_b"] for i in range(n)]
    except KeyError as exc:
        raise ConfigError(f"{why}: array {exc} is missing ({n} layers declared)") from exc
    if not all(np.isfinite(a).all() for a in ws + bs):
        raise ConfigError(f"{why}: the weights hold NaN or infinite values")
    if not (float(meta["gsd_m"]) > 0 and float(meta["temperature"]) > 0 and float(meta["norm_sigma_px"]) > 0):
        raise ConfigError(f"{why}: gsd_m, temperature and norm_sigma_px must be positive, got {meta}")
    _WEIGHTS[key] = Weights(Encoder(ws, bs, [int(s) for s in meta["strides"]]), meta, digest)
    return _WEIGHTS[key]


def embed(weights: Weights, gray: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The embedding (h, w, C) of a gray image already at the encoder's sampling (zero where ``mask``'s cell is
    invalid)."""
    x = local_normalize(gray, float(weights.meta["norm_sigma_px"]), mask)
    e = weights.encoder(x)
    if mask is not None:
        s = weights.encoder.stride
        e *= mask[::s, ::s][:e.shape[0], :e.shape[1], None]
    return e


# ---------------------------------------------------------------------- geometry
def frame_canvas(gray: np.ndarray, camera, yaw_rad: float, altitude_m: float, pixel_m: tuple[float, float],
                 stride: int) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
    """The camera luma north-up on a grid of ``pixel_m`` (east, north) metres per pixel, its footprint's bounding
    box (a multiple of ``stride`` pixels on each side): (image float32, valid mask bool, the vehicle's canvas
    pixel (col, row)). The frame is box-filtered to about the grid's sampling first (no aliasing)."""
    a = camera.camera_to_world(0.0, 0.0, yaw_rad, altitude_m)              # camera px -> metres from the vehicle
    corners = np.asarray(camera.footprint_corners_m(0.0, 0.0, yaw_rad, altitude_m))
    px, py = pixel_m
    half_w = float(np.abs(corners[:, 0]).max()) / px
    half_h = float(np.abs(corners[:, 1]).max()) / py
    cw = max(stride, int(math.ceil(2.0 * half_w / stride)) * stride)
    ch = max(stride, int(math.ceil(2.0 * half_h / stride)) * stride)
    ccx, ccy = (cw - 1) / 2.0, (ch - 1) / 2.0
    # canvas px -> metres: east = (c - ccx) px, north = -(r - ccy) py
    canvas_to_world = np.array([[px, 0.0, -ccx * px], [0.0, -py, ccy * py], [0.0, 0.0, 1.0]])
    a3 = np.vstack([a, [0.0, 0.0, 1.0]])
    canvas_to_cam = np.linalg.inv(a3) @ canvas_to_world
    h, w = gray.shape[:2]
    factor = max(1.0, min(px, py) / float(camera.gsd_m(altitude_m)))
    sw, sh = max(2, int(round(w / factor))), max(2, int(round(h / factor)))
    small = cv2.resize(np.asarray(gray, np.float32), (sw, sh), interpolation=cv2.INTER_AREA)
    fx, fy = w / sw, h / sh
    cam_to_small = np.array([[1.0 / fx, 0.0, 0.5 / fx - 0.5], [0.0, 1.0 / fy, 0.5 / fy - 0.5], [0.0, 0.0, 1.0]])
    m = (cam_to_small @ canvas_to_cam)[:2]
    img = cv2.warpAffine(small, m, (cw, ch), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE)
    inside = cv2.warpAffine(np.ones((sh, sw), np.uint8), m, (cw, ch), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                            borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    inside = cv2.erode(inside, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return img, inside.astype(bool), (ccx, ccy)


class MapEmbedding(NamedTuple):
    """A map's embedding, zero-padded by ``pad`` cells, and the affine world metres -> (padded) cell (col, row)."""

    cells: np.ndarray            # (h + 2 pad, w + 2 pad, C) float32
    pad: int
    world_to_cell: np.ndarray    # (2, 3)
    pixel_m: tuple[float, float]  # the level's ground size of a pixel (east, north)


#: the surface is summed directly at the particles' cells while (cells x the frame's valid cells) stays below this
#: times the box's region (in cells), else correlated over the whole box by ``cv2.matchTemplate``: about where the
#: two cost the same (docs/perf-log.md)
CELLS_PER_REGION_CELL = 100

#: map embeddings by (weights digest, map key), least recently used dropped first
_MAP_CACHE: OrderedDict[tuple, MapEmbedding] = OrderedDict()
MAP_CACHE_SIZE = 4


def _map_key(orthomap) -> tuple:
    """What identifies a map's pixels: its size, sampling, window and a digest of a strided sample of them."""
    rgb = orthomap.rgb
    box = orthomap.box if isinstance(orthomap, DatabaseWindow) else None
    step = max(1, int(math.sqrt(rgb.shape[0] * rgb.shape[1] / 65536)))
    sample = np.ascontiguousarray(rgb[::step, ::step])
    return (getattr(orthomap, "name", ""), rgb.shape, orthomap.gsd_x_m, orthomap.gsd_y_m, box,
            hashlib.sha256(sample.tobytes()).hexdigest()[:16])


def embed_map(weights: Weights, orthomap, pad: int) -> MapEmbedding:
    """The map's (or window's) embedding at the encoder's sampling, padded by ``pad`` cells (cached)."""
    key = (weights.digest, pad, _map_key(orthomap))
    if key in _MAP_CACHE:
        _MAP_CACHE.move_to_end(key)
        return _MAP_CACHE[key]
    gsd = float(weights.meta["gsd_m"])
    rgb = orthomap.rgb
    h, w = rgb.shape[:2]
    lw = max(2, int(round(w * orthomap.gsd_x_m / gsd)))
    lh = max(2, int(round(h * orthomap.gsd_y_m / gsd)))
    gray = to_gray(rgb)
    level = cv2.resize(gray, (lw, lh), interpolation=cv2.INTER_AREA) if (lw, lh) != (w, h) else gray
    mask = None
    nodata = orthomap.nodata
    if nodata is not None and np.any(nodata):
        mask = cv2.resize(np.asarray(nodata, np.float32), (lw, lh), interpolation=cv2.INTER_AREA) <= 0.0
    cells = embed(weights, level, mask)
    cells = np.pad(cells, ((pad, pad), (pad, pad), (0, 0)))
    fx, fy = w / lw, h / lh
    s = weights.encoder.stride
    u0, v0 = (orthomap.box[0], orthomap.box[1]) if isinstance(orthomap, DatabaseWindow) else (0, 0)
    # world -> whole-map px (pixel centres at integers) -> window px -> level px -> cell, + pad
    height = orthomap.height_px
    gx, gy = orthomap.gsd_x_m, orthomap.gsd_y_m
    to_px = np.array([[1.0 / gx, 0.0, -0.5 - u0], [0.0, -1.0 / gy, height - 0.5 - v0], [0.0, 0.0, 1.0]])
    to_level = np.array([[1.0 / fx, 0.0, 0.5 / fx - 0.5], [0.0, 1.0 / fy, 0.5 / fy - 0.5], [0.0, 0.0, 1.0]])
    to_cell = np.array([[1.0 / s, 0.0, pad], [0.0, 1.0 / s, pad], [0.0, 0.0, 1.0]])
    out = MapEmbedding(np.ascontiguousarray(cells), pad, (to_cell @ to_level @ to_px)[:2], (gx * fx, gy * fy))
    _MAP_CACHE[key] = out
    while len(_MAP_CACHE) > MAP_CACHE_SIZE:
        _MAP_CACHE.popitem(last=False)
    return out


def correlate(region: np.ndarray, template: np.ndarray) -> np.ndarray:
    """Sum over channels of the cross-correlation (``TM_CCORR``) of ``template`` (h, w, C) over ``region``."""
    out = None
    for c0 in range(0, template.shape[2], 4):
        c1 = min(c0 + 4, template.shape[2])
        if c1 - c0 == 2:      # matchTemplate takes 1, 3 or 4 channels
            parts = [(c0, c0 + 1), (c0 + 1, c1)]
        else:
            parts = [(c0, c1)]
        for a, b in parts:
            r = cv2.matchTemplate(np.ascontiguousarray(region[:, :, a:b]), np.ascontiguousarray(template[:, :, a:b]),
                                  cv2.TM_CCORR)
            out = r if out is None else out + r
    return out


def _corners(shape: tuple[int, int], x: np.ndarray, y: np.ndarray):
    """What ``bilinear`` reads of a (h, w) surface at (x, y): inside, the corner cells (x0, y0, x1, y1) and the
    fractions (fx, fy)."""
    h, w = shape
    ok = (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
    xc, yc = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    x0 = np.minimum(np.floor(xc).astype(np.intp), max(w - 2, 0))
    y0 = np.minimum(np.floor(yc).astype(np.intp), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    return ok, x0, y0, x1, y1, xc - x0, yc - y0


def bilinear(surface: np.ndarray, x: np.ndarray, y: np.ndarray, outside: float) -> np.ndarray:
    """``surface`` read at (x, y) (col, row; centres at integers), ``outside`` beyond its last cells."""
    ok, x0, y0, x1, y1, fx, fy = _corners(surface.shape, x, y)
    v = ((surface[y0, x0] * (1 - fx) + surface[y0, x1] * fx) * (1 - fy)
         + (surface[y1, x0] * (1 - fx) + surface[y1, x1] * fx) * fy)
    return np.where(ok, v, outside)


# ---------------------------------------------------------------------- the measurement model
@dataclass(frozen=True)
class LearnedConfig:
    """The weights file (package-relative, absolute, or relative to the current directory) and the temperature
    of ``log p = score / temperature`` (0: the one calibrated with the weights)."""

    weights: str = DEFAULT_WEIGHTS
    temperature: float = field(default=0.0, metadata=rng(0.0, 100.0, doc="0: the calibrated one"))
    temper: float = field(default=1.0, metadata=rng(0.0, 100.0, lo_open=True,
                                                     doc="multiplies the log-likelihood"))


class FramePrepared(NamedTuple):
    template: np.ndarray       # (h, w, C) the frame's embedding, zero on invalid cells
    n_valid: int
    centre_cell: tuple[float, float]   # the vehicle's (col, row) in template cells
    first: np.ndarray          # (h,) each template row's first valid column (int64) ...
    stop: np.ndarray           # (h,) ... and one past its last (first = stop = 0: none)


class LearnedModel(MeasurementModel):
    """Dense learned embeddings compared by correlation (see the module doc)."""

    Config: ClassVar[type] = LearnedConfig
    reads_windows: ClassVar[bool] = True

    def __init__(self, config: LearnedConfig | None = None) -> None:
        super().__init__(config or LearnedConfig())
        self.weights = load_weights(self.config.weights)      # a missing or corrupt file fails at construction
        self.map: MapEmbedding | None = None

    @property
    def temperature(self) -> float:
        return float(self.config.temperature or self.weights.meta["temperature"])

    def reset(self, briefing, rng: np.random.Generator) -> None:
        self.camera = briefing.camera
        cam = briefing.camera
        s = self.weights.encoder.stride
        # the widest footprint's half-diagonal at the highest altitude the flight is briefed for, in cells
        w_m, h_m = cam.footprint_m(1.25 * briefing.altitude_m)
        pad = int(math.ceil(0.5 * math.hypot(w_m, h_m) / (float(self.weights.meta["gsd_m"]) * s))) + 2
        self.map = embed_map(self.weights, briefing.orthomap, pad)

    def prepare(self, observation: Mapping[str, np.ndarray], rng: np.random.Generator,
                info: Mapping[str, Any] | None = None) -> FramePrepared:
        if self.map is None:
            raise ConfigError("LearnedModel: call reset(briefing, rng) before prepare()")
        obs = parse_observation(observation)
        cam = self.camera
        if obs.image.shape[:2] != (cam.height_px, cam.width_px):
            raise ConfigError(f"LearnedModel: observation image {obs.image.shape[:2]} differs from the briefing's "
                              f"camera ({cam.height_px}, {cam.width_px})")
        s = self.weights.encoder.stride
        img, mask, (ccx, ccy) = frame_canvas(to_gray(obs.image), cam, obs.yaw_rad, obs.altitude_m,
                                             self.map.pixel_m, s)
        template = embed(self.weights, img, mask)
        valid = np.einsum("hwc,hwc->hw", template, template) > 0.5
        any_valid = valid.any(axis=1)
        first = np.where(any_valid, np.argmax(valid, axis=1), 0)
        stop = np.where(any_valid, valid.shape[1] - np.argmax(valid[:, ::-1], axis=1), 0)
        return FramePrepared(np.ascontiguousarray(template), int(valid.sum()), (ccx / s, ccy / s),
                             first.astype(np.int64), stop.astype(np.int64))

    def scores(self, prepared: FramePrepared, states: np.ndarray) -> np.ndarray:
        """The mean cosine similarity (N,) of the frame's embedding with the map's at each particle's position
        (-1 off the padded map)."""
        states = np.asarray(states, dtype=np.float64)
        emb = self.map
        a = emb.world_to_cell
        cx = a[0, 0] * states[:, 0] + a[0, 1] * states[:, 1] + a[0, 2]
        cy = a[1, 0] * states[:, 0] + a[1, 1] * states[:, 1] + a[1, 2]
        th, tw = prepared.template.shape[:2]
        # surface index (a, b): the template's cell (0, 0) on map cell (a, b), the vehicle at (a + ccx, b + ccy)
        sx, sy = cx - prepared.centre_cell[0], cy - prepared.centre_cell[1]
        mh, mw = emb.cells.shape[:2]
        finite = np.isfinite(sx) & np.isfinite(sy)
        out = np.full(len(states), -1.0)
        if prepared.n_valid == 0 or not finite.any():
            return out
        a0 = max(0, int(math.floor(sx[finite].min())))
        b0 = max(0, int(math.floor(sy[finite].min())))
        a1 = min(mw - tw, int(math.ceil(sx[finite].max())) + 1)
        b1 = min(mh - th, int(math.ceil(sy[finite].max())) + 1)
        if a1 < a0 or b1 < b0:
            return out
        # the surface over the box, at the cells the particles' bilinear lookups read (a sum over the template's
        # valid cells each), or over the whole box where that costs more (matchTemplate's cost grows with the box)
        h, w = b1 - b0 + 1, a1 - a0 + 1
        x, y = np.where(finite, sx - a0, -1.0), np.where(finite, sy - b0, -1.0)
        ok, x0, y0, x1, y1, _, _ = _corners((max(h, 2), max(w, 2)), x, y)   # on the edge-padded surface
        need = np.zeros((h, w), bool)
        for yy in (y0[ok], y1[ok]):
            for xx in (x0[ok], x1[ok]):
                need[np.minimum(yy, h - 1), np.minimum(xx, w - 1)] = True
        rows, cols = np.nonzero(need)
        if len(rows) * prepared.n_valid <= CELLS_PER_REGION_CELL * (h + th - 1) * (w + tw - 1):
            values = np.empty(len(rows), np.float32)
            _kern.correlate_cells(emb.cells, prepared.template, prepared.first, prepared.stop, rows + b0,
                                  cols + a0, values)
            surface = np.zeros((h, w), np.float32)
            surface[rows, cols] = values / np.float32(prepared.n_valid)
        else:       # most of a box read (a grid of positions): the whole surface by OpenCV's transform
            region = emb.cells[b0:b1 + th, a0:a1 + tw]
            surface = correlate(region, prepared.template) / np.float32(prepared.n_valid)
        if h < 2 or w < 2:
            surface = np.pad(surface, ((0, max(0, 2 - h)), (0, max(0, 2 - w))), mode="edge")
        v = bilinear(surface.astype(np.float64), x, y, -1.0)
        # beyond the surface's box (clipped at the padded map's edge): the worst score
        return np.clip(v, -1.0, 1.0)

    def log_likelihood(self, prepared: FramePrepared, states: np.ndarray, altitude_m: float) -> np.ndarray:
        if self.map is None:
            raise ConfigError("LearnedModel: call reset(briefing, rng) before log_likelihood()")
        score = self.scores(prepared, states)
        self.last_stats = {"valid_cells": prepared.n_valid, "score_max": float(score.max()) if score.size else
                           float("nan")}
        return score * (self.config.temper / self.temperature)


register_model("learned", LearnedModel)
