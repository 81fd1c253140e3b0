"""MAVLink bridge: stream an estimator's poses to ArduPilot/PX4 as a vision companion computer would.

``PoseFix`` (the input) -> ``MavlinkSender`` (a fixed-rate thread: HEARTBEAT, GPS_INPUT,
VISION_POSITION_ESTIMATE, ODOMETRY, SET_GPS_GLOBAL_ORIGIN); ``EstimateBridge`` turns the env's estimates into
fixes. See docs/mavlink.md. Needs the optional extra ``mavlink`` (pymavlink).
"""

from __future__ import annotations

from aerial_loc_env.errors import require_extra

require_extra("pymavlink", "mavlink", "The MAVLink bridge")

from aerial_loc_env.mavlink.bridge import EstimateBridge  # noqa: E402
from aerial_loc_env.mavlink.fix import FixPolicy, FixQuality, FixSlot, GeoOrigin, PoseFix, assess  # noqa: E402
from aerial_loc_env.mavlink.link import Endpoint, LinkError, parse_connection  # noqa: E402
from aerial_loc_env.mavlink.sender import MavlinkSender, SenderConfig, SenderStats, VehicleState, signing_secret  # noqa: E402

__all__ = ["EstimateBridge", "FixPolicy", "FixQuality", "FixSlot", "GeoOrigin", "PoseFix", "assess",
           "Endpoint", "LinkError", "parse_connection", "MavlinkSender", "SenderConfig", "SenderStats",
           "VehicleState", "signing_secret"]
