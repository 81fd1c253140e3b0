"""The project's numba toolkit (layer 0): the compile options every kernel uses and the intrinsics they share.

- ``JIT``: cached, GIL-free, NumPy's error model, no bounds checks, single-threaded (benchmarks are per core;
  users parallelize over environments and workers).
- ``fma32``, ``fma64``, ``prefetch``, ``wide_vectors``: fused float32 / float64 multiply-adds, a cache-line
  prefetch hint and a code-generation hint (512-bit vectors where the CPU has them); hints never change results.
- ``mul255``, ``quantize``: OpenCV's rounded uint8 multiply by a/255 and its float-to-level quantization,
  reproduced bit for bit (the shading and the frame pass both use them).
- ``bilinear_rgba8``, ``bilinear_f32x8``: the bilinear chain on 8 pixels or points at once, each neighbour pair
  one 64-bit load, written in LLVM's target-independent vector operations (fast with AVX2, AVX-512 or NEON alike);
  ``index32``: a flat index in 32-bit arithmetic.
- ``gather_pairs16``, ``gather_f32x16`` (AVX-512 gathers, ``FAST_GATHER``) and ``lut_rgba16`` (VBMI byte
  permutes, ``FAST_LUT``): CPU instructions LLVM does not choose by itself, compiled only where the host has them
  and they pay, with a portable form elsewhere that gives the same values. All follow numba's target:
  with ``NUMBA_CPU_NAME`` set (a portable cache) the portable code.

Fast without AVX-512 (AVX2 x86-64, and other vector units): a loop LLVM vectorizes with AVX-512 can stay scalar or
slow without it where it converts an int64 to float (the loop counter: convert it through int32), multiplies
int64 lanes (numba widens int32 products: ``index32``, or unsigned 32 x 32 -> 64-bit products), loads under a
condition (load unconditionally, then select), stores back a selected value it loaded (``a[i] = max(a[i], t)``
becomes a masked store, slow on AMD: write to another row), carries a sum or flag that numba widened to int64
(the whole loop then takes 64-bit lanes: cast it back to int32 each step), or casts a value to uint8 (every lane
masked before the packs: ``saturate_u8`` uses the packs' own saturation). ``sysinfo.isa()`` says which code
numba compiles for; ``NUMBA_CPU_NAME=znver3 NUMBA_CPU_FEATURES=`` (an empty list: the named CPU's own features)
compiles for an AVX2 machine on any x86-64 host (``NUMBA_CPU_NAME`` alone keeps the host's features, AVX-512
included).

Every compiled module is named ``<module>_kernels.py`` and sits beside the module it serves.

numba's compile cache is made robust here, for the project's kernels only (importing this module, as every
kernel module does, installs it): a corrupt or truncated index or data file (numba raises whatever unpickling
the garbage raises, on every call, until the files are deleted by hand) has that function's cache files removed
and is compiled again with a ``CacheRebuiltWarning``; a cache that cannot be written costs a compile, never the
call; and where neither ``NUMBA_CACHE_DIR``, the module's ``__pycache__`` nor numba's user cache folder can be
written, the kernels are cached in ``paths.temporary_cache_dir("numba")`` with a ``CacheLocationWarning``. A
kernel made by a factory (a closure: ``perspective_kernels.view_finish`` over its band kernel, ``portable``'s
elementwise loops over their scalar function) is found again by the next process: numba keys such a kernel's cache
entry on a pickle of its closure, and a captured kernel pickles with an identity drawn anew in every process, so
each process compiled it again and added one more entry; the key here describes the captured values by what they
are (a kernel by its Python function's module, name, code and own closure; a number or a flag by its value).
"""

from __future__ import annotations

import hashlib
import os
import types as pytypes
import warnings

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import caching, cgutils
from numba.extending import intrinsic, overload

from aerial_loc_env.paths import CacheLocationWarning, CacheRebuiltWarning, temporary_cache_dir

#: numba options of the project's kernels: cached compiles, no GIL, NumPy's error model, no bounds checks;
#: single-threaded on purpose (benchmarks are per core; users parallelize over environments and workers)
JIT = {"cache": True, "nogil": True, "error_model": "numpy", "boundscheck": False}


def _ours(cache: caching.Cache) -> bool:
    return getattr(getattr(cache, "_py_func", None), "__module__", "").startswith("aerial_loc_env.")


def _kernel_name(cache: caching.Cache) -> str:
    func = cache._py_func
    return f"{func.__module__}.{func.__qualname__}"


def _warn_at(func, message: str, category: type[Warning]) -> None:
    """Warn at the kernel's definition: the call that compiles it runs deep inside numba's dispatcher."""
    code = func.__code__
    warnings.warn_explicit(message, category, code.co_filename, code.co_firstlineno, module=func.__module__)


def _in_words(exc: BaseException) -> str:
    """An exception as ``Type: message`` on one line (pickle's messages may span two): a warning stays one line."""
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def _purge(cache: caching.Cache) -> list[str]:
    """Remove one function's index (.nbi) and data files (.nbc) from its numba cache folder; the names removed."""
    folder = cache.cache_path
    index = getattr(getattr(cache, "_cache_file", None), "_index_path", None)     # numba's IndexDataCacheFile
    removed: list[str] = []
    try:
        names = sorted(os.listdir(folder)) if isinstance(index, str) else []
    except OSError:
        return removed
    base = os.path.basename(index)[: -len(".nbi")]
    for name in names:
        if name == f"{base}.nbi" or (name.startswith(f"{base}.") and name.endswith(".nbc")):
            try:
                os.unlink(os.path.join(folder, name))
                removed.append(name)
            except OSError:
                pass
    return removed


