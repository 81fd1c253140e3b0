"""Shared test fixtures: the repository root and the real imagery beside the project (../shared/data)."""

from __future__ import annotations

import io
import math
import socket
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from shared_helpers import REAL_TILES, REPO_ROOT, SHARED_DATA

_REALTIME_DIRS = ("sitl", "mavlink")   # real UDP links and SITL processes timed by the wall clock


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark the tests of ``tests/sitl`` and ``tests/mavlink`` ``realtime``: they measure message rates and update
    gaps on real sockets, which a machine busy with other test workers stretches (``make test`` runs them on their
    own after the rest)."""
    tests_dir = Path(__file__).resolve().parent
    for item in items:
        rel = Path(str(item.path)).resolve().relative_to(tests_dir)
        if rel.parts and rel.parts[0] in _REALTIME_DIRS:
            item.add_marker(pytest.mark.realtime)


@pytest.fixture()
def cache_homes(tmp_path, monkeypatch) -> tuple[Path, Path]:
    """XDG_CACHE_HOME and the system's temporary folder, both inside the test's folder: (cache, tmp)."""
    cache, tmp = tmp_path / "cache", tmp_path / "tmp"
    tmp.mkdir()
    monkeypatch.setenv("XDG_CACHE_HOME", str(cache))
    monkeypatch.setattr(tempfile, "tempdir", str(tmp))
    return cache, tmp


@pytest.fixture(scope="session")
def avx2_numba_cache(tmp_path_factory) -> Path:
    """One numba cache for the tests' processes that compile as an AVX2 machine (``sysinfo.avx2_env``): the
    kernels they share are compiled once per test worker, not once per test."""
    return tmp_path_factory.mktemp("numba-avx2")


@pytest.fixture(scope="session")
def repo_root() -> Path:
    """The project root (holds pyproject.toml, envs/, agents/)."""
    return REPO_ROOT


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data with the real GeoTIFF tiles; skips where that folder (or a tile) is absent."""
    missing = [t for t in REAL_TILES if not (SHARED_DATA / t).is_file()]
    if missing:
        pytest.skip(f"real imagery not available: {SHARED_DATA} lacks {', '.join(missing)} "
                    "(the tiles live beside the project, never in it)")
    return SHARED_DATA


@pytest.fixture(scope="module")
def manila(shared_data: Path):
    """The Manila tile of ../shared/data, loaded once per test module."""
    from aerial_loc_env.world.maps.io import load_orthomap

    return load_orthomap(shared_data / "manila_pasig_river.tif")


def vincenty_m(lat1, lon1, lat2, lon2) -> float:
    """Vincenty's inverse formula on WGS84 (independent of the library; iterates to 1e-13 rad)."""
    a, f = 6378137.0, 1 / 298.257223563
    b = a * (1 - f)
    L = math.radians(lon2 - lon1)
    U1, U2 = math.atan((1 - f) * math.tan(math.radians(lat1))), math.atan((1 - f) * math.tan(math.radians(lat2)))
    sinU1, cosU1, sinU2, cosU2 = math.sin(U1), math.cos(U1), math.sin(U2), math.cos(U2)
    lam = L
    for _ in range(200):
        sl, cl = math.sin(lam), math.cos(lam)
        sin_s = math.hypot(cosU2 * sl, cosU1 * sinU2 - sinU1 * cosU2 * cl)
        if sin_s == 0:
            return 0.0
        cos_s = sinU1 * sinU2 + cosU1 * cosU2 * cl
        sigma = math.atan2(sin_s, cos_s)
        sin_a = cosU1 * cosU2 * sl / sin_s
        cos2a = 1 - sin_a**2
        cos2sm = cos_s - 2 * sinU1 * sinU2 / cos2a if cos2a else 0.0
        C = f / 16 * cos2a * (4 + f * (4 - 3 * cos2a))
        prev = lam
        lam = L + (1 - C) * f * sin_a * (sigma + C * sin_s * (cos2sm + C * cos_s * (-1 + 2 * cos2sm**2)))
        if abs(lam - prev) < 1e-13:
            break
    u2 = cos2a * (a * a - b * b) / (b * b)
    A = 1 + u2 / 16384 * (4096 + u2 * (-768 + u2 * (320 - 175 * u2)))
    B = u2 / 1024 * (256 + u2 * (-128 + u2 * (74 - 47 * u2)))
    ds = B * sin_s * (cos2sm + B / 4 * (cos_s * (-1 + 2 * cos2sm**2)
                                        - B / 6 * cos2sm * (-3 + 4 * sin_s**2) * (-3 + 4 * cos2sm**2)))
    return b * A * (sigma - ds)


@pytest.fixture(name="vincenty_m", scope="session")
def vincenty_fixture() -> Callable[[float, float, float, float], float]:
    """Geodesic distance in metres between two WGS84 (lat, lon) points (Vincenty; independent of the library)."""
    return vincenty_m


def run_mavlink_cli(argv: list[str]) -> tuple[int, str, list]:
    """Run ``aerial-loc mavlink`` with ``argv`` into a real UDP socket on loopback (``--connect`` is added) and
    collect every MAVLink message it sends until it ends (plus 0.2 s): (exit status, its printed output, msgs)."""
    from pymavlink.dialects.v20 import common as mavlink2

    from aerial_loc_env.mavlink import cli as mav_cli

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    args = mav_cli.build_parser().parse_args([*argv, "--connect", f"udpout:127.0.0.1:{sock.getsockname()[1]}"])
    out = io.StringIO()
    result = {}
    runner = threading.Thread(target=lambda: result.setdefault("rc", mav_cli.run(args, out=out)))
    runner.start()
    parser = mavlink2.MAVLink(None)
    msgs, drain_until = [], None
    try:
        while drain_until is None or time.monotonic() < drain_until:   # until the run ends, then 0.2 s more
            if drain_until is None and not runner.is_alive():
                drain_until = time.monotonic() + 0.2
            try:
                data, _ = sock.recvfrom(65536)
            except TimeoutError:
                continue
            msgs += parser.parse_buffer(data) or []
        runner.join()
    finally:
        sock.close()
    return result.get("rc", -1), out.getvalue(), msgs


@pytest.fixture(name="run_mavlink_cli", scope="session")
def run_mavlink_cli_fixture() -> Callable[[list[str]], tuple[int, str, list]]:
    """``aerial-loc mavlink`` end to end into a loopback UDP socket: see ``run_mavlink_cli``."""
    return run_mavlink_cli
