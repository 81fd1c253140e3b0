"""Where things live: spec folders (source checkout or installed wheel) and the on-disk cache."""

from __future__ import annotations

import os
import stat
import tempfile
import warnings
from pathlib import Path

from aerial_loc_env.errors import ConfigError

_PKG = Path(__file__).resolve().parent


class CacheRebuiltWarning(UserWarning):
    """A cache entry (a cached map, a compiled kernel) was corrupt or stale, and is being rebuilt."""


class CacheLocationWarning(UserWarning):
    """The cache folder is unusable, so a temporary one (or memory) serves instead."""


def spec_dir(kind: str) -> Path:
    """The folder of spec files ``kind`` ('envs' or 'agents'): the checkout's, else the wheel's copy."""
    if kind not in ("envs", "agents"):
        raise ConfigError(f"unknown spec kind {kind!r}; use 'envs' or 'agents'")
    for candidate in (_PKG.parent / kind, _PKG / "_specs" / kind):
        if candidate.is_dir():
            return candidate
    raise ConfigError(
        f"cannot find the '{kind}' spec folder (looked in {_PKG.parent / kind} and {_PKG / '_specs' / kind}); "
        "reinstall the package"
    )


def cache_dir(*parts: str) -> Path:
    """The package cache folder ``parts`` under $XDG_CACHE_HOME (default ~/.cache)/aerial_loc_env, created on demand.

    Where that folder cannot be made or written (XDG_CACHE_HOME a file, a read-only or foreign folder, a dangling
    link), ``temporary_cache_dir(*parts)`` serves instead, with a ``CacheLocationWarning`` (once per process)
    that names the problem and the fix: a cache is never a reason to stop.
    """
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    path = Path(root, "aerial_loc_env", *parts)
    problem = _unusable(path)
    if problem is None:
        return path
    fallback = temporary_cache_dir(*parts)
    if path not in _WARNED:
        _WARNED.add(path)
        warnings.warn(f"cache folder {path} is unusable ({problem}); caching in the temporary folder {fallback} "
                      "instead, which the system may clear; set XDG_CACHE_HOME to a writable folder to keep the "
                      "cache", CacheLocationWarning, stacklevel=2)
    return fallback


#: cache folders found writable (probed once per process) and unusable ones already warned about
_WRITABLE: set[Path] = set()
_WARNED: set[Path] = set()


def _unusable(path: Path) -> str | None:
    """Why ``path`` cannot serve as a cache folder (created if missing), or None when it can."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        for parent in (path, *path.parents):
            if os.path.lexists(parent) and not parent.is_dir():
                kind = "a dangling link" if parent.is_symlink() and not parent.exists() else "not a folder"
                return f"{parent} is {kind}"
        return f"cannot create it: {exc.strerror or exc}"
    if path in _WRITABLE:
        return None
    try:       # the only sure test (modes, ACLs, read-only mounts, root): write a file
        fd, probe = tempfile.mkstemp(dir=path, prefix=".probe-")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return f"cannot write in it: {exc.strerror or exc}"
    _WRITABLE.add(path)
    return None


def temporary_cache_dir(*parts: str) -> Path:
    """The folder ``parts`` of this user's cache under the system's temporary folder (the fallback of
    ``cache_dir``), created on demand. Its root is private (0700); one that another user made, or that others
    could write, is never used: a fresh private folder for this process takes its place."""
    base = Path(tempfile.gettempdir())
    user = os.getuid() if hasattr(os, "getuid") else os.environ.get("USERNAME", "user")
    root = base / f"aerial_loc_env-cache-{user}"
    try:
        root.mkdir(mode=0o700, exist_ok=True)
        st = os.lstat(root)
        if not (stat.S_ISDIR(st.st_mode) and (not hasattr(os, "getuid") or st.st_uid == os.getuid())
                and not st.st_mode & 0o022):
            root = _private_root(base)
    except OSError:
        root = _private_root(base)
    path = root.joinpath(*parts)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"no usable cache folder: {path} cannot be created either ({exc.strerror or exc}); "
                          "set XDG_CACHE_HOME (or TMPDIR) to a writable folder") from exc
    return path


_PRIVATE_ROOTS: dict[Path, Path] = {}


def _private_root(base: Path) -> Path:
    if base not in _PRIVATE_ROOTS:
        try:
            _PRIVATE_ROOTS[base] = Path(tempfile.mkdtemp(prefix="aerial_loc_env-cache-", dir=base))
        except OSError as exc:
            raise ConfigError(f"no usable cache folder: the temporary folder {base} is not writable "
                              f"({exc.strerror or exc}); set XDG_CACHE_HOME (or TMPDIR) to a writable folder") from exc
    return _PRIVATE_ROOTS[base]


def umask_mode(mode: int = 0o666) -> int:
    """``mode`` less the process's umask: what ``open`` gives a new file (``mkstemp``/``mkdtemp`` give
    0600/0700, which would make results and maps private whatever the user's umask)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:   # Linux: read without changing it
            for line in fh:
                if line.startswith("Umask:"):
                    return mode & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mode & ~mask


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file and rename, so readers never see half a file. The file
    gets the mode a plain ``open`` would give (the user's umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, umask_mode())
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def refuse_overwrite(path: Path, what: str, flag: str = "--overwrite") -> None:
    """Raise if ``path`` exists: nothing the user gave is ever overwritten without being asked."""
    if Path(path).exists():
        raise ConfigError(f"{what} '{path}' already exists and would be overwritten; "
                          f"choose another path or pass {flag}")



#: the package folder: models shipped as package data are named relative to it
PACKAGE_DIR = Path(__file__).resolve().parent


def find_model_file(name: str | os.PathLike, what: str, hint: str) -> Path:
    """A model file a spec names: absolute, else under the package folder (shipped as package data, so a spec
    works from any directory and from a wheel), else under the current directory. None there: a ConfigError
    ``"<what> '<name>' does not exist (looked at ...); <hint>"``."""
    p = Path(name).expanduser()
    candidates = [p] if p.is_absolute() else [PACKAGE_DIR / p, Path.cwd() / p]
    found = next((c for c in candidates if c.is_file()), None)
    if found is None:
        raise ConfigError(f"{what} '{name}' does not exist (looked at {', '.join(str(c) for c in candidates)}); "
                          f"{hint}")
    return found