_numba_load_overload = caching.FunctionCache.load_overload
_numba_save_overload = caching.FunctionCache.save_overload
_unsaved: set[str] = set()


def _load_overload(self, sig, target_context):
    """numba's ``load_overload``; for the project's kernels a cache entry that cannot be read back (garbage,
    truncated, from a broken write) is removed and reported, and the kernel compiled again."""
    if not _ours(self):
        return _numba_load_overload(self, sig, target_context)
    try:
        return _numba_load_overload(self, sig, target_context)
    except Exception as exc:        # UnpicklingError, EOFError, ValueError, ... whatever the bytes make pickle raise
        removed = _purge(self)
        _warn_at(self._py_func, f"numba's cache of {_kernel_name(self)} in {self.cache_path} is corrupt "
                 f"({_in_words(exc)}); removed {', '.join(removed) or 'nothing'} and compiling it again",
                 CacheRebuiltWarning)
        return None


def _save_overload(self, sig, data):
    """numba's ``save_overload``; for the project's kernels a cache that cannot be written (disk full, read-only,
    a corrupt index written meanwhile) leaves the compiled kernel in use, with a warning."""
    if not _ours(self):
        return _numba_save_overload(self, sig, data)
    try:
        return _numba_save_overload(self, sig, data)
    except Exception as first:
        if not isinstance(first, OSError):      # an unreadable index in the way: remove it and write afresh
            _purge(self)
            try:
                return _numba_save_overload(self, sig, data)
            except Exception as again:
                first = again
        if self.cache_path not in _unsaved:
            _unsaved.add(self.cache_path)
            _warn_at(self._py_func, f"numba cannot write its cache of {_kernel_name(self)} in {self.cache_path} "
                     f"({_in_words(first)}); the kernels are compiled again in each process; free space "
                     "there or set NUMBA_CACHE_DIR to a writable folder", CacheLocationWarning)
        return None


_numba_index_key = caching.Cache._index_key
_SCALARS = (bool, int, float, complex, str, bytes, type(None))


def _code_digest(code: pytypes.CodeType) -> str:
    """A digest of what a code object does (its bytecode, constants, names), the same in every process: not
    ``marshal``'s bytes, which vary with the objects' reference counts, nor a frozenset's order, which varies with
    string hashing."""
    def const(c) -> str:
        if isinstance(c, pytypes.CodeType):
            return _code_digest(c)
        if isinstance(c, frozenset):
            return "frozenset(" + ",".join(sorted(const(v) for v in c)) + ")"
        if isinstance(c, tuple):
            return "(" + ",".join(const(v) for v in c) + ")"
        return repr(c)

    parts = (code.co_code.hex(), const(code.co_consts), repr(code.co_names), repr(code.co_varnames),
             repr(code.co_freevars), repr(code.co_cellvars))
    return hashlib.sha256("|".join(parts).encode()).hexdigest()


def _described(value, depth: int = 0) -> str | None:
    """A closure cell's value as text that is the same in every process for the same value: a kernel (numba
    dispatcher) by its Python function, a function by its module, name, code (``_code_digest``) and own closure,
    a builtin by its module and name, numbers, strings, flags and tuples of them by value; None for anything
    else."""
    if isinstance(value, _SCALARS):
        return f"{type(value).__name__}:{value!r}"
    if depth >= 8:
        return None
    if isinstance(value, tuple):
        parts = [_described(v, depth + 1) for v in value]
        return None if any(p is None for p in parts) else "(" + ",".join(parts) + ")"
    func = getattr(value, "py_func", None)
    if isinstance(func, pytypes.FunctionType):              # a numba dispatcher
        inner = _described(func, depth + 1)
        return None if inner is None else f"jit:{inner}"
    if isinstance(value, pytypes.FunctionType):
        cells = _described(tuple(c.cell_contents for c in value.__closure__ or ()), depth + 1)
        if cells is None:
            return None
        return f"fn:{value.__module__}.{value.__qualname__}:{_code_digest(value.__code__)}:{cells}"
    if isinstance(value, pytypes.BuiltinFunctionType):
        return f"builtin:{value.__module__}.{value.__qualname__}"
    return None


def _index_key(self, sig, codegen):
    """numba's cache index key; for the project's closures with the captured values described by ``_described``
    instead of pickled (a pickled dispatcher carries an identity drawn anew in each process). Other functions, and
    closures over anything it cannot describe, keep numba's key."""
    func = getattr(self, "_py_func", None)
    if _ours(self) and func is not None and func.__closure__ is not None:
        described = _described(func)        # (its code and its cells)
        if described is not None:
            return sig, codegen.magic_tuple(), (hashlib.sha256(described.encode()).hexdigest(),)
    return _numba_index_key(self, sig, codegen)


