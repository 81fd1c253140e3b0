"""Maps built from a spec, cached on disk: one bundle per key, written atomically, checked when read.

The procedural city (``city.py``), its epoch B (``epochs.py``) and its acquired map database
(``acquisition.py``) are pure functions of their specs and of the generators' versions, and each costs seconds
to build; every process (benchmark workers, each ``gym.make``) would otherwise build them again. Each lives in
``paths.cache_dir("maps")`` as an orthomap bundle named by ``spec_key`` of everything that changes it, with that
spec stored as the bundle's provenance. Reading checks the provenance, the size and each layer's SHA-256 (the
bundle's own check, ``orthomap.py``; an entry written before checksums gains them on first use), so a corrupt
entry (truncated, changed at the same size, a dangling link) or a foreign one (another spec or generator version
behind the same name) is rebuilt with a ``CacheRebuiltWarning`` rather than served as a silently wrong map. A
cache that cannot be written (disk full, read-only) costs time, never the run: the entry goes to the temporary
cache folder, else stays in memory, with a ``CacheLocationWarning``; an unusable cache folder is replaced by a
temporary one upfront (``paths.cache_dir``).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

from aerial_loc_env.errors import ConfigError, MapError
from aerial_loc_env.paths import CacheLocationWarning, CacheRebuiltWarning, temporary_cache_dir
from aerial_loc_env.world.maps.orthomap import Orthomap, add_bundle_checksums, read_bundle_meta

#: what reading a damaged entry can raise (besides MapError): caught, the entry rebuilt
_ENTRY_ERRORS = (MapError, OSError, ValueError, KeyError, TypeError)


def spec_key(spec: dict[str, Any], length: int = 20) -> str:
    """A short hex digest of a JSON-able spec (key order does not matter): the cache file's name part."""
    blob = json.dumps(spec, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:length]


def _check_entry(path: Path, provenance: dict, size_px: tuple[int, int]) -> Orthomap:
    if path.is_symlink() and not path.exists():
        raise MapError(f"it is a link to {os.readlink(path)}, which does not exist")
    meta = read_bundle_meta(path)
    want = json.loads(json.dumps(provenance))       # as JSON stores it (tuples become lists)
    have = meta.get("provenance")
    if have != want:
        keys = sorted(k for k in set(want) | set(have if isinstance(have, dict) else {})
                      if not isinstance(have, dict) or have.get(k) != want.get(k))
        raise MapError(f"it was built from another spec (provenance differs in {', '.join(keys) or 'type'})")
    om = Orthomap.load_bundle(path, mmap=True)
    w_px, h_px = size_px
    if (om.width_px, om.height_px) != (w_px, h_px) or om.dsm_m is None or om.classes is None:
        raise MapError(f"it has size {om.width_px}x{om.height_px} or lacks layers; expected {w_px}x{h_px} with "
                       "dsm_m and classes")
    if any(isinstance(info, dict) and "sha256" not in info for info in meta["layers"].values()):
        add_bundle_checksums(path)      # written before checksums: taken as it is, verified from now on
    return om


def _discard(path: Path) -> None:
    """Move a bad cache entry aside (atomically) and delete it; a concurrent reader keeps its open files. A link
    is removed, never what it points to."""
    try:
        aside = Path(tempfile.mkdtemp(prefix=f".{path.name}.bad-", dir=path.parent))
        os.replace(path, aside / "bundle")
        shutil.rmtree(aside, ignore_errors=True)
    except OSError:
        pass


def _temporary_twin(path: Path) -> Path | None:
    """Where ``path``'s entry goes when its own folder cannot take it: the same name in the temporary cache
    folder (None when ``path`` is already there, or no temporary folder is usable)."""
    try:
        twin = temporary_cache_dir(path.parent.name) / path.name
    except ConfigError:
        return None
    return None if twin.parent.resolve() == path.parent.resolve() else twin


def _reuse(path: Path, provenance: dict, size_px: tuple[int, int]) -> Orthomap | None:
    """The sound entry at ``path``, else None after warning and discarding what is there."""
    try:
        return _check_entry(path, provenance, size_px)
    except _ENTRY_ERRORS as exc:
        reason = str(exc).replace(f"{path}{os.sep}", "")      # the entry's own files by their names
        warnings.warn(f"cached map {path} is unusable ({reason}); rebuilding it", CacheRebuiltWarning, stacklevel=4)
        _discard(path)
        return None


def _reason(exc: BaseException) -> str:
    return exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)


def cached_bundle(path: Path, make: Callable[[], Orthomap], provenance: dict,
                  size_px: tuple[int, int]) -> Orthomap:
    """The bundle at ``path``, memory-mapped; built with ``make()`` and saved atomically when absent or bad.

    An entry whose stored provenance is not ``provenance``, that cannot be read, whose layers do not match their
    checksums, or that does not have ``size_px`` and the dsm_m/classes layers is discarded and rebuilt, with a
    ``CacheRebuiltWarning`` that names it and why (one written before checksums gains them instead). Where
    ``path`` cannot be written (disk full, a folder made read-only meanwhile), the entry is saved in the temporary
    cache folder for this process's use (its workers map it), else used from memory, with a
    ``CacheLocationWarning``; the next process tries ``path`` again. Two processes that race on the first call
    both build; one rename wins and the other loads the winner's bundle.
    """
    if os.path.lexists(path) and (om := _reuse(path, provenance, size_px)) is not None:
        return om
    om = make()
    failures: list[str] = []
    for target in (path, _temporary_twin(path)):
        if target is None:
            continue
        try:
            om.save_bundle(target, provenance=provenance)
            saved = Orthomap.load_bundle(target, mmap=True)
        except _ENTRY_ERRORS as exc:
            try:            # another process saved it meanwhile: use theirs if it is sound
                saved = _check_entry(target, provenance, size_px)
            except _ENTRY_ERRORS:
                failures.append(f"{target.parent}: {_reason(exc)}")
                continue
        if failures:
            warnings.warn(f"cannot write the cached map {path.name} in {failures[0]}; saved it in the temporary "
                          f"folder {target.parent} instead, which the system may clear; free space in "
                          f"{path.parent} or set XDG_CACHE_HOME to a writable folder", CacheLocationWarning,
                          stacklevel=3)
        return saved
    warnings.warn(f"cannot write the cached map {path.name} ({'; '.join(failures)}); using it from memory in this "
                  f"process, which builds it again next time; free space in {path.parent} or set XDG_CACHE_HOME "
                  "to a writable folder", CacheLocationWarning, stacklevel=3)
    return om


__all__ = ["CacheLocationWarning", "CacheRebuiltWarning", "cached_bundle", "spec_key"]
