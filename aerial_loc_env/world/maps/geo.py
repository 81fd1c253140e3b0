"""WGS84 geodesy and georeferences: map pixel (u, v) <-> WGS84 latitude/longitude, vectorized.

Pixels follow the project convention: ``(u, v)`` = (column, row), continuous, pixel centres at integers.

* ``LocalTangentGeoref``: synthetic maps. The map is the tangent plane (East-North) of the WGS84 ellipsoid at
  a configurable origin; ground points are projected orthographically along the local vertical, which is exact
  both ways (ECEF geometry, no series) and makes plane distances equal ground distances to ~1e-8 relative over
  a few km.
* ``AffineGeoref``: an affine pixel -> projected-CRS transform plus a CRS. EPSG:3395 (ellipsoidal World
  Mercator), EPSG:3857 (Web Mercator), EPSG:4326 (lat/lon degrees) and the UTM zones (EPSG:326xx / 327xx,
  Krueger series) are implemented here; any other EPSG code goes through pyproj (optional extra ``geo``).
  ``WorldMercatorGeoref`` / ``WebMercatorGeoref`` are AffineGeorefs with the CRS fixed.

Every georeference serializes with ``to_dict()`` and comes back with ``georeference_from_dict``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from aerial_loc_env import portable
from aerial_loc_env.errors import MapError, require_extra

# --- WGS84 ----------

WGS84_A_M: float = 6378137.0                      # semi-major axis
WGS84_F: float = 1.0 / 298.257223563               # flattening
WGS84_B_M: float = WGS84_A_M * (1.0 - WGS84_F)     # semi-minor axis
WGS84_E2: float = WGS84_F * (2.0 - WGS84_F)        # first eccentricity squared
WGS84_E: float = math.sqrt(WGS84_E2)


def radii_of_curvature_m(lat_deg) -> tuple[np.ndarray, np.ndarray]:
    """Meridional (M, north-south) and prime-vertical (N, east-west) radii of curvature at ``lat_deg``."""
    s2 = np.sin(np.radians(np.asarray(lat_deg, dtype=np.float64))) ** 2
    w = np.sqrt(1.0 - WGS84_E2 * s2)
    return WGS84_A_M * (1.0 - WGS84_E2) / w**3, WGS84_A_M / w


def geodetic_to_ecef(lat_deg, lon_deg, h_m=0.0) -> np.ndarray:
    """WGS84 geodetic -> ECEF metres, shape (..., 3)."""
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    _, n = radii_of_curvature_m(np.degrees(lat))
    h = np.asarray(h_m, dtype=np.float64)
    xyz = ((n + h) * np.cos(lat) * np.cos(lon), (n + h) * np.cos(lat) * np.sin(lon),
           (n * (1.0 - WGS84_E2) + h) * np.sin(lat))
    return np.stack(np.broadcast_arrays(*xyz), axis=-1)


def mercator_scale_factor(lat_deg) -> np.ndarray:
    """Point scale k of the ellipsoidal (conformal) Mercator: projected metres = k x ground metres.

    k = sqrt(1 - e^2 sin^2 phi) / cos phi; on the sphere this is the familiar 1 / cos(lat).
    """
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    return np.sqrt(1.0 - WGS84_E2 * np.sin(lat) ** 2) / np.cos(lat)


def _arrays(a, b) -> tuple[np.ndarray, np.ndarray]:
    a, b = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    return a, b


def _check_lat(lat: np.ndarray, what: str) -> None:
    if np.any(np.abs(lat) >= 90.0):
        raise MapError(f"{what}: latitude must be in (-90, 90) degrees, got max |lat| {np.max(np.abs(lat))}")


# --- projections (CRS) ----------

def _deg_lon(lon: float) -> str:
    return f"{abs(lon):g} deg {'W' if lon < 0 else 'E'}"


def _deg_lat(lat: float) -> str:
    return f"{abs(lat):g} deg {'S' if lat < 0 else 'N'}"


@dataclass(frozen=True)
class AreaOfUse:
    """Where a CRS is meant to be used: a lat/lon box in degrees (``west > east`` crosses the antimeridian)."""

    west: float
    south: float
    east: float
    north: float
    name: str = ""

    def distance_deg(self, lat_deg: float, lon_deg: float) -> float:
        """How many degrees (of latitude or longitude, the larger) the point lies outside the box; 0 inside."""
        width = (self.east - self.west) % 360.0 or (360.0 if self.east != self.west else 0.0)
        rel = (lon_deg - self.west) % 360.0
        off_lon = 0.0 if rel <= width else min(rel - width, 360.0 - rel)
        off_lat = max(0.0, self.south - lat_deg, lat_deg - self.north)
        return max(off_lon, off_lat)

    def describe(self) -> str:
        box = f"{_deg_lon(self.west)} to {_deg_lon(self.east)}, {_deg_lat(self.south)} to {_deg_lat(self.north)}"
        return f"{self.name} ({box})" if self.name and box not in self.name else (self.name or box)


#: a regional CRS, for ``regional_crs_covering``: an area of use at most this many degrees on each side
REGIONAL_CRS_MAX_DEG = 20.0


def regional_crs_covering(lat_deg: float, lon_deg: float) -> list[str] | None:
    """The projected CRSs of the EPSG/ESRI database (pyproj) whose area of use, at most ``REGIONAL_CRS_MAX_DEG``
    on a side, contains the point: national and regional grids exist wherever land (or coastal water) is mapped,
    so none at all means open ocean. None when pyproj is not installed (the check cannot be made)."""
    try:
        from pyproj.aoi import AreaOfInterest
        from pyproj.database import query_crs_info
        from pyproj.enums import PJType
    except ImportError:   # pragma: no cover - depends on the environment
        return None
    found = query_crs_info(pj_types=PJType.PROJECTED_CRS, contains=False,
                           area_of_interest=AreaOfInterest(lon_deg, lat_deg, lon_deg, lat_deg))
    out = []
    for info in found:
        a = info.area_of_use
        if a is None:
            continue
        if (a.east - a.west) % 360.0 <= REGIONAL_CRS_MAX_DEG and a.north - a.south <= REGIONAL_CRS_MAX_DEG:
            out.append(f"{info.auth_name}:{info.code} {info.name}")
    return out


class Projection(ABC):
    """A projected (or geographic) CRS: lat/lon degrees <-> CRS coordinates (x east-ish, y north-ish)."""

    crs: str
    unit: str = "metre"      # the unit of the CRS coordinates (of a world file's pixel size)

    @abstractmethod
    def forward(self, lat_deg: np.ndarray, lon_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    @abstractmethod
    def inverse(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def ground_scale(self, lat_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Ground metres per CRS unit along x and y at ``lat_deg``, or None where no closed form is given."""
        return None

    def area_of_use(self) -> AreaOfUse | None:
        """Where the CRS is meant to be used (EPSG's area of use), or None when unknown."""
        return None


