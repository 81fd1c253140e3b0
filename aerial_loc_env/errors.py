"""Error classes: every message names the file or field, the problem, and the fix."""

from __future__ import annotations


class AerialLocError(Exception):
    """Base class of every error this package raises on purpose."""


class MapError(AerialLocError, ValueError):
    """A map file or layer is missing, unreadable, or inconsistent."""


class ConfigError(AerialLocError, ValueError):
    """A spec file, config field or override is unknown or out of range."""


class FootprintError(AerialLocError, ValueError):
    """A camera footprint leaves the map or touches no-data."""


class MissingExtraError(AerialLocError, ImportError):
    """An optional dependency is not installed."""


def require_extra(module: str, extra: str, purpose: str):
    """Import an optional module or raise a clear error naming the extra to install."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingExtraError(
            f"{purpose} needs the optional package '{module}', which is not installed. "
            f"Install it with: pip install 'aerial-loc-env[{extra}]'"
        ) from exc
