"""Frozen-dataclass configs that reject unknown keys and check declared ranges.

Declare a range on a field with ``field(default=..., metadata=rng(lo, hi))``; ``build_config`` then
rejects values outside it with a message naming the field, where it came from, and the allowed range.
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import sys
import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

from aerial_loc_env.errors import ConfigError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

T = TypeVar("T")


def read_toml(path, what: str = "spec") -> dict:
    """A TOML file as a dict; unreadable, non-UTF-8 or invalid files are ConfigErrors naming the file."""
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the {what}: {exc}") from exc
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ConfigError(f"{path}: the {what} is not UTF-8 text (byte 0x{data[exc.start]:02x} on line {line}); "
                          "TOML files must be UTF-8: re-save it as UTF-8") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: invalid TOML: {exc}") from exc


def is_number(value: Any) -> bool:
    """A real number (Python or NumPy), not a bool."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)   # np.bool_ is not Real


def rng(lo: float | None = None, hi: float | None = None, *, choices: tuple | None = None,
        lo_open: bool = False, hi_open: bool = False, doc: str = "") -> dict:
    """Field metadata declaring the allowed range (closed unless *_open) or the allowed choices."""
    return {"lo": lo, "hi": hi, "choices": choices, "lo_open": lo_open, "hi_open": hi_open, "doc": doc}


def _describe_range(meta: Mapping) -> str:
    if meta.get("choices") is not None:
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    lo, hi = meta.get("lo"), meta.get("hi")
    left = "(" if meta.get("lo_open") else "["
    right = ")" if meta.get("hi_open") else "]"
    return f"{left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"


def check_value(name: str, value: Any, meta: Mapping, where: str) -> None:
    """Raise ConfigError if ``value`` violates the range/choices in ``meta``."""
    if not meta or value is None:  # None: an optional field left unset (its type check is in _coerce)
        return
    if meta.get("choices") is not None:
        if value not in meta["choices"]:
            raise ConfigError(f"{where}: field '{name}' = {value!r} is not allowed; use {_describe_range(meta)}")
        return
    lo, hi = meta.get("lo"), meta.get("hi")
    if lo is None and hi is None:
        return
    values = value if isinstance(value, (tuple, list)) else (value,)
    for v in values:
        if not is_number(v):
            raise ConfigError(f"{where}: field '{name}' must be a number, got {v!r}")
        if not math.isfinite(v):
            raise ConfigError(f"{where}: field '{name}' = {v!r} must be finite, in {_describe_range(meta)}")
        bad_lo = lo is not None and (v <= lo if meta.get("lo_open") else v < lo)
        bad_hi = hi is not None and (v >= hi if meta.get("hi_open") else v > hi)
        if bad_lo or bad_hi:
            raise ConfigError(f"{where}: field '{name}' = {v!r} is out of range; allowed {_describe_range(meta)}")


def _coerce(name: str, value: Any, annotation: Any, where: str) -> Any:
    """Light coercion of TOML/JSON values to the annotated type (int -> float, list -> tuple)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        non_none = [a for a in args if a is not type(None)]
        if len(non_none) == 1:
            return _coerce(name, value, non_none[0], where)
        return value
    if annotation is float:   # NumPy scalars too (np.float32(120) is a number)
        if not is_number(value):
            raise ConfigError(f"{where}: field '{name}' must be a number, got {value!r}")
        return float(value)
    if annotation is int:
        if is_number(value) and float(value).is_integer():
            return int(value)
        raise ConfigError(f"{where}: field '{name}' must be an integer, got {value!r}")
    if annotation is bool and not isinstance(value, bool):
        raise ConfigError(f"{where}: field '{name}' must be true or false, got {value!r}")
    if annotation is str and not isinstance(value, str):
        raise ConfigError(f"{where}: field '{name}' must be a string, got {value!r}")
    if origin is tuple and isinstance(value, list):
        return tuple(value)
    return value


def build_config(cls: type[T], mapping: Mapping[str, Any] | None = None, *, where: str | None = None,
                 base: T | None = None) -> T:
    """Build the frozen dataclass ``cls`` from ``mapping``, optionally on top of ``base``.

    Unknown keys and out-of-range values raise ConfigError naming ``where`` (a file or 'gym.make overrides').
    """
    where = where or cls.__name__
    mapping = dict(mapping or {})
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(mapping) - set(fields))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(map(repr, unknown))} for {cls.__name__}; "
            f"allowed keys: {', '.join(sorted(fields))}"
        )
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for name in fields:
        if name in mapping:
            values[name] = _coerce(name, mapping[name], hints.get(name, Any), where)
        elif base is not None:
            values[name] = getattr(base, name)
    obj = cls(**values)
    for name, f in fields.items():
        check_value(name, getattr(obj, name), f.metadata, where)
    validate = getattr(obj, "validate", None)
    if callable(validate):
        validate(where)
    return obj


def config_to_dict(obj: Any) -> dict:
    """A plain dict (tuples -> lists) that ``build_config`` turns back into ``obj``."""
    out = {}
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            v = config_to_dict(v)
        elif isinstance(v, tuple):
            v = list(v)
        out[f.name] = v
    return out


def parse_assignments(items: Sequence[str], *, where: str, example: str) -> dict[str, Any]:
    """Command-line ``KEY=VALUE`` overrides as a dict: each value read as JSON where it parses (numbers, lists,
    booleans), else kept as the string. ``where`` names the option in the error, ``example`` shows one."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"{where} {item!r} must look like KEY=VALUE (e.g. {example})")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out
