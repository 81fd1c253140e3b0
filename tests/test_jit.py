"""jit.py's guard of numba's compile cache, in fresh interpreters with their own NUMBA_CACHE_DIR: a corrupt or
truncated cache file, a cache that cannot be written, and no writable cache location at all each cost a compile
and a warning, never the call."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]

#: calls two of the toolkit's own kernels and prints the values and where they came from
_CALL = """
import numpy as np
from aerial_loc_env.jit import mul255, quantize
print("values", mul255(np.int32(200), np.int32(100)), quantize(np.float32(0.5)))
print("mul255 hits", sum(mul255.stats.cache_hits.values()), "misses", sum(mul255.stats.cache_misses.values()))
"""


def _run(tmp_path: Path, prelude: str = "", *, numba_cache: bool = True) -> tuple[list[str], list[str]]:
    """Run ``prelude`` then ``_CALL`` in a fresh interpreter: (its printed lines, its warning lines)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env.update(TMPDIR=str(tmp_path / "tmp"), PYTHONWARNINGS="default")
    if numba_cache:
        env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")
    (tmp_path / "tmp").mkdir(exist_ok=True)
    code = textwrap.dedent(prelude) + _CALL
    r = subprocess.run([sys.executable, "-c", code], env=env, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    warned = [line for line in r.stderr.splitlines() if "Warning: " in line]
    return r.stdout.splitlines(), warned


def _cache_files(tmp_path: Path, suffix: str) -> list[Path]:
    return sorted((tmp_path / "numba").rglob(f"jit.mul255-*{suffix}"))


GOOD = "values 78 128"


def _damaged(data: bytes, damage: str) -> bytes:
    """``data`` (a cache file's bytes) damaged: the same size of seeded random bytes, cut to half, or an opcode
    whose error from pickle spans two lines (the random bytes draw it now and then)."""
    if damage.startswith("garbage"):
        return np.random.default_rng(26).integers(0, 256, len(data), dtype=np.uint8).tobytes()
    if damage.startswith("truncated"):
        return data[: len(data) // 2]
    return b"P0\n." + data


@pytest.mark.parametrize("damage", ["garbage_index", "truncated_index", "persistent_id_index", "garbage_data",
                                    "truncated_data"])
@pytest.mark.slow
def test_a_corrupt_cache_file_is_removed_and_compiled_again(tmp_path, damage):
    """One warning, on one line, whatever pickle makes of the bytes; then the kernel compiled and cached again."""
    out, warned = _run(tmp_path)
    assert out == [GOOD, "mul255 hits 0 misses 1"] and warned == []
    target = _cache_files(tmp_path, ".nbi" if "index" in damage else ".nbc")
    assert len(target) == 1
    target[0].write_bytes(_damaged(target[0].read_bytes(), damage))
    out, warned = _run(tmp_path)
    assert out == [GOOD, "mul255 hits 0 misses 1"]
    assert len(warned) == 1, warned
    folder = target[0].parent
    assert f"CacheRebuiltWarning: numba's cache of aerial_loc_env.jit.mul255 in {folder} is corrupt (" in warned[0]
    names = ", ".join(p.name for p in sorted(_cache_files(tmp_path, ".nbc") + _cache_files(tmp_path, ".nbi")))
    assert warned[0].endswith(f"); removed {names} and compiling it again")
    assert warned[0].startswith(f"{REPO / 'aerial_loc_env' / 'jit.py'}:")      # at the kernel, not inside numba
    out, warned = _run(tmp_path)                                           # written again, whole
    assert out == [GOOD, "mul255 hits 1 misses 0"] and warned == []


def test_a_cache_that_cannot_be_written_costs_a_compile_not_the_call(tmp_path):
    full_disk = """
        import errno, os
        from numba.core import caching
        def full(self, *args):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        caching.IndexDataCacheFile._save_index = full
    """
    out, warned = _run(tmp_path, full_disk)
    assert out == [GOOD, "mul255 hits 0 misses 1"]
    assert len(warned) == 1, warned
    assert ("CacheLocationWarning: numba cannot write its cache of aerial_loc_env.jit.mul255 in "
            f"{tmp_path / 'numba'}") in warned[0]
    assert warned[0].endswith("(OSError: [Errno 28] No space left on device); the kernels are compiled again in "
                              "each process; free space there or set NUMBA_CACHE_DIR to a writable folder")


@pytest.mark.slow
def test_no_writable_cache_location_falls_back_to_a_temporary_folder(tmp_path):
    nowhere = """
        from numba.core import caching
        for cls in (caching.UserProvidedCacheLocator, caching.InTreeCacheLocator, caching.UserWideCacheLocator):
            cls.from_function = classmethod(lambda cls, func, file: None)     # none of them can be written
    """
    out, warned = _run(tmp_path, nowhere, numba_cache=False)
    assert out == [GOOD, "mul255 hits 0 misses 1"]
    root = tmp_path / "tmp" / f"aerial_loc_env-cache-{os.getuid()}" / "numba"
    assert len(warned) == 1, warned
    assert warned[0].endswith(
        f"CacheLocationWarning: numba cannot write its cache of the compiled kernels beside {REPO / 'aerial_loc_env'} "
        f"(__pycache__), in NUMBA_CACHE_DIR or in its user cache folder; caching them in the temporary folder {root} "
        "instead, which the system may clear; set NUMBA_CACHE_DIR to a writable folder to keep them")
    assert len(list(root.rglob("jit.mul255-*.nbi"))) == 1
    out, _ = _run(tmp_path, nowhere, numba_cache=False)
    assert out == [GOOD, "mul255 hits 1 misses 0"]


def test_borrowed_views_share_their_arrays_memory_and_count_no_references():
    """``borrowed``: views (of an array, or each array of a tuple) that read and write the array's own memory with its
    shape and strides, valid while the owner lives (a local kept to the end by ``keep_alive``); anything else is a
    typing error."""
    import numba as nb

    from aerial_loc_env.jit import borrowed, keep_alive

    @nb.njit
    def fill(a, b):
        owned = np.arange(6.0).reshape(2, 3)
        va, (vb, vo) = borrowed(a), borrowed((b, owned))
        for i in range(va.shape[0]):
            va[i] = 2 * i
        vb[1] = vo[1, 2]                        # a row of a view is a view too
        total = vo.sum() + vo[1].sum()
        keep_alive(owned)
        return total, vo.strides[0]

    a, b = np.zeros(4), np.zeros((3, 2), np.int32)
    total, stride = fill(a, b)
    assert a.tolist() == [0.0, 2.0, 4.0, 6.0] and b.tolist() == [[0, 0], [5, 5], [0, 0]]
    assert total == 15.0 + 12.0 and stride == 24
    with pytest.raises(nb.core.errors.TypingError):
        nb.njit(lambda x: borrowed(x))(3.0)


def test_saturate_u8_clips_every_int32_in_a_vector_loop():
    """``saturate_u8`` in a loop LLVM vectorizes (the form the sensor stage and the samples use, lowered to the packs'
    own saturation) gives ``np.clip`` of every value: in range, just outside it, and at int32's ends, at every lane
    position (a length that leaves a scalar tail)."""
    import numba as nb

    from aerial_loc_env.jit import saturate_u8

    @nb.njit
    def bytes_of(values, out):
        for i in range(values.size):
            out[i] = saturate_u8(values[i])

    edges = np.array([-2 ** 31, -2 ** 31 + 1, -65536, -256, -255, -1, 0, 1, 127, 128, 254, 255, 256, 257, 65535, 65536,
                      2 ** 31 - 1], np.int32)
    drawn = np.random.default_rng(3).integers(-2 ** 31, 2 ** 31, 4099, dtype=np.int64).astype(np.int32)
    values = np.concatenate([np.arange(-300, 600, dtype=np.int32), edges, edges[::-1], drawn])
    out = np.empty(values.size, np.uint8)
    bytes_of(values, out)
    np.testing.assert_array_equal(out, np.clip(values, 0, 255).astype(np.uint8))


#: a factory's kernel: portable's elementwise loop closing over another kernel (numba would pickle that one with an
#: identity drawn anew in every process)
_CLOSURE_CALL = """
import numpy as np
from aerial_loc_env import portable_kernels as k
out = np.empty(2)
k.log(np.array([0.5, 2.0]), out)
print("log", out.tolist(), "hits", sum(k.log.stats.cache_hits.values()), "misses",
      sum(k.log.stats.cache_misses.values()))
"""


def test_a_kernel_closing_over_a_kernel_is_loaded_by_the_next_process(tmp_path):
    """The second interpreter finds the first one's cache entry of a closure over a kernel (``jit._index_key``):
    it loads it instead of compiling again, and no second entry is written."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_")}
    env["NUMBA_CACHE_DIR"] = str(tmp_path / "numba")
    runs = [subprocess.run([sys.executable, "-c", _CLOSURE_CALL], env=env, cwd=REPO, capture_output=True, text=True,
                           timeout=300) for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[-1].stderr
    first, second = (r.stdout.split() for r in runs)
    assert first[-4:] == ["hits", "0", "misses", "1"]
    assert second[-4:] == ["hits", "1", "misses", "0"]
    assert first[:-4] == second[:-4]             # the same values from the loaded code
    assert len(list((tmp_path / "numba").rglob("portable_kernels._elementwise*.nbc"))) == 1


def test_closure_descriptions_are_the_same_in_every_process_and_tell_kernels_apart():
    """``jit._described`` of the perspective frame kernels' closures: equal in two interpreters (no identity, no
    reference count, no string hashing in them), and different for the four variants."""
    code = textwrap.dedent("""
        from aerial_loc_env import jit
        from aerial_loc_env.sensors import perspective_kernels as pk
        for key in sorted(pk.view_finish):
            cells = tuple(c.cell_contents for c in pk.view_finish[key].py_func.__closure__)
            print(key, jit._described(cells))
    """)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONHASHSEED"}
    outs = [subprocess.run([sys.executable, "-c", code], env={**env, "PYTHONHASHSEED": seed}, cwd=REPO,
                           capture_output=True, text=True, timeout=300) for seed in ("1", "2")]
    assert [r.returncode for r in outs] == [0, 0], outs[-1].stderr
    lines = outs[0].stdout.splitlines()
    assert lines == outs[1].stdout.splitlines() and len(lines) == 4
    assert "None" not in outs[0].stdout and len({line.split(") ", 1)[1] for line in lines}) == 4
