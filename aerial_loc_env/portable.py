"""Math whose results are the same on every CPU: exp, log, atan2, powers and matrix products for the simulator's
data and the estimators' weights.

Why: NumPy computes ``exp``, ``log``, ``arctan2``, ``power`` (and more) with its own vector code where the CPU has
AVX-512, and with libm elsewhere; OpenBLAS picks a matrix kernel per CPU. These round differently in the last
bits, so a world generated, a frame rendered or a particle cloud weighted on an AVX-512 machine differed from one
on an AVX2 machine, and a particle filter turns such bits into other resampling draws. The functions here call
libm once per element (``portable_kernels``; as NumPy does without AVX-512) and add products in index order, so
results depend on the inputs alone. Use them wherever a result reaches a map, a frame, an estimate or a digest;
NumPy's own ``sqrt``, ``sin``, ``cos``, float32 ``exp``/``log``, ``hypot``, sums and elementwise arithmetic are
already the same everywhere (``tests/test_portable.py`` checks both lists under emulated CPUs).

A libm with other roundings (not glibc's) or a numba with Intel's vector math library (``icc_rt``) installed gives
other floats; ``sysinfo.isa()`` (the benchmark header) says when numba has it.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from aerial_loc_env import portable_kernels as _k


def _float_array(x: Any) -> np.ndarray:
    """``x`` as a C-contiguous float array: float32 stays float32, anything else becomes float64 (NumPy's rule
    for these functions)."""
    a = np.asarray(x)
    return np.asarray(a, dtype=np.float32 if a.dtype == np.float32 else np.float64, order="C")


def _like_input(res: np.ndarray, *inputs: Any) -> Any:
    """``res`` as the inputs were given: an array for arrays, a NumPy scalar for NumPy scalars, else a float."""
    if any(np.ndim(x) for x in inputs):
        return res
    return res[()] if any(isinstance(x, np.generic) for x in inputs) else float(res)


def _unary(kernel: Any, x: Any, out: np.ndarray | None, *args: Any) -> Any:
    """``kernel(flat x, *args, flat result)`` into a new array or ``out``."""
    a = _float_array(x)
    res = np.empty_like(a) if out is None else out
    if res.shape != a.shape or res.dtype != a.dtype or not res.flags.c_contiguous:
        raise ValueError(f"portable: out must be a C-contiguous {a.dtype} array of shape {a.shape}, got "
                         f"{res.dtype} {res.shape}")
    kernel(a.reshape(-1), *args, res.reshape(-1))
    return res if out is not None else _like_input(res, x)


def exp(x: Any, out: np.ndarray | None = None) -> Any:
    """``np.exp`` (libm's, per element); a Python number gives a float. ``out`` may be ``x`` itself."""
    if type(x) is float and out is None:       # (a number: libm's exp as Python calls it, without the arrays)
        try:
            return math.exp(x)
        except OverflowError:
            return math.inf
    return _unary(_k.exp, x, out)


def log(x: Any, out: np.ndarray | None = None) -> Any:
    """``np.log``: -inf at 0, NaN below it (without NumPy's warnings)."""
    if type(x) is float and out is None:
        return math.log(x) if x > 0 else (-math.inf if x == 0 else math.nan)
    return _unary(_k.log, x, out)


def _elementwise(kernel: Any, name: str, limits: str = "") -> Any:
    def f(x: Any) -> Any:
        return _unary(kernel, x, None)

    f.__name__ = f.__qualname__ = name
    f.__doc__ = f"``np.{name}`` (libm's, per element){limits}."
    return f


log1p = _elementwise(_k.log1p, "log1p", ": -inf at -1, NaN below it")
arcsin = _elementwise(_k.arcsin, "arcsin", ": NaN outside [-1, 1]")
arctan = _elementwise(_k.arctan, "arctan")
arctanh = _elementwise(_k.arctanh, "arctanh", ": +-inf at +-1, NaN beyond")
sinh = _elementwise(_k.sinh, "sinh")
cosh = _elementwise(_k.cosh, "cosh")
tan = _elementwise(_k.tan, "tan")


def arctan2(y: Any, x: Any) -> Any:
    """``np.arctan2`` of broadcast ``y``, ``x`` (float32 where both are float32)."""
    ya, xa = np.asarray(y), np.asarray(x)
    dtype = np.float32 if ya.dtype == np.float32 and xa.dtype == np.float32 else np.float64
    yb, xb = np.broadcast_arrays(ya, xa)
    yc, xc = np.asarray(yb, dtype, order="C"), np.asarray(xb, dtype, order="C")
    out = np.empty(yc.shape, dtype)
    _k.arctan2(yc.reshape(-1), xc.reshape(-1), out.reshape(-1))
    return _like_input(out, y, x)


def power(x: Any, p: float) -> Any:
    """``np.power(x, p)`` for a scalar exponent, in ``x``'s precision (a float32 array: ``powf``)."""
    return _unary(_k.power, x, None, (np.float32 if np.asarray(x).dtype == np.float32 else np.float64)(p))


def matmul(a: Any, b: Any) -> Any:
    """``a @ b`` for 1-D and 2-D operands, each entry's products added in index order (no BLAS); float32 where
    both are float32, else float64; a 1-D by 1-D product gives a float."""
    aa, ba = np.asarray(a), np.asarray(b)
    if aa.ndim == 1 and ba.ndim == 1 and aa.dtype == ba.dtype == np.float64 and aa.shape == ba.shape:
        return _k.dot(aa, ba)      # (the particle filter's weighted sums: one call, the same floats as below)
    if aa.ndim not in (1, 2) or ba.ndim not in (1, 2):
        raise ValueError(f"portable.matmul: 1-D or 2-D operands, got {aa.shape} and {ba.shape}")
    dtype = np.float32 if aa.dtype == np.float32 and ba.dtype == np.float32 else np.float64
    a2 = np.ascontiguousarray(aa.reshape(1, -1) if aa.ndim == 1 else aa, dtype=dtype)
    b2 = np.ascontiguousarray(ba.reshape(-1, 1) if ba.ndim == 1 else ba, dtype=dtype)
    if a2.shape[1] != b2.shape[0]:
        raise ValueError(f"portable.matmul: shapes {aa.shape} and {ba.shape} do not align")
    out = np.zeros((a2.shape[0], b2.shape[1]), dtype)
    _k.matmul(a2, b2, out)
    if aa.ndim == 1 and ba.ndim == 1:
        return float(out[0, 0])
    if aa.ndim == 1:
        return out[0]
    return out[:, 0] if ba.ndim == 1 else out


__all__ = ["arcsin", "arctan", "arctan2", "arctanh", "cosh", "exp", "log", "log1p", "matmul", "power", "sinh", "tan"]
