"""Where things live: spec folders (source checkout or installed wheel) and the on-disk cache."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from aerial_loc_env.errors import ConfigError

_PKG = Path(__file__).resolve().parent


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
    """The package cache under $XDG_CACHE_HOME (default ~/.cache)/aerial_loc_env, created on demand."""
    root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    path = Path(root) / "aerial_loc_env"
    for p in parts:
        path = path / p
    path.mkdir(parents=True, exist_ok=True)
    return path


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