class WorldMercatorProjection(Projection):
    """EPSG:3395, Mercator on the WGS84 ellipsoid (conformal); the inverse iterates to machine precision."""

    crs = "EPSG:3395"

    def area_of_use(self) -> AreaOfUse:
        return AreaOfUse(-180.0, -80.0, 180.0, 84.0, "the world between 80 deg S and 84 deg N")

    def forward(self, lat_deg, lon_deg):
        lat_deg, lon_deg = _arrays(lat_deg, lon_deg)
        _check_lat(lat_deg, self.crs)
        phi = np.radians(lat_deg)
        es = WGS84_E * np.sin(phi)
        # y = a * (atanh(sin phi) - e atanh(e sin phi)): the isometric latitude, stable near the equator.
        y = WGS84_A_M * (portable.arctanh(np.sin(phi)) - WGS84_E * portable.arctanh(es))
        return WGS84_A_M * np.radians(lon_deg), y

    def inverse(self, x, y):
        x, y = _arrays(x, y)
        t = portable.exp(-y / WGS84_A_M)
        phi = np.pi / 2 - 2 * portable.arctan(t)
        for _ in range(30):
            es = WGS84_E * np.sin(phi)
            new = np.pi / 2 - 2 * portable.arctan(t * portable.power((1 - es) / (1 + es), WGS84_E / 2))
            done = np.max(np.abs(new - phi), initial=0.0) < 1e-15
            phi = new
            if done:
                break
        return np.degrees(phi), np.degrees(x / WGS84_A_M)

    def ground_scale(self, lat_deg):
        s = 1.0 / mercator_scale_factor(lat_deg)
        return s, s


