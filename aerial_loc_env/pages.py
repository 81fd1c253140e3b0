"""How large NumPy arrays get their memory pages.

NumPy asks Linux for transparent huge pages (2 MB) for every array of 4 MB or more (``madvise(MADV_HUGEPAGE)``).
Where the kernel defragments on such a request (the THP ``defrag`` setting ``madvise``, the kernel's default, or
``always``), a first touch of a fresh array can stall while the kernel compacts memory to free a whole 2 MB
block, and the longer a machine has run, the longer it stalls. Work that fills many short-lived large arrays once
or a few times each (the procedural city and its epochs: dozens of full-map planes) then spends more time in those
faults than in its own arithmetic, while arrays read many times over (a renderer's map copy, a baked box) gain
from huge pages' fewer TLB misses. ``small_pages`` turns NumPy's request off for the arrays made inside it, and
only there.
"""

from __future__ import annotations

import contextlib
import importlib
import threading
from collections.abc import Callable, Iterator

_lock = threading.Lock()
_depth = 0
_saved = True


def _switch() -> Callable[[bool], bool] | None:
    """NumPy's setter of its huge-page request (it returns the previous setting; off Linux it changes nothing),
    or None where this NumPy has none."""
    for name in ("numpy._core.multiarray", "numpy.core.multiarray"):     # NumPy 2, NumPy 1
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        setter = getattr(module, "_set_madvise_hugepage", None)
        if callable(setter):
            return setter
    return None


@contextlib.contextmanager
def small_pages() -> Iterator[None]:
    """Inside, NumPy's new arrays take the system's normal pages (no huge-page request); on exit the setting
    before the outermost entry comes back. Nests, and is safe across threads (a counter under a lock: the setting
    is the process's). A no-op where NumPy has no such setting."""
    global _depth, _saved
    switch = _switch()
    if switch is None:
        yield
        return
    with _lock:
        if _depth == 0:
            _saved = bool(switch(False))
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                switch(_saved)


__all__ = ["small_pages"]
