"""portable: libm's floats element by element and products summed in index order, so that maps, frames and
estimates are the same on every CPU; checked in a process that computes as an AVX2 machine does."""

from __future__ import annotations

import functools
import hashlib
import json
import math
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from shared_helpers import host_env

from aerial_loc_env import portable

_UNARY = [("exp", math.exp, -30.0, 30.0), ("log", math.log, 1e-3, 1e3), ("log1p", math.log1p, -0.9, 10.0),
          ("arcsin", math.asin, -1.0, 1.0), ("arctan", math.atan, -50.0, 50.0), ("arctanh", math.atanh, -0.99, 0.99),
          ("sinh", math.sinh, -5.0, 5.0), ("cosh", math.cosh, -5.0, 5.0), ("tan", math.tan, -1.5, 1.5)]


@pytest.mark.parametrize(("name", "ref", "lo", "hi"), _UNARY)
def test_each_function_gives_libms_floats(name, ref, lo, hi):
    x = np.random.default_rng(0).uniform(lo, hi, 3000).reshape(60, 50)
    got = getattr(portable, name)(x)
    assert got.dtype == np.float64 and got.shape == x.shape
    np.testing.assert_array_equal(got.reshape(-1), [ref(v) for v in x.reshape(-1)])
    assert getattr(portable, name)(float(x[0, 0])) == ref(float(x[0, 0]))      # a number gives a float


def test_two_argument_functions_give_libms_floats():
    rng = np.random.default_rng(1)
    y, x = rng.normal(size=500), rng.normal(size=500)
    np.testing.assert_array_equal(portable.arctan2(y, x), [math.atan2(a, b) for a, b in zip(y, x, strict=True)])
    np.testing.assert_array_equal(portable.arctan2(y[:, None], x[None, :3]),
                                  [[math.atan2(a, b) for b in x[:3]] for a in y])          # broadcast
    p = rng.uniform(0.0, 2.0, 500)
    np.testing.assert_array_equal(portable.power(p, 1.0 / 2.2), [v ** (1.0 / 2.2) for v in p])


def test_float32_stays_float32_and_scalars_keep_their_kind():
    x32 = np.linspace(0.1, 2.0, 50, dtype=np.float32)
    for f in (portable.exp, portable.log, portable.arcsin, portable.arctan):
        assert f(x32).dtype == np.float32
    assert portable.power(x32, 0.45).dtype == np.float32
    np.testing.assert_allclose(portable.power(x32, 0.45), x32.astype(np.float64) ** 0.45, rtol=2e-7)
    assert portable.arctan2(x32, x32[::-1]).dtype == np.float32
    assert portable.arctan2(x32, x32[::-1].astype(np.float64)).dtype == np.float64
    assert isinstance(portable.exp(np.float32(1.0)), np.float32)
    assert isinstance(portable.exp(1), float) and isinstance(portable.arctan2(1.0, 2.0), float)


def test_limits_are_numpys_without_its_warnings():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert portable.log(0.0) == -np.inf and math.isnan(portable.log(-1.0))
        assert portable.log1p(-1.0) == -np.inf and math.isnan(portable.log1p(-2.0))
        assert math.isnan(portable.arcsin(1.5)) and portable.arctanh(-1.0) == -np.inf
        assert portable.exp(1000.0) == np.inf and portable.exp(-1000.0) == 0.0
        assert all(math.isnan(f(math.nan)) for f in (portable.exp, portable.log, portable.sinh, portable.tan))


def test_exp_writes_in_place_and_refuses_a_wrong_out():
    x = np.linspace(-2.0, 2.0, 9)
    want = portable.exp(x)
    assert portable.exp(x, out=x) is x
    np.testing.assert_array_equal(x, want)
    with pytest.raises(ValueError, match="out must be a C-contiguous float64 array of shape"):
        portable.exp(x, out=np.empty(3))


