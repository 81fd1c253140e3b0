"""sysinfo: the machine and the instruction sets a figure was measured with (benchmark headers, reports)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from aerial_loc_env.sysinfo import isa, machine, vector_isa


def test_vector_isa_names_the_enabled_sets_widest_first():
    assert vector_isa("+avx,+avx2,-avx512f,+fma,+sse4.2") == "AVX2 SSE4.2 FMA"
    assert vector_isa("+avx512f,+avx512vbmi,+avx2,+sse4.2,+fma") == "AVX-512 AVX2 SSE4.2 VBMI FMA"
    assert vector_isa("+neon,+fp-armv8") == "NEON"
    assert vector_isa("-avx2,+cx16") == "baseline"


def test_isa_names_the_target_and_the_kernels_cpu_paths():
    from llvmlite import binding as llvm

    from aerial_loc_env import jit

    text = isa()
    assert text.startswith(llvm.get_host_cpu_name()) or "NUMBA_CPU_NAME" in text
    assert f"FAST_GATHER {jit.FAST_GATHER}, FAST_LUT {jit.FAST_LUT}" in text
    assert machine().count("cores") == 1


def test_isa_under_numba_target_options_says_so():
    """``NUMBA_CPU_NAME`` with an empty ``NUMBA_CPU_FEATURES`` (another CPU's own code, e.g. an AVX2 machine's on an
    AVX-512 host) is named, and the CPU-specific paths are off."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(NUMBA_CPU_NAME="haswell", NUMBA_CPU_FEATURES="")
    r = subprocess.run([sys.executable, "-c", "from aerial_loc_env.sysinfo import isa; print(isa())"], env=env,
                       cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("haswell (NUMBA_CPU_NAME; host ")
    assert "haswell's own (NUMBA_CPU_FEATURES empty); FAST_GATHER False, FAST_LUT False" in r.stdout


def test_isa_says_when_numba_takes_intels_vector_math(monkeypatch):
    """With Intel's SVML (``icc_rt``) numba vectorizes ``portable``'s libm loops with other roundings: said."""
    from numba.core import config

    monkeypatch.setattr(config, "USING_SVML", True)
    assert isa().endswith("; Intel SVML in numba's math (other floats than libm's: see portable)")
    monkeypatch.setattr(config, "USING_SVML", False)
    assert "SVML" not in isa()