class WebMercatorProjection(Projection):
    """EPSG:3857: spherical Mercator formulas applied to WGS84 lat/lon (not conformal on the ellipsoid)."""

    crs = "EPSG:3857"

    def area_of_use(self) -> AreaOfUse:
        return AreaOfUse(-180.0, -85.06, 180.0, 85.06, "the world between 85.06 deg S and 85.06 deg N")

    def forward(self, lat_deg, lon_deg):
        lat_deg, lon_deg = _arrays(lat_deg, lon_deg)
        _check_lat(lat_deg, self.crs)
        return WGS84_A_M * np.radians(lon_deg), WGS84_A_M * portable.arctanh(np.sin(np.radians(lat_deg)))

    def inverse(self, x, y):
        x, y = _arrays(x, y)
        return np.degrees(portable.arctan(portable.sinh(y / WGS84_A_M))), np.degrees(x / WGS84_A_M)

    def ground_scale(self, lat_deg):
        # dx = a dlon and dy = a dlat / cos(lat), while the ellipsoid has dE = N cos(lat) dlon, dN = M dlat.
        m, n = radii_of_curvature_m(lat_deg)
        c = np.cos(np.radians(np.asarray(lat_deg, dtype=np.float64)))
        return n * c / WGS84_A_M, m * c / WGS84_A_M


class GeographicProjection(Projection):
    """EPSG:4326 with x = longitude, y = latitude in degrees (the axis order of GeoTIFFs and world files)."""

    unit = "degree"

    crs = "EPSG:4326"

    def area_of_use(self) -> AreaOfUse:
        return AreaOfUse(-180.0, -90.0, 180.0, 90.0, "the world")

    def forward(self, lat_deg, lon_deg):
        lat_deg, lon_deg = _arrays(lat_deg, lon_deg)
        return lon_deg.copy(), lat_deg.copy()

    def inverse(self, x, y):
        x, y = _arrays(x, y)
        return y.copy(), x.copy()

    def ground_scale(self, lat_deg):
        m, n = radii_of_curvature_m(lat_deg)
        c = np.cos(np.radians(np.asarray(lat_deg, dtype=np.float64)))
        return n * c * np.pi / 180.0, m * np.pi / 180.0


# Krueger's series for the transverse Mercator to fourth order in n (truncation ~1 um inside a UTM zone).
_N = WGS84_F / (2.0 - WGS84_F)
_TM_A = WGS84_A_M / (1.0 + _N) * (1.0 + _N**2 / 4.0 + _N**4 / 64.0)
_TM_ALPHA = (_N / 2 - 2 * _N**2 / 3 + 5 * _N**3 / 16 + 41 * _N**4 / 180,
             13 * _N**2 / 48 - 3 * _N**3 / 5 + 557 * _N**4 / 1440,
             61 * _N**3 / 240 - 103 * _N**4 / 140,
             49561 * _N**4 / 161280)
_TM_BETA = (_N / 2 - 2 * _N**2 / 3 + 37 * _N**3 / 96 - _N**4 / 360,
            _N**2 / 48 + _N**3 / 15 - 437 * _N**4 / 1440,
            17 * _N**3 / 480 - 37 * _N**4 / 840,
            4397 * _N**4 / 161280)