def _in_order(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Each entry's products added one by one from zero, in the operands' own type."""
    zero = a.dtype.type(0)
    return np.array([[functools.reduce(lambda s, t: s + a[i, t] * b[t, j], range(a.shape[1]), zero)
                      for j in range(b.shape[1])] for i in range(a.shape[0])], a.dtype)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_matmul_adds_the_products_in_index_order(dtype):
    rng = np.random.default_rng(2)
    a, b = rng.normal(size=(5, 40)).astype(dtype), rng.normal(size=(40, 3)).astype(dtype)
    got = portable.matmul(a, b)
    assert got.dtype == dtype
    np.testing.assert_array_equal(got, _in_order(a, b))
    np.testing.assert_array_equal(portable.matmul(a[0], b), _in_order(a[:1], b)[0])          # vector @ matrix
    np.testing.assert_array_equal(portable.matmul(a, b[:, 0]), _in_order(a, b[:, :1])[:, 0])  # matrix @ vector
    assert portable.matmul(a[0], b[:, 0]) == _in_order(a[:1], b[:, :1])[0, 0]
    np.testing.assert_allclose(got, a @ b, rtol=1e-4 if dtype == np.float32 else 1e-12)
    with pytest.raises(ValueError, match="do not align"):
        portable.matmul(a, b.T)
    with pytest.raises(ValueError, match="1-D or 2-D operands"):
        portable.matmul(a[None], b)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_matmul_of_a_wide_operand_adds_in_index_order_too(dtype):
    """A ``b`` of many columns (a convolution's) goes row by row through the kernel: the same index-order sums."""
    rng = np.random.default_rng(4)
    a, b = rng.normal(size=(3, 25)).astype(dtype), rng.normal(size=(25, 40)).astype(dtype)
    np.testing.assert_array_equal(portable.matmul(a, b), _in_order(a, b))
    np.testing.assert_array_equal(portable.matmul(a[1], b), _in_order(a[1:2], b)[0])


def cpu_sensitive_results() -> dict[str, str]:
    """Digests of what NumPy's vector code and OpenBLAS's kernels would make depend on the CPU: the portable
    functions, NumPy's functions the module says are the same everywhere, and the simulator's and estimators'
    uses (a map's colour response, the shading and tone curves, facade light, a UTM round trip, two MCL runs)."""
    import gymnasium as gym

    import aerial_loc_env  # noqa: F401
    from aerial_loc_env.estimators.episode import EpisodeDriver
    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.sensors.perspective import PerspectiveConfig, ReliefView, ViewMaps
    from aerial_loc_env.sensors.render import gamma_lut, tone_lut
    from aerial_loc_env.world.maps.acquisition import AcquisitionConfig, _colour_response
    from aerial_loc_env.world.maps.geo import UTMProjection
    from aerial_loc_env.world.shadows import shading_lut

    def digest(*arrays) -> str:
        h = hashlib.sha256()
        for a in arrays:
            h.update(np.ascontiguousarray(a).tobytes())
        return h.hexdigest()[:16]

    rng = np.random.default_rng(3)
    x, x32 = rng.uniform(-3.0, 3.0, 20000), rng.uniform(0.01, 3.0, 20000).astype(np.float32)
    out = {name: digest(getattr(portable, name)(np.clip(x, lo, hi)), getattr(portable, name)(
        np.clip(x32, lo, hi).astype(np.float32))) for name, _, lo, hi in _UNARY}
    out["arctan2 power matmul"] = digest(portable.arctan2(x, x[::-1]), portable.power(x32, 0.45),
                                         portable.matmul(x.reshape(-1, 4)[:50], x.reshape(4, -1)[:, :60]))
    out["numpy's own"] = digest(np.sqrt(x32), np.sin(x), np.cos(x), np.exp(x32), np.log(x32), np.sin(x32),
                                np.hypot(x, x[::-1]), np.sum(x), x.reshape(-1, 8).sum(axis=0), np.tanh(x))
    img = rng.integers(0, 256, (64, 96, 3), dtype=np.uint8)
    cfg = AcquisitionConfig(tone_gamma=0.8, saturation=1.2, contrast=1.1, gain_rgb=(1.05, 1.0, 0.95))
    out["acquisition colour"] = digest(_colour_response(img, cfg))
    out["tone curves"] = digest(shading_lut(0.8, shadow_ratio=0.3, sky_tint_rgb=(0.6, 0.7, 0.9), gamma=2.1),
                                gamma_lut(0.93),
                                tone_lut(1.07, np.array([1.02, 0.98, 1.01])))
    ang = rng.uniform(-np.pi, np.pi, 5000)
    facing = np.stack([np.sin(ang), np.cos(ang)], axis=1).astype(np.float32)
    view = ViewMaps(np.zeros((1, 1), np.float32), np.zeros((1, 1), np.float32), np.arange(ang.size),
                    (0.0, 0.0, 1.0, 1.0), facing)
    out["facade light"] = digest(ReliefView(None, PerspectiveConfig(enabled=True)).facade_gains(view, (200.0, 35.0)))
    utm = UTMProjection(32, south=False)
    e, n = utm.forward(rng.uniform(45.0, 50.0, 300), rng.uniform(6.0, 12.0, 300))
    out["utm"] = digest(e, n, *utm.inverse(e, n))
    env = gym.make("AerialLoc/Small-v3", **{"flight.duration_s": 2.0})    # frames from the box baked at level 1
    obs, _ = env.reset(seed=3)
    images = [obs["image"]] + [env.step(np.zeros(2, np.float32))[0]["image"] for _ in range(3)]
    out["Small-v3 frames"] = digest(*images)
    env.close()
    for name in ("mcl-ssd", "mcl-global"):   # (dense and pair models; the weighted mean, the mean-shift mode)
        env = gym.make("AerialLoc/PaperShadows-v2", **{"flight.duration_s": 3.0})
        with EpisodeDriver(env, [make_agent(name)]) as driver:
            out[name] = digest(*[np.array([r.estimates[0].x_m, r.estimates[0].y_m]) for r in driver.run(5)])
        env.close()
    return out


@pytest.mark.slow
@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="emulates an x86-64 AVX2 CPU")
def test_results_are_the_same_on_an_avx2_cpu(tmp_path, avx2_numba_cache):
    """The same digests from a process that computes as an AVX2 machine without AVX-512 does (``sysinfo.avx2_env``:
    numba's code, NumPy's and OpenCV's dispatch, OpenBLAS's kernels); on an AVX2 host this compares it with itself
    (the AVX-512 side is then checked where the digests' other machines run the suite)."""
    from aerial_loc_env.sysinfo import avx2_env

    env = host_env()
    env.update(avx2_env(str(avx2_numba_cache)), PYTHONPATH=str(Path(__file__).parent), XDG_CACHE_HOME=str(tmp_path))
    script = "import json, test_portable as t; print(json.dumps(t.cpu_sensitive_results()))"
    r = subprocess.run([sys.executable, "-c", script], env=env, cwd=Path(__file__).resolve().parents[1],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    theirs, ours = json.loads(r.stdout.splitlines()[-1]), cpu_sensitive_results()
    differ = sorted(k for k in ours if theirs.get(k) != ours[k])
    assert not differ, f"computed otherwise on an AVX2 CPU: {differ}"