class _TemporaryCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """numba's last resort for the project's kernels: ``paths.temporary_cache_dir("numba")``, where numba's own
    locations (``NUMBA_CACHE_DIR``, the module's ``__pycache__``, its user cache folder) cannot be written."""

    warned = False

    def __init__(self, py_func, py_file):
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        self._cache_path = str(temporary_cache_dir("numba") / self.get_suitable_cache_subpath(py_file))

    def get_cache_path(self):
        return self._cache_path

    @classmethod
    def from_function(cls, py_func, py_file):
        if not getattr(py_func, "__module__", "").startswith("aerial_loc_env."):
            return None
        try:
            self = super().from_function(py_func, py_file)
        except Exception:      # no usable temporary folder either (ConfigError): numba says it cannot cache
            return None
        if self is not None and not cls.warned:
            cls.warned = True
            _warn_at(py_func, f"numba cannot write its cache of the compiled kernels beside {os.path.dirname(py_file)} "
                     "(__pycache__), in NUMBA_CACHE_DIR or in its user cache folder; caching them in the temporary "
                     f"folder {os.path.dirname(self._cache_path)} instead, which the system may clear; set "
                     "NUMBA_CACHE_DIR to a writable folder to keep them", CacheLocationWarning)
        return self


def _install_cache_guard() -> None:
    """Route numba's function cache through the guards above (once per process; other packages' functions keep
    numba's behaviour) and add the temporary folder as the last cache location."""
    if getattr(caching.FunctionCache, "_aerial_loc_env_guard", False):
        return
    caching.FunctionCache.load_overload = _load_overload
    caching.FunctionCache.save_overload = _save_overload
    caching.FunctionCache._index_key = _index_key
    caching.FunctionCache._aerial_loc_env_guard = True
    impl = caching.CompileResultCacheImpl
    impl._locator_classes = [*impl._locator_classes, _TemporaryCacheLocator]


_install_cache_guard()


def _fma(ty: types.Float, name: str):
    """An intrinsic ``a * b + c`` rounded once in the float type ``ty`` (LLVM's fma: the FMA instruction, or libm's
    fma without one); numba without fastmath fuses nothing else. No silent casts: every operand must be ``ty``."""

    def typer(typingctx, a, b, c):
        if not all(t == ty for t in (a, b, c)):
            return None

        def codegen(context, builder, signature, args):
            return builder.fma(*args)

        return ty(ty, ty, ty), codegen

    typer.__name__ = typer.__qualname__ = name
    return typer


#: float32 ``a * b + c`` rounded once, as OpenCV's ``v_fma``
fma32 = intrinsic(_fma(types.float32, "fma32"))
#: float64 ``a * b + c`` rounded once, as OpenBLAS's FMA kernels accumulate small products (NumPy's ``@`` on 3 x 3
#: and 2 x 2 float64 matrices, reproduced in compiled code)
fma64 = intrinsic(_fma(types.float64, "fma64"))