class UTMProjection(Projection):
    """UTM zone (EPSG:326zz north, 327zz south): transverse Mercator, k0 = 0.9996, Krueger series.

    The inverse latitude comes from the conformal latitude by Newton iteration (exact, no second series).
    """

    def __init__(self, zone: int, south: bool):
        if not 1 <= zone <= 60:
            raise MapError(f"UTM zone must be in [1, 60], got {zone}")
        self.zone, self.south = int(zone), bool(south)
        self.crs = f"EPSG:{(32700 if south else 32600) + self.zone}"
        self._lon0 = math.radians(-183.0 + 6.0 * self.zone)
        self._n0 = 10_000_000.0 if south else 0.0

    def area_of_use(self) -> AreaOfUse:
        """The zone's 6-degree longitude band; 0-84 deg N (north zones) or 80 deg S-0 (south zones)."""
        west = -180.0 + 6.0 * (self.zone - 1)
        south, north = (-80.0, 0.0) if self.south else (0.0, 84.0)
        return AreaOfUse(west, south, west + 6.0, north,
                         f"UTM zone {self.zone}{'S' if self.south else 'N'}: {_deg_lon(west)} to "
                         f"{_deg_lon(west + 6.0)}, {_deg_lat(south)} to {_deg_lat(north)}")

    def forward(self, lat_deg, lon_deg):
        lat_deg, lon_deg = _arrays(lat_deg, lon_deg)
        _check_lat(lat_deg, self.crs)
        phi, lam = np.radians(lat_deg), np.radians(lon_deg) - self._lon0
        lam = (lam + np.pi) % (2 * np.pi) - np.pi
        c = 2 * math.sqrt(_N) / (1 + _N)
        t = portable.sinh(portable.arctanh(np.sin(phi)) - c * portable.arctanh(c * np.sin(phi)))
        xi_p = portable.arctan2(t, np.cos(lam))
        eta_p = portable.arctanh(np.sin(lam) / np.sqrt(1 + t * t))
        xi, eta = xi_p.copy(), eta_p.copy()
        for j, a in enumerate(_TM_ALPHA, start=1):
            xi += a * np.sin(2 * j * xi_p) * portable.cosh(2 * j * eta_p)
            eta += a * np.cos(2 * j * xi_p) * portable.sinh(2 * j * eta_p)
        return 500_000.0 + 0.9996 * _TM_A * eta, self._n0 + 0.9996 * _TM_A * xi

    def inverse(self, x, y):
        x, y = _arrays(x, y)
        xi = (y - self._n0) / (0.9996 * _TM_A)
        eta = (x - 500_000.0) / (0.9996 * _TM_A)
        xi_p, eta_p = xi.copy(), eta.copy()
        for j, b in enumerate(_TM_BETA, start=1):
            xi_p -= b * np.sin(2 * j * xi) * portable.cosh(2 * j * eta)
            eta_p -= b * np.cos(2 * j * xi) * portable.sinh(2 * j * eta)
        tau_p = np.sin(xi_p) / np.sqrt(portable.sinh(eta_p) ** 2 + np.cos(xi_p) ** 2)   # tan(conformal latitude)
        lam = portable.arctan2(portable.sinh(eta_p), np.cos(xi_p))
        tau = tau_p.copy()
        for _ in range(10):   # Newton on tau = tan(phi) (Karney 2011, eqs. 19-21)
            sig = portable.sinh(WGS84_E * portable.arctanh(WGS84_E * tau / np.sqrt(1 + tau * tau)))
            f_tau = tau * np.sqrt(1 + sig * sig) - sig * np.sqrt(1 + tau * tau)
            d_tau = ((tau_p - f_tau) / np.sqrt(1 + f_tau * f_tau) * (1 + (1 - WGS84_E2) * tau * tau)
                     / ((1 - WGS84_E2) * np.sqrt(1 + tau * tau)))
            tau = tau + d_tau
            if np.max(np.abs(d_tau), initial=0.0) < 1e-15:
                break
        lon = np.degrees(lam + self._lon0)
        return np.degrees(portable.arctan(tau)), (lon + 180.0) % 360.0 - 180.0


class PyprojProjection(Projection):
    """Any CRS pyproj knows (optional extra ``geo``); x/y in the CRS's easting/northing order."""

    def __init__(self, crs: str):
        pyproj = require_extra("pyproj", "geo", f"the CRS {crs}")
        try:
            self._crs_obj = pyproj.CRS.from_user_input(crs)
        except pyproj.exceptions.CRSError as exc:
            raise MapError(f"unknown CRS {crs!r}: {exc}") from exc
        self.crs = crs
        axes = self._crs_obj.axis_info
        self.unit = axes[0].unit_name if axes else "unknown unit"
        self._fwd = pyproj.Transformer.from_crs("EPSG:4326", self._crs_obj, always_xy=True)
        self._inv = pyproj.Transformer.from_crs(self._crs_obj, "EPSG:4326", always_xy=True)

    def area_of_use(self) -> AreaOfUse | None:
        area = self._crs_obj.area_of_use
        if area is None:
            return None
        return AreaOfUse(float(area.west), float(area.south), float(area.east), float(area.north), str(area.name))

    def forward(self, lat_deg, lon_deg):
        lat_deg, lon_deg = _arrays(lat_deg, lon_deg)
        x, y = self._fwd.transform(lon_deg, lat_deg)
        return np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)

    def inverse(self, x, y):
        x, y = _arrays(x, y)
        lon, lat = self._inv.transform(x, y)
        return np.asarray(lat, dtype=np.float64), np.asarray(lon, dtype=np.float64)


