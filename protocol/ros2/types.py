"""ROS 2 message types: one type store, DDS type names and RIHS01 type hashes per distro.

rmw_zenoh puts the message type into every data key and liveliness token twice: as the DDS
type name (``nav_msgs::msg::dds_::OccupancyGrid_``) and as the type hash. Humble's
rmw_zenoh (0.1.x) writes the literal ``TypeHashNotSupported`` where Jazzy (0.2.x) and Kilted
(0.6.x) write ``RIHS01_<sha256>`` (REP 2011); the hash is computed by ``rosbags``, never
copied by hand.
"""

from __future__ import annotations

from functools import cache
from typing import Any

#: The distros whose rmw_zenoh key format is supported; Humble has no type hashes.
DISTROS = ("humble", "jazzy", "kilted")
#: What Humble's rmw_zenoh writes in place of the type hash.
HASH_NOT_SUPPORTED = "TypeHashNotSupported"

OCCUPANCY_GRID = "nav_msgs/msg/OccupancyGrid"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
LASER_SCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
#: Humble's definition differs from Jazzy's only by a constant (``ARROW_STRIP``), which
#: neither the CDR layout nor the type hash holds: one type store serves every distro.
MARKER_ARRAY = "visualization_msgs/msg/MarkerArray"


@cache
def typestore() -> Any:
    """The ``rosbags`` type store of ROS 2 Jazzy (whose message definitions Kilted shares).

    Imported on first use: ``rosbags`` is needed only by agents that talk to ROS 2.
    """
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def check_distro(distro: str) -> str:
    """Return ``distro`` if it is one of :data:`DISTROS`, else raise ``ValueError``."""
    if distro not in DISTROS:
        raise ValueError(f"unknown ROS 2 distro {distro!r}, expected one of {', '.join(DISTROS)}")
    return distro


def dds_type_name(msgtype: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``, the type name rmw_zenoh writes in keys.

    Raises
    ------
    ValueError
        If ``msgtype`` is not of the form ``pkg/msg/Name``.
    """
    parts = msgtype.split("/")
    if len(parts) != 3 or not all(parts) or parts[1] != "msg":
        raise ValueError(f"not a ROS 2 message type: {msgtype!r} (expected pkg/msg/Name)")
    pkg, _, name = parts
    return f"{pkg}::msg::dds_::{name}_"


def type_hash(msgtype: str, distro: str) -> str:
    """The type-hash field of ``msgtype``'s keys on ``distro``'s rmw_zenoh."""
    if check_distro(distro) == "humble":
        return HASH_NOT_SUPPORTED
    return str(typestore().hash_rihs01(msgtype))