@intrinsic
def wide_vectors(typingctx):
    """Call first in a kernel: compile the calling function with 512-bit vectors preferred where the CPU has them
    (LLVM's ``"prefer-vector-width"="512"`` on it) and keep it out of numba's wrappers (``noinline``: inlined
    there, it would take the wrappers' attributes). A hint about code generation, never about results: the
    arithmetic is the same (tests compare the outputs bit for bit); on CPUs without AVX-512, and on other
    architectures, LLVM ignores it.

    Why: on AVX-512 Intel cores LLVM's default (256-bit preferred; wider operations still legal) mixes 256-bit
    loops with 512-bit ones in one function, and such a frame pass (``render_kernels.warp_finish``) runs slower
    whenever other work ran just before it (the 512-bit units' warm-up); with 512-bit vectors throughout it runs
    at the same speed either way (docs/perf-log.md has the figures)."""
    sig = types.void()

    def codegen(context, builder, signature, args):
        attrs = builder.function.attributes
        attrs.add("noinline")
        # llvmlite's FunctionAttributes accepts only its known keywords; LLVM reads this key-value one
        set.add(attrs, '"prefer-vector-width"="512"')
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def prefetch(typingctx, arr, k):
    """A read prefetch of element ``k`` of the array ``arr`` into every cache level (LLVM's ``llvm.prefetch``: a
    hint, never a fault, wherever ``k`` points): for gathers whose addresses are known a few rows ahead."""
    if not isinstance(arr, types.Array) or not isinstance(k, types.Integer):
        return None
    sig = types.void(arr, k)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            "llvm.prefetch.p0i8")
        ptr = builder.bitcast(builder.gep(data, [args[1]]), i8p)
        builder.call(fn, [ptr, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return sig, codegen


def _borrowed_view(context, builder, ty: types.Array, value):
    src = context.make_array(ty)(context, builder, value)
    view = context.make_array(ty)(context, builder)
    for field in ("nitems", "itemsize", "data", "shape", "strides"):
        setattr(view, field, getattr(src, field))
    view.meminfo = cgutils.get_null_value(view.meminfo.type)
    view.parent = cgutils.get_null_value(view.parent.type)
    return view._getvalue()


@intrinsic
def borrowed(typingctx, arr):
    """A view of the array ``arr`` (or a tuple of such views of a tuple of arrays) that numba counts no references
    to (no memory info): for arrays bound again and again in a kernel's loops, as inlined helpers bind their
    arguments per call (numba counts a reference at each binding, an atomic add, and cannot drop the counts across
    the helpers' loops). A view is valid while its array lives: an argument of the kernel, or a local kept to the
    end by ``keep_alive``; a kernel never returns one (Python would get memory that no one owns)."""
    if isinstance(arr, types.Array):
        def codegen(context, builder, signature, args):
            return _borrowed_view(context, builder, arr, args[0])

        return arr(arr), codegen
    if isinstance(arr, types.BaseTuple) and all(isinstance(t, types.Array) for t in arr.types):
        def codegen_tuple(context, builder, signature, args):
            views = [_borrowed_view(context, builder, t, builder.extract_value(args[0], i))
                     for i, t in enumerate(arr.types)]
            return context.make_tuple(builder, arr, views)

        return arr(arr), codegen_tuple
    return None


@intrinsic
def keep_alive(typingctx, value):
    """Nothing, but a use of ``value`` here: numba frees a local at its last use, so a kernel ends with this on the
    owners of its ``borrowed`` views."""
    sig = types.void(value)

    def codegen(context, builder, signature, args):
        return context.get_dummy_value()

    return sig, codegen


def _host_has(*features: str) -> bool:
    """Whether numba compiles for this host (no ``NUMBA_CPU_NAME`` / ``NUMBA_CPU_FEATURES``: a portable cache
    compiles for a generic CPU) and the host's CPU has all these LLVM features (e.g. ``"+avx512vbmi"``)."""
    from llvmlite import binding as llvm
    from numba.core import config

    if config.CPU_NAME is not None or config.CPU_FEATURES is not None:
        return False
    try:
        have = set(llvm.get_host_cpu_features().flatten().split(","))
    except Exception:  # pragma: no cover - a host llvmlite cannot describe: the portable code
        return False
    return all(f in have for f in features)


def _host_cpu() -> str:
    """LLVM's name of the host's CPU (e.g. ``"emeraldrapids"``)."""
    from llvmlite import binding as llvm

    return llvm.get_host_cpu_name()


#: points per ``gather_pairs16``
GATHER_LANES = 16
#: LLVM's names of the CPUs whose AVX-512 gathers are fast: Intel's server cores from Sapphire Rapids on (not affected
#: by Gather Data Sampling, so no microcode slows their gathers). Elsewhere (the Skylake to Rocket Lake families, whose
#: mitigated gathers are several times slower, as LLVM's own "prefer-no-gather" tuning says; AMD; Arm) the scalar
#: loads are as fast or faster, and the only code that compiles.
_FAST_GATHER_CPUS = frozenset({"sapphirerapids", "emeraldrapids", "graniterapids", "graniterapids-d",
                               "diamondrapids"})


#: whether the box-sampling passes use ``gather_pairs16`` on this host (see ``_FAST_GATHER_CPUS``)
FAST_GATHER = _host_has("+avx512f") and _host_cpu() in _FAST_GATHER_CPUS


@intrinsic
def gather_pairs16(typingctx, flat, idx, x, off, first, second):
    """For 16 points from ``x``: ``first[x + i] = flat[idx[x + i] + off]`` and ``second[x + i]`` the pixel after
    it (``flat``, ``idx``, ``first``, ``second`` 1-D C-contiguous uint32; every index + 1 below 2**31 and inside
    ``flat``), by two AVX-512 ``vpgatherdq``: each point's two pixels as one 64-bit load, split by two shuffles.
    Compiled only where ``FAST_GATHER`` (elsewhere LLVM could not select it).

    Why: LLVM does not vectorize the box-sampling passes' neighbour loads (four per pixel); a pair per 64-bit lane
    gathers half the elements that one 32-bit gather per neighbour would (docs/perf-log.md has the figures)."""
    if not (isinstance(x, types.Integer) and isinstance(off, types.Integer)
            and all(isinstance(a, types.Array) and a.dtype == types.uint32 and a.ndim == 1 and a.layout == "C"
                    for a in (flat, idx, first, second))):
        return None
    sig = types.void(flat, idx, x, off, first, second)

    def codegen(context, builder, signature, args):
        flat_p, idx_p, first_p, second_p = (context.make_array(signature.args[i])(context, builder, args[i]).data
                                            for i in (0, 1, 4, 5))
        i1, i32, i64 = ir.IntType(1), ir.IntType(32), ir.IntType(64)
        v16, v8, q8 = ir.VectorType(i32, 16), ir.VectorType(i32, 8), ir.VectorType(i64, 8)
        i8p = ir.IntType(8).as_pointer()
        xi = context.cast(builder, args[2], signature.args[2], types.intp)
        k0 = builder.trunc(context.cast(builder, args[3], signature.args[3], types.int64), i32)
        iv = builder.load(builder.bitcast(builder.gep(idx_p, [xi]), v16.as_pointer()), align=4)
        off_v = builder.shuffle_vector(builder.insert_element(ir.Constant(v16, None), k0, ir.Constant(i32, 0)),
                                       ir.Constant(v16, None), ir.Constant(v16, [0] * 16))
        kv = builder.add(iv, off_v)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(q8, [q8, i8p, v8, ir.VectorType(i1, 8),
                                                                             i32]),
                                            "llvm.x86.avx512.mask.gather.dpq.512")
        mask, base = ir.Constant(ir.VectorType(i1, 8), [1] * 8), builder.bitcast(flat_p, i8p)
        halves = []
        for h in range(2):
            k8 = builder.shuffle_vector(kv, ir.Constant(v16, None), ir.Constant(v8, list(range(8 * h, 8 * h + 8))))
            got = builder.call(fn, [ir.Constant(q8, None), base, k8, mask, ir.Constant(i32, 4)])
            halves.append(builder.bitcast(got, v16))
        for parity, dest in ((0, first_p), (1, second_p)):    # little-endian: the pixel at k is the low half
            part = builder.shuffle_vector(halves[0], halves[1], ir.Constant(v16, list(range(parity, 32, 2))))
            builder.store(part, builder.bitcast(builder.gep(dest, [xi]), v16.as_pointer()), align=4)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def gather_f32x16(typingctx, table, idx, x, out):
    """``out[x + i] = table[idx[x + i]]`` for the 16 points from ``x`` (``table``, ``out`` 1-D C-contiguous float32,
    ``idx`` 1-D C-contiguous int32, every index inside ``table``) by one AVX-512 ``vgatherdps``. Compiled only where
    ``FAST_GATHER``, as ``gather_pairs16``.

    Why: the perspective maps' fixed-point steps look up the height model at ~60k listed pixels three times a
    frame, each a scalar load LLVM does not vectorize."""
    if not (isinstance(x, types.Integer)
            and all(isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C" for a in (table, idx, out))
            and table.dtype == types.float32 and out.dtype == types.float32 and idx.dtype == types.int32):
        return None
    sig = types.void(table, idx, x, out)

    def codegen(context, builder, signature, args):
        tab_p, idx_p, out_p = (context.make_array(signature.args[i])(context, builder, args[i]).data
                               for i in (0, 1, 3))
        i1, i8, i32 = ir.IntType(1), ir.IntType(8), ir.IntType(32)
        v16, f16 = ir.VectorType(i32, GATHER_LANES), ir.VectorType(ir.FloatType(), GATHER_LANES)
        xi = context.cast(builder, args[2], signature.args[2], types.intp)
        k = builder.load(builder.bitcast(builder.gep(idx_p, [xi]), v16.as_pointer()), align=4)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(f16, [f16, i8.as_pointer(), v16,
                                                                              ir.VectorType(i1, GATHER_LANES), i32]),
                                            "llvm.x86.avx512.mask.gather.dps.512")
        got = builder.call(fn, [ir.Constant(f16, None), builder.bitcast(tab_p, i8.as_pointer()), k,
                                ir.Constant(ir.VectorType(i1, GATHER_LANES), [1] * GATHER_LANES), ir.Constant(i32, 4)])
        builder.store(got, builder.bitcast(builder.gep(out_p, [xi]), f16.as_pointer()), align=4)
        return context.get_dummy_value()

    return sig, codegen


#: pixels per ``bilinear_rgba8`` call
BILINEAR_PIXELS = 8


@intrinsic
def bilinear_rgba8(typingctx, flat, idx, stride, fa, fb, out, x):
    """The bilinear samples of the 8 pixels from ``x``: pixel ``x + i`` has its top-left neighbour at
    ``flat[idx[x + i]]`` (``flat`` uint32 RGBA pixels, memory order), the top-right one after it and the bottom pair
    ``stride`` pixels further, its weights ``fa[x + i]``, ``fb[x + i]`` (float32); each channel's value is the fma
    chain ``v0 = fma(a, p01 - p00, p00)``, ``v1 = fma(a, p11 - p10, p10)``, ``fma(b, v1 - v0, v0)`` rounded half to
    even, written to ``out[4 (x + i) + c]`` (uint8). Arrays 1-D C-contiguous (``idx`` uint32, every index +
    ``stride`` + 1 inside ``flat``).

    Why: the same arithmetic as a loop over the pixels (``render_kernels._blend_row``), but each neighbour pair is
    one 64-bit load (two loads a pixel, not four, and no neighbour rows stored and read back) and the chain runs on
    the 32 channels as one vector, each pixel's weights spread to its four channels by a shuffle. Two pixels' pairs
    share a 256-bit vector, one in the low half of each 128-bit lane, so that one in-lane byte shuffle with zeros
    widens a pixel of each pair to its four channels as int32 (the bytes read as little-endian words, as on every
    target numba has), where all eight pairs in one vector took cross-lane shuffles to split. Written in
    LLVM's target-independent vector operations: the target's widest registers do it (two 256-bit halves with
    AVX2, one 512-bit register with AVX-512, NEON's 128-bit ones), where a loop over the pixels needs AVX-512's
    byte permutes to vectorize well; no instruction that some x86-64 lacks."""
    if not (isinstance(x, types.Integer) and isinstance(stride, types.Integer)
            and all(isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C" for a in (flat, idx, fa, fb, out))
            and flat.dtype == types.uint32 and idx.dtype == types.uint32 and out.dtype == types.uint8
            and fa.dtype == types.float32 and fb.dtype == types.float32):
        return None
    sig = types.void(flat, idx, stride, fa, fb, out, x)

    def codegen(context, builder, signature, args):
        flat_p, idx_p, fa_p, fb_p, out_p = (context.make_array(signature.args[i])(context, builder, args[i]).data
                                            for i in (0, 1, 3, 4, 5))
        p, n = BILINEAR_PIXELS, 4 * BILINEAR_PIXELS
        i8, i32, i64, f32 = ir.IntType(8), ir.IntType(32), ir.IntType(64), ir.FloatType()
        xi = context.cast(builder, args[6], signature.args[6], types.intp)
        below = builder.zext(context.cast(builder, args[2], signature.args[2], types.uint32), i64)
        # the neighbour pairs (p00, p01) and (p10, p11), one 64-bit load each; two pixels' pairs a 256-bit vector
        v4, vb32, v8i32 = ir.VectorType(i64, 4), ir.VectorType(i8, 32), ir.VectorType(i32, 8)
        zero32 = ir.Constant(vb32, [0] * 32)
        halves = ([], [])
        for q in range(p // 2):
            words = ([], [])
            for i in (2 * q, 2 * q + 1):
                k = builder.zext(builder.load(builder.gep(idx_p, [builder.add(xi, ir.Constant(xi.type, i))])), i64)
                for row, at in enumerate((k, builder.add(k, below))):
                    words[row].append(builder.load(builder.bitcast(builder.gep(flat_p, [at]), i64.as_pointer()),
                                                   align=4))
            for row in (0, 1):
                vec = ir.Constant(v4, None)
                for lane, word in zip((0, 2), words[row], strict=True):
                    vec = builder.insert_element(vec, word, ir.Constant(i32, lane))
                halves[row].append(builder.bitcast(vec, vb32))
        vf = ir.VectorType(f32, n)

        def widened(row: int, second: bool):
            """The first or second pixel of each pair of this row, its four channels as float32 (32 lanes)."""
            lanes = [16 * (j // 4) + 4 * second + j % 4 for j in range(8)]
            mask = ir.Constant(ir.VectorType(i32, 32), [lanes[d // 4] if d % 4 == 0 else 32 for d in range(32)])
            parts = [builder.uitofp(builder.bitcast(builder.shuffle_vector(h, zero32, mask), v8i32),
                                    ir.VectorType(f32, 8)) for h in halves[row]]
            while len(parts) > 1:
                parts = [builder.shuffle_vector(parts[j], parts[j + 1], ir.Constant(
                    ir.VectorType(i32, 2 * parts[j].type.count), list(range(2 * parts[j].type.count))))
                    for j in range(0, len(parts), 2)]
            return parts[0]

        p00, p01, p10, p11 = widened(0, False), widened(0, True), widened(1, False), widened(1, True)
        wv, spread = ir.VectorType(f32, p), ir.Constant(ir.VectorType(i32, n), [j // 4 for j in range(n)])
        a, b = (builder.shuffle_vector(builder.load(builder.bitcast(builder.gep(w, [xi]), wv.as_pointer()), align=4),
                                       ir.Constant(wv, None), spread) for w in (fa_p, fb_p))
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vf, [vf, vf, vf]), f"llvm.fma.v{n}f32")
        rint = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vf, [vf]), f"llvm.rint.v{n}f32")
        v0 = builder.call(fma, [a, builder.fsub(p01, p00), p00])
        v1 = builder.call(fma, [a, builder.fsub(p11, p10), p10])
        value = builder.call(rint, [builder.call(fma, [b, builder.fsub(v1, v0), v0])])
        vb = ir.VectorType(i8, n)
        dest = builder.gep(out_p, [builder.mul(xi, ir.Constant(xi.type, 4))])
        vi = ir.VectorType(i32, n)     # saturated as ``saturate_u8`` saturates (the packs' own saturation)
        smax = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vi, [vi, vi]), f"llvm.smax.v{n}i32")
        smin = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vi, [vi, vi]), f"llvm.smin.v{n}i32")
        level = builder.call(smin, [builder.call(smax, [builder.fptosi(value, vi), ir.Constant(vi, [0] * n)]),
                                    ir.Constant(vi, [255] * n)])
        builder.store(builder.trunc(level, vb), builder.bitcast(dest, vb.as_pointer()), align=1)
        return context.get_dummy_value()

    return sig, codegen


#: points per ``bilinear_f32x8`` call
BILINEAR_LANES = 8


@intrinsic
def bilinear_f32x8(typingctx, plane, idx, below, fa, fb, out, j):
    """The bilinear samples of the 8 points from ``j``: point ``j + i`` has its top-left neighbour at
    ``plane[idx[j + i]]`` (``plane`` float32, one channel's pixels), the top-right one after it and the bottom pair
    ``below`` further, its weights ``fa[j + i]``, ``fb[j + i]``; ``out[j + i]`` = the fma chain
    ``v0 = fma(a, p01 - p00, p00)``, ``v1 = fma(a, p11 - p10, p10)``, ``fma(b, v1 - v0, v0)`` (float32, unrounded).
    Arrays 1-D C-contiguous (``idx`` uint32, every index + ``below`` + 1 inside ``plane``).

    Why: as ``bilinear_rgba8``: each neighbour pair one 64-bit load (two loads a point, not four) and the chain on
    8 points at once in LLVM's target-independent vector operations. LLVM vectorizes the loop form only with
    AVX-512's gathers (four per 16 points); without them it stays scalar."""
    if not (isinstance(j, types.Integer) and isinstance(below, types.Integer)
            and all(isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C"
                    for a in (plane, idx, fa, fb, out))
            and idx.dtype == types.uint32
            and all(a.dtype == types.float32 for a in (plane, fa, fb, out))):
        return None
    sig = types.void(plane, idx, below, fa, fb, out, j)

    def codegen(context, builder, signature, args):
        plane_p, idx_p, fa_p, fb_p, out_p = (context.make_array(signature.args[i])(context, builder, args[i]).data
                                             for i in (0, 1, 3, 4, 5))
        n = BILINEAR_LANES
        i32, i64, f32 = ir.IntType(32), ir.IntType(64), ir.FloatType()
        ji = context.cast(builder, args[6], signature.args[6], types.intp)
        step = builder.zext(context.cast(builder, args[2], signature.args[2], types.uint32), i64)
        pairs = [ir.Constant(ir.VectorType(i64, n), None), ir.Constant(ir.VectorType(i64, n), None)]
        for i in range(n):      # the neighbour pairs: (p00, p01) and (p10, p11), one 64-bit load each
            k = builder.zext(builder.load(builder.gep(idx_p, [builder.add(ji, ir.Constant(ji.type, i))])), i64)
            for row, at in enumerate((k, builder.add(k, step))):
                word = builder.load(builder.bitcast(builder.gep(plane_p, [at]), i64.as_pointer()), align=4)
                pairs[row] = builder.insert_element(pairs[row], word, ir.Constant(i32, i))
        v2n, vf = ir.VectorType(f32, 2 * n), ir.VectorType(f32, n)
        even = ir.Constant(ir.VectorType(i32, n), [2 * i for i in range(n)])      # memory order: first of a pair
        odd = ir.Constant(ir.VectorType(i32, n), [2 * i + 1 for i in range(n)])
        top, bottom = (builder.bitcast(pair, v2n) for pair in pairs)
        p00, p01, p10, p11 = (builder.shuffle_vector(row, ir.Constant(v2n, None), lane)
                              for row, lane in ((top, even), (top, odd), (bottom, even), (bottom, odd)))
        a, b = (builder.load(builder.bitcast(builder.gep(w, [ji]), vf.as_pointer()), align=4) for w in (fa_p, fb_p))
        fma = cgutils.get_or_insert_function(builder.module, ir.FunctionType(vf, [vf, vf, vf]), f"llvm.fma.v{n}f32")
        v0 = builder.call(fma, [a, builder.fsub(p01, p00), p00])
        v1 = builder.call(fma, [a, builder.fsub(p11, p10), p10])
        value = builder.call(fma, [b, builder.fsub(v1, v0), v0])
        builder.store(value, builder.bitcast(builder.gep(out_p, [ji]), vf.as_pointer()), align=4)
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def index32(typingctx, row, stride, col):
    """int32 ``row * stride + col`` in 32-bit arithmetic (numba widens int32 products to int64: a 64-bit vector
    multiply, which AVX2 lacks and emulates); the caller keeps it below 2**31."""
    if not all(t == types.int32 for t in (row, stride, col)):
        return None

    def codegen(context, builder, signature, args):
        return builder.add(builder.mul(args[0], args[1], flags=["nsw"]), args[2], flags=["nsw"])

    return types.int32(types.int32, types.int32, types.int32), codegen


#: whether ``lut_rgba16`` uses AVX-512 VBMI's byte permutes on this host (Ice Lake and later Intel cores, AMD Zen 4
#: and later): a 256-entry byte table is two two-register permutes and a select, 64 lookups at a time
FAST_LUT = _host_has("+avx512vbmi", "+avx512bw")
#: pixels per ``lut_rgba16`` block: one 512-bit vector of RGBA bytes
LUT_PIXELS = 16


@intrinsic
def _lut_rgba16_vbmi(typingctx, src, x, tabs, out, alpha):
    """``lut_rgba16`` by AVX-512 VBMI (C-contiguous arrays only; compiled only where ``FAST_LUT``)."""
    if not (isinstance(x, types.Integer)
            and all(isinstance(a, types.Array) and a.dtype == types.uint8 and a.ndim == 1 and a.layout == "C"
                    for a in (src, tabs, out, alpha))):
        return None
    sig = types.int32(src, x, tabs, out, alpha)

    def codegen(context, builder, signature, args):
        src_p, tab_p, out_p, alpha_p = (context.make_array(signature.args[i])(context, builder, args[i]).data
                                        for i in (0, 2, 3, 4))
        i8, i16, i32 = ir.IntType(8), ir.IntType(16), ir.IntType(32)
        n = LUT_PIXELS
        xi = context.cast(builder, args[1], signature.args[1], types.intp)
        x3, x4 = builder.mul(xi, ir.Constant(xi.type, 3)), builder.mul(xi, ir.Constant(xi.type, 4))
        v64 = ir.VectorType(i8, 64)
        vec = builder.load(builder.bitcast(builder.gep(src_p, [x4]), v64.as_pointer()), align=1)
        permute = cgutils.get_or_insert_function(builder.module, ir.FunctionType(v64, [v64, v64, v64]),
                                                 "llvm.x86.avx512.vpermi2var.qi.512")
        high = builder.icmp_signed("<", vec, ir.Constant(v64, [0] * 64))    # index >= 128
        looked = []
        for c in range(3):
            quarter = [builder.load(builder.bitcast(builder.gep(tab_p, [ir.Constant(xi.type, 256 * c + 64 * k)]),
                                                    v64.as_pointer()), align=1) for k in range(4)]
            low_half = builder.call(permute, [quarter[0], vec, quarter[1]])
            high_half = builder.call(permute, [quarter[2], vec, quarter[3]])
            looked.append(builder.select(high, high_half, low_half))
        # byte 4 i + c from channel c's lookups (masked blends), then the 48 colour bytes in order by one vpermb
        # (LLVM's own lowering of a 64 -> 48 byte shuffle inserted bytes one by one), stored as 32 + 16 bytes
        mix = looked[0]
        for c in (1, 2):
            mix = builder.select(ir.Constant(ir.VectorType(ir.IntType(1), 64), [j % 4 == c for j in range(64)]),
                                 looked[c], mix)
        vpermb = cgutils.get_or_insert_function(builder.module, ir.FunctionType(v64, [v64, v64]),
                                                "llvm.x86.avx512.permvar.qi.512")
        order = [4 * (j // 3) + j % 3 for j in range(3 * n)] + [0] * (64 - 3 * n)
        rgb = builder.call(vpermb, [mix, ir.Constant(v64, order)])
        for start, size in ((0, 32), (32, 16)):
            part = builder.shuffle_vector(rgb, ir.Constant(v64, None),
                                          ir.Constant(ir.VectorType(i32, size), list(range(start, start + size))))
            dest = builder.gep(out_p, [builder.add(x3, ir.Constant(xi.type, start))])
            builder.store(part, builder.bitcast(dest, ir.VectorType(i8, size).as_pointer()), align=1)
        a16 = builder.shuffle_vector(vec, ir.Constant(v64, None), ir.Constant(
            ir.VectorType(i32, n), [4 * i + 3 for i in range(n)]))
        builder.store(a16, builder.bitcast(builder.gep(alpha_p, [xi]), ir.VectorType(i8, n).as_pointer()), align=1)
        bits = builder.bitcast(builder.icmp_signed("<", a16, ir.Constant(ir.VectorType(i8, n), [0] * n)), i16)
        ctpop = cgutils.get_or_insert_function(builder.module, ir.FunctionType(i16, [i16]), "llvm.ctpop.i16")
        return builder.zext(builder.call(ctpop, [bits]), i32)

    return sig, codegen


def lut_rgba16(src, x, tabs, out, alpha):
    """The tone lookups of 16 RGBA pixels from pixel ``x`` of ``src`` (uint8, 4 bytes a pixel):
    ``out[3 x + 3 i + c] = tabs[256 c + src[4 (x + i) + c]]`` for c < 3 (``tabs`` uint8 (768,): one byte table per
    channel), ``alpha[x + i] = src[4 (x + i) + 3]``; returns how many of those alphas exceed 127. In compiled code:
    AVX-512 VBMI's ``vpermi2b`` per 128 table entries, a select on the index's top bit and constant shuffles
    (where ``FAST_LUT``, on C-contiguous arrays: ``_lut_rgba16_vbmi``), else the scalar lookups (this function). The
    same bytes either way (tests compare both).

    Why: a frame's tone lookups are 3 x 240k bytes, each a scalar load and store LLVM does not vectorize; the
    permutes do 16 pixels in about a dozen instructions."""
    count = 0
    for i in range(LUT_PIXELS):
        p = 4 * (x + i)
        for c in range(3):
            out[3 * (x + i) + c] = tabs[256 * c + np.int64(src[p + c])]
        alpha[x + i] = src[p + 3]
        count += np.int32(src[p + 3] > 127)
    return np.int32(count)


@overload(lut_rgba16, jit_options=JIT)
def _lut_rgba16_jit(src, x, tabs, out, alpha):
    if FAST_LUT and all(isinstance(a, types.Array) and a.layout == "C" for a in (src, tabs, out, alpha)):
        return lambda src, x, tabs, out, alpha: _lut_rgba16_vbmi(src, x, tabs, out, alpha)
    return lut_rgba16


@nb.njit(inline="always", **JIT)
def saturate_u8(v):
    """The int32 ``v`` saturated to 0..255, as uint8. Why this form for a value already in range too: LLVM turns it
    into the vector packs' own saturation, where a bare cast masks every lane before the packs and a float clamp
    adds a compare, a mask and a minimum per vector (docs/perf-log.md has the sensor stage's figures)."""
    return np.uint8(min(max(v, np.int32(0)), np.int32(255)))


@nb.njit(inline="always", **JIT)
def mul255(a, b):
    """round(a b / 255) for a, b in [0, 255] (int32): ``cv2.multiply(a, b, scale=1/255)`` on uint8."""
    p = a * b + np.int32(128)
    return (p + (p >> np.int32(8))) >> np.int32(8)


@nb.njit(inline="always", **JIT)
def quantize(v):
    """The occlusion level of a float occlusion ``v``: ``cv2.convertScaleAbs(v, alpha=255)`` (int32 in [0, 255]).
    NaN and levels beyond int32 give 0, as OpenCV's (cvRound's INT_MIN saturated), never an out-of-range index."""
    x = np.abs(v * np.float32(255.0))
    if x <= np.float32(255.0):
        return np.int32(np.rint(x))
    return np.int32(255) if x < np.float32(2147483648.0) else np.int32(0)   # NaN: both comparisons False