def normalize_crs(crs: str | int) -> str:
    """'EPSG:3395', 'epsg:3395', 3395 -> 'EPSG:3395'; other strings (WKT, proj) are kept as given."""
    if isinstance(crs, (int, np.integer)) and not isinstance(crs, bool):
        return f"EPSG:{int(crs)}"
    if not isinstance(crs, str) or not crs.strip():
        raise MapError(f"crs must be an EPSG code like 'EPSG:3395' or an integer, got {crs!r}")
    s = crs.strip()
    if s.upper().startswith("EPSG:") and s[5:].strip().isdigit():
        return f"EPSG:{int(s[5:])}"
    return s


def projection_for(crs: str | int) -> Projection:
    """The Projection of a CRS: native for EPSG 3395/3857/4326/326xx/327xx, pyproj for anything else."""
    crs = normalize_crs(crs)
    code = int(crs[5:]) if crs.startswith("EPSG:") else None
    if code == 3395:
        return WorldMercatorProjection()
    if code == 3857:
        return WebMercatorProjection()
    if code == 4326:
        return GeographicProjection()
    if code is not None and (32601 <= code <= 32660 or 32701 <= code <= 32760):
        return UTMProjection(code % 100, south=code > 32700)
    return PyprojProjection(crs)


# --- georeferences ----------

_REGISTRY: dict[str, type[Georeference]] = {}


