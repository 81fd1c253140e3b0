"""The link: a serial port without pyserial is a clear error naming the device and the extra that brings it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import tomllib

from aerial_loc_env.errors import MissingExtraError
from aerial_loc_env.mavlink.link import Link, parse_connection


def test_serial_without_pyserial_names_the_device_and_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "serial", None)     # as if pyserial were not installed
    link = Link(parse_connection("/dev/ttyACM7,921600"))
    with pytest.raises(MissingExtraError, match=r"/dev/ttyACM7.*pyserial.*aerial-loc-env\[mavlink\]"):
        link.open()


def test_pyserial_is_in_the_mavlink_extra():
    meta = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())
    extra = meta["project"]["optional-dependencies"]["mavlink"]
    assert any(req.lower().startswith("pyserial") for req in extra), extra
