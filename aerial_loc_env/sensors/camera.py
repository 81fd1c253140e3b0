"""Nadir camera model: footprint geometry and the affine maps between camera, world and map pixels.

Conventions (docs/ARCHITECTURE.md): camera column ``u`` grows to the vehicle's right, row ``v`` towards its
tail, so the top of the image points along the heading; pixel centres sit at integers. The vehicle is below
the image centre ``((W - 1) / 2, (H - 1) / 2)``. World ``x`` is east, ``y`` north, yaw counter-clockwise from
east.

Every transform here is an affine 2x3 matrix ``A`` with ``dst = A[:, :2] @ (u, v) + A[:, 2]``, vectorized
over any batch of poses. ``camera_to_map`` is the paper's eq. (3), ``x_hat = s R(psi) x + T``: the
measurement models of the estimators project their sample pixels with ``project_pixels`` rather than
re-deriving it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple, Protocol

import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError

ArrayLike = float | np.ndarray

#: 41.11 deg, exactly ``2 atan(0.375)``: 600 px cover 150 m at 200 m, i.e. 0.25 m/px (the paper's setup).
DEFAULT_HFOV_DEG = math.degrees(2.0 * math.atan(0.375))


class MapGrid(Protocol):
    """What the camera needs of a map: its pixel size and height (``Orthomap`` satisfies this)."""

    gsd_x_m: float
    gsd_y_m: float

    @property
    def height_px(self) -> int: ...


class Pose(NamedTuple):
    """The camera pose: world position (metres), ENU yaw (rad, 0 = east) and altitude above ground (m)."""

    x_m: float
    y_m: float
    yaw_rad: float
    altitude_m: float


@dataclass(frozen=True)
class CameraModel:
    """A gimbaled nadir pinhole camera with no distortion.

    The default 41.11 deg (exactly ``2 atan(0.375)``) horizontal field of view gives a 150 m wide footprint
    at 200 m, i.e. 0.25 m/px over 600 px: the paper's crop of its 0.25 m/px database. ``pixel_aspect``
    (ground size of a pixel along ``v`` over along ``u``) is 1 for a real sensor; ``resized`` changes it
    when an observation is resized to another aspect ratio, so that the footprint stays the same.
    """

    width_px: int = field(default=600, metadata=rng(1, 20000, doc="image width"))
    height_px: int = field(default=400, metadata=rng(1, 20000, doc="image height"))
    hfov_deg: float = field(default=DEFAULT_HFOV_DEG,
                            metadata=rng(0.0, 170.0, lo_open=True, hi_open=True, doc="horizontal fov"))
    pixel_aspect: float = field(default=1.0, metadata=rng(0.0, 100.0, lo_open=True, doc="v/u pixel size"))

    def __post_init__(self) -> None:
        self.validate("CameraModel")

    def validate(self, where: str = "CameraModel") -> None:
        """Reject sizes/angles that make the geometry meaningless (called by build_config too)."""
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= 20000:
                raise ConfigError(f"{where}: field '{name}' = {value!r} must be an integer in [1, 20000]")
        if not (isinstance(self.hfov_deg, (int, float)) and 0.0 < self.hfov_deg < 170.0):
            raise ConfigError(f"{where}: field 'hfov_deg' = {self.hfov_deg!r} must be in (0, 170) degrees")
        if not (isinstance(self.pixel_aspect, (int, float)) and 0.0 < self.pixel_aspect <= 100.0):
            raise ConfigError(f"{where}: field 'pixel_aspect' = {self.pixel_aspect!r} must be in (0, 100]")

    # ------------------------------------------------------------------ geometry
    @property
    def center_px(self) -> tuple[float, float]:
        """The image centre (u, v) in pixel-centre coordinates: the point straight below the camera."""
        return (self.width_px - 1) / 2.0, (self.height_px - 1) / 2.0

    def gsd_m(self, altitude_m: ArrayLike) -> ArrayLike:
        """Ground size of one pixel along ``u`` (metres); along ``v`` it is ``pixel_aspect`` times this."""
        if isinstance(altitude_m, (float, int)) and not isinstance(altitude_m, bool) and \
                math.isfinite(altitude_m) and altitude_m > 0.0:   # a plain number: the same float64 arithmetic
            return 2.0 * float(altitude_m) * math.tan(math.radians(self.hfov_deg) / 2.0) / self.width_px
        alt = _positive_altitude(altitude_m)
        gsd = 2.0 * alt * math.tan(math.radians(self.hfov_deg) / 2.0) / self.width_px
        return float(gsd) if np.ndim(gsd) == 0 else gsd

    def footprint_m(self, altitude_m: ArrayLike) -> tuple[ArrayLike, ArrayLike]:
        """Ground footprint (across-track width, along-track length) in metres."""
        gsd = self.gsd_m(altitude_m)
        return gsd * self.width_px, gsd * self.pixel_aspect * self.height_px

    def resized(self, width_px: int, height_px: int) -> CameraModel:
        """The model of this camera's image resized to ``width_px x height_px``: same footprint."""
        aspect = self.pixel_aspect * (self.height_px / height_px) * (width_px / self.width_px)
        return replace(self, width_px=int(width_px), height_px=int(height_px), pixel_aspect=aspect)

    def camera_to_world(self, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
                        altitude_m: ArrayLike) -> np.ndarray:
        """Affine (..., 2, 3): camera pixel (u, v) -> world metres (x east, y north)."""
        x, y, yaw = (np.asarray(a, dtype=np.float64) for a in (x_m, y_m, yaw_rad))
        alt = np.asarray(altitude_m, dtype=np.float64)
        shape = np.broadcast_shapes(x.shape, y.shape, yaw.shape, alt.shape)
        if not x.shape == y.shape == yaw.shape == shape:
            x, y, yaw = np.broadcast_arrays(x, y, yaw, alt)[:3]
        # a scalar altitude stays a scalar: the same float products as broadcast, without the (N,) copies
        gu = self.gsd_m(altitude_m if isinstance(altitude_m, (float, int)) else alt)
        gv = gu * self.pixel_aspect
        c, s = np.cos(yaw), np.sin(yaw)
        cu, cv = self.center_px
        # right of the vehicle = (sin, -cos), forward = (cos, sin); v grows backwards.
        a = np.empty(shape + (2, 3))
        a[..., 0, 0] = gu * s
        a[..., 0, 1] = -gv * c
        a[..., 1, 0] = -gu * c
        a[..., 1, 1] = -gv * s
        a[..., 0, 2] = x - a[..., 0, 0] * cu - a[..., 0, 1] * cv
        a[..., 1, 2] = y - a[..., 1, 0] * cu - a[..., 1, 1] * cv
        return a

    def footprint_corners_m(self, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
                            altitude_m: ArrayLike) -> np.ndarray:
        """World coordinates (..., 4, 2) of the outer image corners: top-left, top-right, bottom-right,
        bottom-left (top = ahead of the vehicle)."""
        a = self.camera_to_world(x_m, y_m, yaw_rad, altitude_m)
        return apply_affine(a, self.corners_px())

    def corners_px(self) -> np.ndarray:
        """The outer corners (4, 2) of the image in pixel-centre coordinates."""
        w, h = self.width_px - 0.5, self.height_px - 0.5
        return np.array([[-0.5, -0.5], [w, -0.5], [w, h], [-0.5, h]])

    def scale_rotation(self, orthomap: MapGrid, yaw_rad: ArrayLike,
                       altitude_m: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """The ``s`` and ``R(psi)`` of eq. (3): camera pixel offsets -> map pixel offsets.

        ``s`` (..., 2, 2) is the diagonal scale ``diag(gsd / map_gsd_x, gsd / map_gsd_y)`` (a scalar times the
        identity for square pixels) and ``R`` (..., 2, 2) the rotation by the compass heading ``pi/2 - yaw``
        (map rows grow south, camera rows grow towards the tail). ``s @ R @ diag(1, pixel_aspect)`` is the
        linear part of ``camera_to_map``.
        """
        yaw, alt = np.broadcast_arrays(np.asarray(yaw_rad, np.float64), np.asarray(altitude_m, np.float64))
        gu = np.asarray(self.gsd_m(alt), dtype=np.float64)
        s = np.zeros(yaw.shape + (2, 2))
        s[..., 0, 0] = gu / orthomap.gsd_x_m
        s[..., 1, 1] = gu / orthomap.gsd_y_m
        c, sn = np.cos(yaw), np.sin(yaw)
        r = np.empty(yaw.shape + (2, 2))
        r[..., 0, 0] = sn
        r[..., 0, 1] = -c
        r[..., 1, 0] = c
        r[..., 1, 1] = sn
        return s, r

    def camera_to_map(self, orthomap: MapGrid, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
                      altitude_m: ArrayLike) -> np.ndarray:
        """Affine (..., 2, 3): camera pixel (u, v) -> map pixel (u, v); eq. (3) ``s R(psi) x + T``."""
        a = self.camera_to_world(x_m, y_m, yaw_rad, altitude_m)
        # world_to_map_affine(orthomap) @ a, written out: that affine is diagonal, so each row of ``a`` is
        # scaled and its translation shifted (the same floats as the 3x3 product, whose other terms are exact
        # zeros; tests/sensors/test_camera.py checks it bit for bit), without N tiny matrix products
        w = world_to_map_affine(orthomap)
        a[..., 0, :] *= w[0, 0]
        a[..., 0, 2] += w[0, 2]
        a[..., 1, :] *= w[1, 1]
        a[..., 1, 2] += w[1, 2]
        return a

    def map_to_camera(self, orthomap: MapGrid, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
                      altitude_m: ArrayLike) -> np.ndarray:
        """Affine (..., 2, 3): map pixel -> camera pixel, the inverse of ``camera_to_map``."""
        return invert_affine(self.camera_to_map(orthomap, x_m, y_m, yaw_rad, altitude_m))

    def project_pixels(self, orthomap: MapGrid, uv: np.ndarray, x_m: ArrayLike, y_m: ArrayLike,
                       yaw_rad: ArrayLike, altitude_m: ArrayLike) -> np.ndarray:
        """Map pixels (N, K, 2) of the camera pixels ``uv`` (K, 2) for N poses (scalars broadcast to N=1)."""
        uv = np.asarray(uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise ValueError(f"project_pixels: uv must have shape (K, 2), got {uv.shape}")
        a = self.camera_to_map(orthomap, x_m, y_m, yaw_rad, altitude_m).reshape(-1, 2, 3)
        return apply_affine(a, uv)

    def affine_terms(self, orthomap: MapGrid, altitude_m: float) -> tuple[float, ...]:
        """The scalars of ``camera_to_map`` at one altitude, as ``pose_affine`` takes them: the pixel's ground size
        along u and v, the image centre (u, v), and the world -> map affine's x scale, x offset, y scale and y
        offset (float64)."""
        gu = self.gsd_m(float(altitude_m))
        (wx, _, ox), (_, wy, oy) = world_to_map_affine(orthomap).tolist()
        return (gu, gu * self.pixel_aspect, *(float(c) for c in self.center_px), wx, ox, wy, oy)

    def project_pose(self, orthomap: MapGrid, pose: Pose, terms: tuple[float, ...] | None = None) -> np.ndarray:
        """``camera_to_map`` (2, 3) for a single ``Pose``, in scalar float64 arithmetic (``pose_affine``: the same
        floats; tests/sensors/test_render_geometry.py checks them bit for bit) without a dozen numpy calls on 0-d arrays
        (the renderer calls it every frame). ``terms``: ``affine_terms`` at the pose's altitude if the caller keeps
        them (the renderer does, per altitude)."""
        x, y, yaw, alt = (float(v) for v in pose)
        terms = self.affine_terms(orthomap, alt) if terms is None else terms
        a = pose_affine(terms, x, y, float(np.cos(yaw)), float(np.sin(yaw)))
        return np.array(a).reshape(2, 3)


def pose_affine(terms: tuple[float, ...], x: float, y: float, c: float, s: float) -> tuple[float, ...]:
    """``CameraModel.camera_to_map`` of one pose (x, y, its yaw's cos ``c`` and sin ``s``, NumPy's) as six float64
    (a00, a01, a02, a10, a11, a12), from ``CameraModel.affine_terms``: the same operations in the same order as the
    vectorized form (``camera_to_world``'s rows, then each row scaled and its translation shifted), so the same
    floats. Plain arithmetic on purpose: the MCL pair kernel compiles this same function (numba fuses no
    multiply-add), so the renderer and the particles share one formula."""
    gu, gv, cu, cv, wx, ox, wy, oy = terms[0], terms[1], terms[2], terms[3], terms[4], terms[5], terms[6], terms[7]
    # right of the vehicle = (sin, -cos), forward = (cos, sin); v grows backwards (as camera_to_world)
    a00, a01 = gu * s, -gv * c
    a10, a11 = -gu * c, -gv * s
    a02 = x - a00 * cu - a01 * cv
    a12 = y - a10 * cu - a11 * cv
    return a00 * wx, a01 * wx, a02 * wx + ox, a10 * wy, a11 * wy, a12 * wy + oy


# ---------------------------------------------------------------------- affine helpers
def world_to_map_affine(orthomap: MapGrid) -> np.ndarray:
    """Affine (2, 3): world metres -> map pixel (u, v), ``u = x/gsd_x - 0.5``, ``v = H - 0.5 - y/gsd_y``."""
    return np.array([[1.0 / orthomap.gsd_x_m, 0.0, -0.5],
                     [0.0, -1.0 / orthomap.gsd_y_m, orthomap.height_px - 0.5]])


def apply_affine(a: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply affines (..., 2, 3) to points (K, 2): returns (..., K, 2).

    One matrix product (..., 2, 3) x (3, K); the result is a transposed view of the (..., 2, K) product (so
    ``out[..., 0]`` and ``out[..., 1]`` are cheap contiguous rows): BLAS does the work, not einsum's loops.
    """
    a = np.asarray(a, dtype=np.float64)
    pts = np.asarray(pts, dtype=np.float64)
    hom = np.vstack([pts.T, np.ones(pts.shape[0])])                     # (3, K)
    prod = (a.reshape(-1, 3) @ hom).reshape(a.shape[:-2] + (2, pts.shape[0]))
    return np.swapaxes(prod, -1, -2)


def invert_affine(a: np.ndarray) -> np.ndarray:
    """Inverse of affines (..., 2, 3) (closed form, vectorized)."""
    a = np.asarray(a, dtype=np.float64)
    lin = a[..., :2]
    det = lin[..., 0, 0] * lin[..., 1, 1] - lin[..., 0, 1] * lin[..., 1, 0]
    inv = np.empty_like(a)
    inv[..., 0, 0] = lin[..., 1, 1] / det
    inv[..., 0, 1] = -lin[..., 0, 1] / det
    inv[..., 1, 0] = -lin[..., 1, 0] / det
    inv[..., 1, 1] = lin[..., 0, 0] / det
    inv[..., :, 2] = -np.einsum("...ij,...j->...i", inv[..., :2], a[..., 2])
    return inv


def _positive_altitude(altitude_m: ArrayLike) -> np.ndarray | float:
    alt = np.asarray(altitude_m, dtype=np.float64)
    if not np.all(np.isfinite(alt)) or np.any(alt <= 0.0):
        bad = alt[~(np.isfinite(alt) & (alt > 0))].ravel()[:3]
        raise ConfigError(f"camera: altitude_m must be finite and > 0 m above ground, got {bad.tolist()}")
    return alt


# ---------------------------------------------------------------------- camera errors (scenario sections)
@dataclass(frozen=True)
class GimbalConfig:
    """The [gimbal] section: the stabilized camera's attitude errors. All zero by default (a perfect gimbal).

    Roll and pitch errors (each) follow a first-order Gauss-Markov process, stationary with standard deviation
    ``roll_pitch_std_deg`` and correlation time ``correlation_time_s`` (0: independent per frame); the frame is
    rendered tilted by them (``sensors.perspective.tilt_homography``), the vehicle does not know them. The
    reported heading carries a per-episode offset drawn from ``N(0, heading_bias_std_deg^2)`` (compass
    calibration, camera mount yaw) on top of the per-frame noise of ``odometry.heading_std_rad``.
    """

    roll_pitch_std_deg: float = field(default=0.0, metadata=rng(0.0, 10.0, doc="roll/pitch error std (each)"))
    correlation_time_s: float = field(default=1.0, metadata=rng(0.0, 3600.0,
                                                                 doc="Gauss-Markov time constant (0: white)"))
    heading_bias_std_deg: float = field(default=0.0, metadata=rng(0.0, 45.0, doc="per-episode heading offset std"))

    def draw_attitude(self, rng: np.random.Generator, n: int, dt_s: float) -> np.ndarray:
        """(n, 2) roll and pitch errors (rad) at ``n`` frames ``dt_s`` apart; nothing drawn when off."""
        sigma = math.radians(self.roll_pitch_std_deg)
        if sigma == 0.0:
            return np.zeros((n, 2))
        return gauss_markov(rng, n, sigma, dt_s, self.correlation_time_s, size=(2,))

    def draw_heading_bias(self, rng: np.random.Generator) -> float:
        """The episode's heading offset (rad); 0 without a draw when off."""
        return float(rng.normal(0.0, math.radians(self.heading_bias_std_deg))) if self.heading_bias_std_deg else 0.0


def gauss_markov(rng: np.random.Generator, n: int, sigma: float, dt_s: float, tau_s: float,
                 size: tuple[int, ...] = ()) -> np.ndarray:
    """``n`` steps (n, *size) of a stationary first-order Gauss-Markov process: ``x_0 ~ N(0, sigma^2)``,
    ``x_{k+1} = phi x_k + sqrt(1 - phi^2) sigma w_k`` with ``phi = exp(-dt / tau)`` (``tau = 0``: white)."""
    phi = math.exp(-dt_s / tau_s) if tau_s > 0.0 else 0.0
    w = rng.standard_normal((n, *size)) * sigma
    out = np.empty_like(w)
    out[0] = w[0]
    q = math.sqrt(1.0 - phi * phi)
    for k in range(1, n):
        out[k] = phi * out[k - 1] + q * w[k]
    return out


@dataclass(frozen=True)
class HazeConfig:
    """The [haze] section: aerial perspective between the ground and the camera. Off by default.

    A fraction ``1 - exp(-extinction_per_km * altitude_km)`` of every pixel is replaced by the airlight colour
    (Koschmieder's law over the nadir path, so haze grows with altitude): lower contrast, a bluish veil.
    """

    extinction_per_km: float = field(default=0.0, metadata=rng(0.0, 50.0, doc="0 disables haze"))
    airlight_rgb: tuple[float, float, float] = field(default=(200.0, 208.0, 222.0),
                                                     metadata=rng(0.0, 255.0, doc="veil colour, 8-bit"))

    def validate(self, where: str) -> None:
        if len(self.airlight_rgb) != 3:
            raise ConfigError(f"{where}: field 'airlight_rgb' must have three values (R, G, B) in [0, 255]")

    def transmission(self, altitude_m: float) -> float:
        return math.exp(-self.extinction_per_km * altitude_m / 1000.0)


@dataclass(frozen=True)
class ExposureConfig:
    """The [exposure] section: auto-exposure. Off by default (``strength = 0``: a fixed exposure).

    The camera meters the frame's mean luma (after haze) and sets the gain ``(target_luma / mean) ** strength``
    within ``gain_range``; the gain follows that setpoint with time constant ``time_constant_s`` (0: at once),
    so dark scenes (shadowed streets, water) come out brighter and bright ones darker, with a lag.
    """

    strength: float = field(default=0.0, metadata=rng(0.0, 1.0, doc="0 = fixed exposure, 1 = full correction"))
    target_luma: float = field(default=118.0, metadata=rng(1.0, 254.0, doc="mean luma the camera aims at"))
    time_constant_s: float = field(default=0.5, metadata=rng(0.0, 600.0, doc="lag of the gain"))
    gain_range: tuple[float, float] = field(default=(0.25, 4.0), metadata=rng(0.01, 100.0))

    def validate(self, where: str) -> None:
        if len(self.gain_range) != 2 or self.gain_range[0] > self.gain_range[1]:
            raise ConfigError(f"{where}: field 'gain_range' = {self.gain_range!r} must be (lo, hi) with lo <= hi")


_LUMA = np.array([0.2126, 0.7152, 0.0722])   # Rec. 709


class SceneExposure:
    """Haze and auto-exposure of one episode's frames: ``__call__(image, altitude_m)`` is one per-channel LUT.

    Stateful (the exposure gain's lag): ``reset()`` at each episode. Deterministic (no random draws).
    """

    def __init__(self, haze: HazeConfig, exposure: ExposureConfig, dt_s: float) -> None:
        self.haze, self.exposure = haze, exposure
        tau = exposure.time_constant_s
        self._alpha = 1.0 - math.exp(-dt_s / tau) if tau > 0.0 else 1.0
        self.gain: float | None = None

    @property
    def active(self) -> bool:
        return self.haze.extinction_per_km > 0.0 or self.exposure.strength > 0.0

    def reset(self) -> None:
        self.gain = None

    def __call__(self, image: np.ndarray, altitude_m: float) -> np.ndarray:
        import cv2

        t = self.haze.transmission(altitude_m)
        air = np.asarray(self.haze.airlight_rgb, dtype=np.float64)
        gain = 1.0
        ex = self.exposure
        if ex.strength > 0.0:
            mean = t * portable.matmul(_LUMA, cv2.mean(image)[:3]) + (1.0 - t) * portable.matmul(_LUMA, air)
            want = (ex.target_luma / max(mean, 1.0)) ** ex.strength
            want = min(max(want, ex.gain_range[0]), ex.gain_range[1])
            self.gain = want if self.gain is None else self.gain + self._alpha * (want - self.gain)
            gain = self.gain
        if t == 1.0 and gain == 1.0:
            return image
        x = np.arange(256, dtype=np.float64)[:, None]
        lut = np.clip(np.rint(gain * (t * x + (1.0 - t) * air[None, :])), 0, 255).astype(np.uint8)
        return cv2.LUT(image, lut.reshape(1, 256, 3))