class Georeference(ABC):
    """Map pixel (u, v) <-> WGS84 lat/lon in degrees, vectorized (any broadcastable shapes)."""

    kind: ClassVar[str]

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "kind" in cls.__dict__:
            _REGISTRY[cls.kind] = cls

    @abstractmethod
    def pixel_to_latlon(self, u, v) -> tuple[np.ndarray, np.ndarray]: ...

    @abstractmethod
    def latlon_to_pixel(self, lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]: ...

    @abstractmethod
    def to_dict(self) -> dict: ...

    @abstractmethod
    def shifted(self, du_px: float, dv_px: float) -> Georeference:
        """The georeference of a crop whose pixel (0, 0) is this one's pixel (du_px, dv_px)."""

    def ground_gsd_m(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Ground metres per pixel along the columns (x) and rows (y) at pixel (u, v).

        Generic version: central differences of +-0.5 px through lat/lon, lengths on the ellipsoid with the
        local radii of curvature (relative error ~ (pixel / Earth radius)^2).
        """
        u, v = _arrays(u, v)
        out = []
        for du, dv in ((0.5, 0.0), (0.0, 0.5)):
            lat1, lon1 = self.pixel_to_latlon(u - du, v - dv)
            lat2, lon2 = self.pixel_to_latlon(u + du, v + dv)
            m, n = radii_of_curvature_m(0.5 * (lat1 + lat2))
            dn = m * np.radians(lat2 - lat1)
            dlon = (lon2 - lon1 + 180.0) % 360.0 - 180.0
            de = n * np.cos(np.radians(0.5 * (lat1 + lat2))) * np.radians(dlon)
            out.append(np.hypot(de, dn))
        return out[0], out[1]


def georeference_from_dict(d: dict) -> Georeference:
    """Inverse of ``Georeference.to_dict``."""
    if not isinstance(d, dict) or "type" not in d:
        raise MapError(f"georeference: expected a dict with a 'type' key, got {d!r}")
    cls = _REGISTRY.get(d["type"])
    if cls is None:
        raise MapError(f"georeference: unknown type {d['type']!r}; known: {', '.join(sorted(_REGISTRY))}")
    kwargs = {k: val for k, val in d.items() if k != "type"}
    try:
        return cls(**kwargs)
    except TypeError as exc:
        raise MapError(f"georeference of type {d['type']!r}: bad fields {sorted(kwargs)}: {exc}") from exc


@dataclass(frozen=True)
class LocalTangentGeoref(Georeference):
    """Synthetic map on the East-North tangent plane of WGS84 at (origin_lat_deg, origin_lon_deg).

    Pixel (origin_u_px, origin_v_px) is the origin; east = +u * gsd_x_m, north = -v * gsd_y_m. A ground point
    maps to the foot of its perpendicular on the plane (orthographic along the origin's vertical); the inverse
    intersects that vertical line with the ellipsoid, so both directions are exact.
    """

    kind: ClassVar[str] = "local_tangent"
    origin_lat_deg: float
    origin_lon_deg: float
    gsd_x_m: float
    gsd_y_m: float
    origin_u_px: float = 0.0
    origin_v_px: float = 0.0
    _frame: np.ndarray = field(init=False, repr=False, compare=False)   # rows: east, north, up (ECEF)
    _origin_ecef: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("origin_lat_deg", "origin_lon_deg", "gsd_x_m", "gsd_y_m", "origin_u_px", "origin_v_px"):
            val = getattr(self, name)
            if isinstance(val, bool) or not isinstance(val, (int, float, np.integer, np.floating)) \
                    or not math.isfinite(val):
                raise MapError(f"LocalTangentGeoref: '{name}' must be a finite number, got {val!r}")
            object.__setattr__(self, name, float(val))
        if not -89.0 <= self.origin_lat_deg <= 89.0:
            raise MapError(f"LocalTangentGeoref: origin_lat_deg must be in [-89, 89], "
                           f"got {self.origin_lat_deg}")
        if not -180.0 <= self.origin_lon_deg <= 180.0:
            raise MapError(f"LocalTangentGeoref: origin_lon_deg must be in [-180, 180], "
                           f"got {self.origin_lon_deg}")
        if self.gsd_x_m <= 0 or self.gsd_y_m <= 0:
            raise MapError(f"LocalTangentGeoref: gsd_x_m and gsd_y_m must be > 0, "
                           f"got {self.gsd_x_m}, {self.gsd_y_m}")
        p, l = math.radians(self.origin_lat_deg), math.radians(self.origin_lon_deg)
        frame = np.array([[-math.sin(l), math.cos(l), 0.0],
                          [-math.sin(p) * math.cos(l), -math.sin(p) * math.sin(l), math.cos(p)],
                          [math.cos(p) * math.cos(l), math.cos(p) * math.sin(l), math.sin(p)]])
        object.__setattr__(self, "_frame", frame)
        object.__setattr__(self, "_origin_ecef", geodetic_to_ecef(self.origin_lat_deg, self.origin_lon_deg))

    @classmethod
    def centered(cls, origin_lat_deg: float, origin_lon_deg: float, width_px: int, height_px: int,
                 gsd_x_m: float, gsd_y_m: float | None = None) -> LocalTangentGeoref:
        """Origin at the map centre (least distortion)."""
        return cls(origin_lat_deg, origin_lon_deg, gsd_x_m, gsd_x_m if gsd_y_m is None else gsd_y_m,
                   (width_px - 1) / 2.0, (height_px - 1) / 2.0)

    def pixel_to_en_m(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Pixel -> (east, north) metres on the tangent plane from the origin."""
        u, v = _arrays(u, v)
        return (u - self.origin_u_px) * self.gsd_x_m, (self.origin_v_px - v) * self.gsd_y_m

    def pixel_to_latlon(self, u, v):
        e, n = self.pixel_to_en_m(u, v)
        east, north, up = self._frame
        q = self._origin_ecef + e[..., None] * east + n[..., None] * north
        scale = np.array([WGS84_A_M, WGS84_A_M, WGS84_B_M])
        qs, ds = q / scale, up / scale
        a = portable.matmul(ds, ds)
        b = 2.0 * portable.matmul(qs.reshape(-1, 3), ds).reshape(qs.shape[:-1])
        c = np.einsum("...i,...i->...", qs, qs) - 1.0
        disc = b * b - 4.0 * a * c
        if np.any(disc < 0):
            raise MapError("LocalTangentGeoref: pixel too far from the origin (vertical misses the Earth)")
        t = -2.0 * c / (b + np.sqrt(disc))          # the root near 0, in a cancellation-free form
        p = q + t[..., None] * up
        lat = np.degrees(portable.arctan2(p[..., 2], (1.0 - WGS84_E2) * np.hypot(p[..., 0], p[..., 1])))
        lon = np.degrees(portable.arctan2(p[..., 1], p[..., 0]))
        return lat, lon

    def latlon_to_pixel(self, lat_deg, lon_deg):
        lat_deg, lon_deg = _arrays(lat_deg, lon_deg)
        _check_lat(lat_deg, "LocalTangentGeoref")
        d = geodetic_to_ecef(lat_deg, lon_deg) - self._origin_ecef
        en = portable.matmul(d.reshape(-1, 3), self._frame[:2].T)
        e, n = en[:, 0].reshape(d.shape[:-1]), en[:, 1].reshape(d.shape[:-1])
        return self.origin_u_px + e / self.gsd_x_m, self.origin_v_px - n / self.gsd_y_m

    def shifted(self, du_px: float, dv_px: float) -> LocalTangentGeoref:
        return LocalTangentGeoref(self.origin_lat_deg, self.origin_lon_deg, self.gsd_x_m, self.gsd_y_m,
                                  self.origin_u_px - du_px, self.origin_v_px - dv_px)

    def to_dict(self) -> dict:
        names = ("origin_lat_deg", "origin_lon_deg", "gsd_x_m", "gsd_y_m", "origin_u_px", "origin_v_px")
        return {"type": self.kind, **{k: getattr(self, k) for k in names}}


@dataclass(frozen=True)
class AffineGeoref(Georeference):
    """Affine pixel -> CRS transform: ``x = a u + b v + c``, ``y = d u + e v + f``, pixel centres at integers.

    This is the ESRI world-file convention (its six numbers in the order a, d, b, e, c, f). GDAL geotransforms
    refer to the outer corner instead: use ``from_gdal``.
    """

    kind: ClassVar[str] = "affine"
    pixel_to_crs: tuple[float, float, float, float, float, float]
    crs: str
    _proj: Projection = field(init=False, repr=False, compare=False)
    _inv: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        t = tuple(float(x) for x in np.asarray(self.pixel_to_crs, dtype=np.float64).ravel())
        if len(t) != 6 or not all(math.isfinite(x) for x in t):
            raise MapError(f"AffineGeoref: pixel_to_crs must be 6 finite numbers (a, b, c, d, e, f), got {t}")
        a, b, c, d, e, f = t
        det = a * e - b * d
        if det == 0.0:
            raise MapError(f"AffineGeoref: pixel_to_crs {t} is singular (zero pixel size?)")
        object.__setattr__(self, "pixel_to_crs", t)
        object.__setattr__(self, "crs", normalize_crs(self.crs))
        object.__setattr__(self, "_proj", projection_for(self.crs))
        inv = np.array([[e, -b], [-d, a]]) / det
        object.__setattr__(self, "_inv", np.column_stack([inv, -inv @ np.array([c, f])]))

    @classmethod
    def from_gdal(cls, geotransform, crs: str | int) -> AffineGeoref:
        """From a GDAL geotransform (c, a, b, f, d, e), which maps the outer corner (0, 0) of pixel (0, 0)."""
        c, a, b, f, d, e = (float(x) for x in geotransform)
        return cls((a, b, c + 0.5 * (a + b), d, e, f + 0.5 * (d + e)), crs)

    @classmethod
    def north_up(cls, crs: str | int, left: float, top: float, pixel_w: float,
                 pixel_h: float) -> AffineGeoref:
        """North-up grid: (left, top) is the outer top-left corner, pixels pixel_w x pixel_h CRS units."""
        return cls.from_gdal((left, pixel_w, 0.0, top, 0.0, -pixel_h), crs)

    @property
    def projection(self) -> Projection:
        return self._proj

    def pixel_to_xy(self, u, v) -> tuple[np.ndarray, np.ndarray]:
        """Pixel -> CRS coordinates."""
        u, v = _arrays(u, v)
        a, b, c, d, e, f = self.pixel_to_crs
        return a * u + b * v + c, d * u + e * v + f

    def xy_to_pixel(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        x, y = _arrays(x, y)
        m = self._inv
        return m[0, 0] * x + m[0, 1] * y + m[0, 2], m[1, 0] * x + m[1, 1] * y + m[1, 2]

    def pixel_to_latlon(self, u, v):
        return self._proj.inverse(*self.pixel_to_xy(u, v))

    def latlon_to_pixel(self, lat_deg, lon_deg):
        return self.xy_to_pixel(*self._proj.forward(lat_deg, lon_deg))

    def ground_gsd_m(self, u, v):
        """Ground metres per pixel; closed form (CRS point scale) for the natively supported CRSs."""
        u, v = _arrays(u, v)
        lat, _ = self.pixel_to_latlon(u, v)
        scale = self._proj.ground_scale(lat)
        if scale is None:
            return super().ground_gsd_m(u, v)
        sx, sy = scale
        a, b, _, d, e, _ = self.pixel_to_crs
        return np.hypot(a * sx, d * sy), np.hypot(b * sx, e * sy)

    def is_north_up(self, tol: float = 1e-9) -> bool:
        """True when columns run along +x and rows along -y of the CRS, with no rotation or shear."""
        a, b, _, d, e, _ = self.pixel_to_crs
        return a > 0 and e < 0 and abs(b) <= tol * abs(a) and abs(d) <= tol * abs(e)

    def shifted(self, du_px: float, dv_px: float) -> AffineGeoref:
        a, b, c, d, e, f = self.pixel_to_crs
        return type(self)((a, b, c + a * du_px + b * dv_px, d, e, f + d * du_px + e * dv_px), self.crs)

    def to_dict(self) -> dict:
        return {"type": self.kind, "pixel_to_crs": list(self.pixel_to_crs), "crs": self.crs}


@dataclass(frozen=True)
class _FixedCrsGeoref(AffineGeoref):
    """An AffineGeoref whose subclass fixes the CRS (the default of its ``crs`` field)."""

    def __post_init__(self) -> None:
        want = type(self).__dataclass_fields__["crs"].default
        if normalize_crs(self.crs) != want:
            raise MapError(f"{type(self).__name__}: crs must be {want}, got {self.crs!r}; use AffineGeoref")
        super().__post_init__()

    @classmethod
    def from_gdal(cls, geotransform, crs: str | int | None = None) -> AffineGeoref:
        return super().from_gdal(geotransform, cls.__dataclass_fields__["crs"].default if crs is None else crs)


@dataclass(frozen=True)
class WorldMercatorGeoref(_FixedCrsGeoref):
    """AffineGeoref in EPSG:3395 (the real GeoTIFF tiles)."""

    kind: ClassVar[str] = "world_mercator"
    crs: str = "EPSG:3395"


@dataclass(frozen=True)
class WebMercatorGeoref(_FixedCrsGeoref):
    """AffineGeoref in EPSG:3857 (web map tiles)."""

    kind: ClassVar[str] = "web_mercator"
    crs: str = "EPSG:3857"


def georef_for_crs(pixel_to_crs, crs: str | int) -> AffineGeoref:
    """The most specific AffineGeoref class for ``crs`` (World/Web Mercator or generic)."""
    crs = normalize_crs(crs)
    cls = {"EPSG:3395": WorldMercatorGeoref, "EPSG:3857": WebMercatorGeoref}.get(crs, AffineGeoref)
    return cls(tuple(pixel_to_crs), crs)


# --- east-north offsets between nearby points ----------

def east_north_m(origin_lat_deg, origin_lon_deg, lat_deg, lon_deg) -> tuple[np.ndarray, np.ndarray]:
    """East and north metres of (lat, lon) on the WGS84 tangent plane at the origin, vectorized (origins too).

    The plane of ``LocalTangentGeoref``: the point's ECEF offset from the origin projected on the origin's east
    and north axes, exact (no series), so plane metres are ground metres to ~1e-8 relative over a few km.
    """
    lat0, lon0 = _arrays(origin_lat_deg, origin_lon_deg)
    _check_lat(lat0, "east_north_m origin")
    _check_lat(np.asarray(lat_deg, dtype=np.float64), "east_north_m")
    d = geodetic_to_ecef(lat_deg, lon_deg) - geodetic_to_ecef(lat0, lon0)
    p, lam = np.radians(lat0), np.radians(lon0)
    horizontal = np.cos(lam) * d[..., 0] + np.sin(lam) * d[..., 1]      # along the meridian plane's outward axis
    return np.cos(lam) * d[..., 1] - np.sin(lam) * d[..., 0], np.cos(p) * d[..., 2] - np.sin(p) * horizontal


def offset_latlon(lat_deg: float, lon_deg: float, east_m, north_m) -> tuple[np.ndarray, np.ndarray]:
    """The ground point ``east_m`` east and ``north_m`` north of (lat, lon) on its tangent plane: the inverse of
    ``east_north_m`` (``LocalTangentGeoref``'s, exact both ways); vectorized over the offsets."""
    plane = LocalTangentGeoref(float(lat_deg), float(lon_deg), 1.0, 1.0)
    east_m, north_m = _arrays(east_m, north_m)
    return plane.pixel_to_latlon(east_m, -north_m)


def distance_m(lat1_deg, lon1_deg, lat2_deg, lon2_deg) -> np.ndarray:
    """Horizontal ground distance between two points a few km apart at most, metres, vectorized: the length of
    the second's offset on the first's tangent plane (``east_north_m``; equal to the geodesic to ~1e-7 at 5 km)."""
    east, north = east_north_m(lat1_deg, lon1_deg, lat2_deg, lon2_deg)
    return np.hypot(east, north)
