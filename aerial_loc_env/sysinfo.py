"""What machine a figure was measured on (benchmarks, reports, training logs), and which instructions the compiled
kernels use there."""

from __future__ import annotations

import os
import platform

import numpy as np


def machine() -> str:
    """CPU model, core count, Python and NumPy versions: noted beside every speed figure."""
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}"


#: LLVM feature -> the name a reader knows, widest first; the first two decide the vector width
_VECTOR_FEATURES = (("avx512f", "AVX-512"), ("avx2", "AVX2"), ("sse4.2", "SSE4.2"), ("neon", "NEON"),
                    ("sve", "SVE"), ("avx512vbmi", "VBMI"), ("fma", "FMA"))


def vector_isa(features: str) -> str:
    """The vector instruction sets named in an LLVM feature list (``+avx2,-avx512f,...``): e.g.
    ``"AVX-512 AVX2 SSE4.2 VBMI FMA"``, or ``"baseline"`` where none is."""
    have = {f[1:] for f in features.split(",") if f.startswith("+")}
    return " ".join(name for key, name in _VECTOR_FEATURES if key in have) or "baseline"


def isa() -> str:
    """The code numba compiles the kernels for: LLVM's CPU name, its vector instructions and which of the
    kernels' CPU-specific paths run (``jit.FAST_GATHER``, ``jit.FAST_LUT``); set by ``NUMBA_CPU_NAME`` /
    ``NUMBA_CPU_FEATURES`` where given (``NUMBA_CPU_NAME=znver3 NUMBA_CPU_FEATURES=``: an AVX2 machine's code on
    any x86-64 host), and whether numba vectorizes math with Intel's SVML (``icc_rt`` installed), which rounds
    ``portable``'s functions otherwise. Imports numba (seconds on a cold start): for benchmark headers, not for
    every report."""
    from llvmlite import binding as llvm
    from numba.core import config

    from aerial_loc_env import jit

    host = llvm.get_host_cpu_name()
    cpu = config.CPU_NAME or host
    if config.CPU_FEATURES is None:
        features = f"{vector_isa(llvm.get_host_cpu_features().flatten())} (the host's)"
    elif config.CPU_FEATURES == "":
        features = f"{cpu}'s own (NUMBA_CPU_FEATURES empty)"
    else:
        features = f"{vector_isa(config.CPU_FEATURES)} (NUMBA_CPU_FEATURES)"
    target = cpu if cpu == host else f"{cpu} (NUMBA_CPU_NAME; host {host})"
    svml = "; Intel SVML in numba's math (other floats than libm's: see portable)" if config.USING_SVML else ""
    return f"{target}, {features}; FAST_GATHER {jit.FAST_GATHER}, FAST_LUT {jit.FAST_LUT}{svml}"


#: NumPy's dispatch targets beyond AVX2 (numpy 2's names; older ones use AVX512F, AVX512_SKX ...)
_NUMPY_BEYOND_AVX2 = ("X86_V4", "AVX512_SKX", "AVX512_CLX", "AVX512_CNL", "AVX512_ICL", "AVX512_SPR", "AVX512F",
                      "AVX512CD", "AVX512_KNL", "AVX512_KNM")
#: OpenCV's names of the AVX-512 features behind its AVX512_SKX dispatch (it warns about naming one the host lacks)
_OPENCV_AVX512 = ("AVX512F", "AVX512-COMMON", "AVX512-SKX", "AVX512BW", "AVX512CD", "AVX512DQ", "AVX512VL")


def avx2_env(cache_dir: str) -> dict[str, str]:
    """Environment variables that make a new x86-64 process compute as an AVX2 machine without AVX-512 does, on any
    host: numba compiles Zen 3's own code (its kernels cached in ``cache_dir``), NumPy and OpenCV leave out their
    AVX-512 code, OpenBLAS takes its Haswell kernels, torch (the learned agents' extra) its AVX2 ones. For
    benchmarks of the AVX2 path and for checking that results do not depend on the CPU (``portable``); each library
    reads them at import."""
    from numpy._core import _multiarray_umath as npcore

    numpy_off = [f for f in _NUMPY_BEYOND_AVX2 if f in npcore.__cpu_dispatch__]
    opencv_off = _OPENCV_AVX512 if npcore.__cpu_features__.get("AVX512_SKX") else ()
    return {"NUMBA_CPU_NAME": "znver3", "NUMBA_CPU_FEATURES": "", "NUMBA_CACHE_DIR": cache_dir,
            "NPY_DISABLE_CPU_FEATURES": " ".join(numpy_off), "OPENBLAS_CORETYPE": "Haswell",
            "OPENCV_CPU_DISABLE": ",".join(opencv_off), "ATEN_CPU_CAPABILITY": "avx2"}
