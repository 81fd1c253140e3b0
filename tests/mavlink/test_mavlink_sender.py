"""The sender: what its status counts while the link is down, and MAVLink 2 signing keys (hex or passphrase)."""

from __future__ import annotations

import time

import pytest

from aerial_loc_env.errors import ConfigError
from aerial_loc_env.mavlink import cli as mav_cli
from aerial_loc_env.mavlink.fix import GeoOrigin, PoseFix
from aerial_loc_env.mavlink.selfcheck import free_udp_port
from aerial_loc_env.mavlink.sender import MavlinkSender, SenderConfig, signing_secret

FIX = PoseFix(time_s=0.0, lat_deg=47.4, lon_deg=8.54, alt_amsl_m=600.0, east_m=0.0, north_m=0.0, up_m=100.0,
              vel_enu_mps=(1.0, 0.0, 0.0), yaw_rad=0.0, cov_en_m2=(4.0, 0.0, 4.0), v_std_m=0.5,
              yaw_std_rad=0.05, speed_std_mps=0.5)


def test_status_counts_only_messages_the_link_took():
    """A udpin link nobody has talked to cannot send: nothing may be counted as sent, all as dropped."""
    cfg = SenderConfig(connect=f"udpin:127.0.0.1:{free_udp_port()}", rate_hz=50.0, heartbeat_hz=10.0)
    with MavlinkSender(cfg, origin=GeoOrigin(47.4, 8.54, 500.0)) as sender:
        sender.publish(FIX)
        time.sleep(0.3)
        stats = sender.stats()
    assert stats.dropped > 0
    assert sum(stats.sent.values()) == 0, stats.sent
    line = mav_cli.status_line(0.0, stats)
    assert "gps_input=" not in line and f"dropped={stats.dropped}" in line


def test_non_utf8_signing_key_is_a_clear_error():
    key = b"caf\xe9-key".decode("utf-8", "surrogateescape")    # what argv holds for non-UTF-8 bytes
    with pytest.raises(ConfigError, match="signing_key.*UTF-8"):
        signing_secret(key)
    args = mav_cli.build_parser().parse_args(["--demo", "--signing-key", key])
    with pytest.raises(ConfigError, match="signing_key.*UTF-8"):
        mav_cli.sender_config(args)


@pytest.mark.parametrize("digits", [63, 65, 62])
def test_almost_hex_signing_key_is_refused_not_hashed(digits):
    with pytest.raises(ConfigError, match=f"{digits} hex digits.*64"):
        signing_secret("a" * digits)


def test_signing_keys_that_stay_valid():
    assert signing_secret("ab" * 32) == bytes([0xAB] * 32)
    assert len(signing_secret("correct horse battery staple")) == 32
    assert len(signing_secret("cafe")) == 32        # a short passphrase that happens to be hex
