"""Maps built from a spec, cached on disk: one bundle per key, written atomically, checked when read.

The procedural city (``city.py``), its epoch B (``epochs.py``) and its acquired map database
(``acquisition.py``) are pure functions of their specs and of the generators' versions, and each costs seconds
to build; every process (benchmark workers, each ``gym.make``) would otherwise build them again. Each lives in
``paths.cache_dir("maps")`` as an orthomap bundle named by ``spec_key`` of everything that changes it, with that
spec stored as the bundle's provenance. Reading checks the provenance and the layers, so a corrupt entry or a
foreign one (another spec or generator version behind the same name) is rebuilt with a ``CacheRebuiltWarning``
rather than served as a silently wrong map.
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

from aerial_loc_env.errors import MapError
from aerial_loc_env.world.maps.orthomap import Orthomap, read_bundle_meta


class CacheRebuiltWarning(UserWarning):
    """A cached map was unreadable or built from another spec, and is being rebuilt."""


def spec_key(spec: dict[str, Any], length: int = 20) -> str:
    """A short hex digest of a JSON-able spec (key order does not matter): the cache file's name part."""
    blob = json.dumps(spec, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:length]


def _check_entry(path: Path, provenance: dict, size_px: tuple[int, int]) -> Orthomap:
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
    return om


def _discard(path: Path) -> None:
    """Move a bad cache entry aside (atomically) and delete it; a concurrent reader keeps its open files."""
    try:
        aside = Path(tempfile.mkdtemp(prefix=f".{path.name}.bad-", dir=path.parent))
        os.replace(path, aside / "bundle")
        shutil.rmtree(aside, ignore_errors=True)
    except OSError:
        pass


def cached_bundle(path: Path, make: Callable[[], Orthomap], provenance: dict,
                  size_px: tuple[int, int]) -> Orthomap:
    """The bundle at ``path``, memory-mapped; built with ``make()`` and saved atomically when absent or bad.

    An entry whose stored provenance is not ``provenance``, that cannot be read, or that does not have
    ``size_px`` and the dsm_m/classes layers is discarded and rebuilt, with a ``CacheRebuiltWarning`` that
    names it and why. Two processes that race on the first call both build; one rename wins and the other
    loads the winner's bundle.
    """
    if path.exists():
        try:
            return _check_entry(path, provenance, size_px)
        except (MapError, OSError, ValueError, KeyError, TypeError) as exc:
            warnings.warn(f"cached map {path} is unusable ({exc}); rebuilding it", CacheRebuiltWarning,
                          stacklevel=3)
            _discard(path)
    om = make()
    try:
        om.save_bundle(path, provenance=provenance)
    except (MapError, OSError):
        if not path.exists():       # not a lost race but a real failure (disk full, permissions)
            raise
    return Orthomap.load_bundle(path, mmap=True)


__all__ = ["CacheRebuiltWarning", "cached_bundle", "spec_key"]
