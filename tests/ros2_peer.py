"""A ROS 2 node on rmw_zenoh, as its documentation describes it, for tests: no project code.

Written from ros2/rmw_zenoh ``docs/design.md`` and its attachment and liveliness sources, with
``rosbags`` for CDR and type hashes and Zenoh's own API:

- data key ``<domain>/<topic without leading slash>/<pkg>::msg::dds_::<Name>_/<RIHS01 hash>``;
- a 33-byte attachment ``<q sequence><q timestamp ns><B 16><16-byte GID>`` on every sample;
- a latched (transient-local) publisher is an advanced publisher with a one-sample cache;
- liveliness tokens ``@ros2_lv/<domain>/<zid>/<nid>/<eid>/<MP|MS>/<enclave>/<ns>/<node>/...``.

:class:`BridgeRoute` is the other way a ROS 2 topic reaches Zenoh: a DDS robot's latched topic
as eclipse-zenoh/zenoh-plugin-ros2dds (zenoh-bridge-ros2dds) routes it, written from the
plugin's ``route_publisher.rs`` and ``ros2_name_to_key_expr``.
"""

from __future__ import annotations

import json
import struct
import time

import zenoh
import zenoh.ext
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
GRID = "nav_msgs/msg/OccupancyGrid"


def session(listen: str | None = None, connect: str | None = None) -> zenoh.Session:
    cfg = zenoh.Config()
    settings: dict[str, object] = {
        "mode": "peer",
        "scouting/multicast/enabled": False,
        "scouting/delay": 0,
        "timestamping/enabled": True,
    }
    if listen:
        settings["listen/endpoints"] = [listen]
    if connect:
        settings["connect/endpoints"] = [connect]
    for path, value in settings.items():
        cfg.insert_json5(path, json.dumps(value))
    return zenoh.open(cfg)


def key(topic: str, msgtype: str = GRID, domain: int = 0, type_hash: str | None = None) -> str:
    pkg, _, name = msgtype.split("/")
    return f"{domain}/{topic.lstrip('/')}/{pkg}::msg::dds_::{name}_/" + (
        type_hash or TS.hash_rihs01(msgtype)
    )


def attachment(seq: int) -> bytes:
    return struct.pack("<qqB", seq, time.time_ns(), 16) + b"rosnode-gid-0001"


def grid_cdr(
    cells,
    width: int,
    height: int,
    resolution: float,
    origin: tuple[float, float],
    frame_id: str = "map",
) -> bytes:
    """OccupancyGrid CDR; ``cells`` in ROS order (row 0 = lowest row), -1..100."""
    t = TS.types
    stamp = t["builtin_interfaces/msg/Time"](sec=1, nanosec=0)
    msg = t[GRID](
        header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=stamp,
            resolution=resolution,
            width=width,
            height=height,
            origin=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=origin[0], y=origin[1], z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            ),
        ),
        data=cells,
    )
    return bytes(TS.serialize_cdr(msg, GRID))


class LatchedPublisher:
    """slam_toolbox's ``/map``: transient local, depth 1, with its MP token."""

    def __init__(
        self, s: zenoh.Session, topic: str, type_hash: str | None = None, domain: int = 0
    ) -> None:
        self.key = key(topic, type_hash=type_hash, domain=domain)
        self.pub = zenoh.ext.declare_advanced_publisher(
            s, self.key, cache=zenoh.ext.CacheConfig(max_samples=1), publisher_detection=True
        )
        self.seq = 0
        mangled = topic.replace("/", "%")
        type_field = self.key.split("/")[-1]
        self.token = s.liveliness().declare_token(
            f"@ros2_lv/{domain}/{s.zid()}/0/10/MP/%/%/slam_toolbox/{mangled}/"
            f"nav_msgs::msg::dds_::OccupancyGrid_/{type_field}/:1:,1:,:,:,,"
        )

    def put(self, cdr: bytes, with_attachment: bool = True) -> None:
        self.seq += 1
        self.pub.put(cdr, attachment=attachment(self.seq) if with_attachment else None)

    def close(self) -> None:
        self.token.undeclare()
        self.pub.undeclare()


def latched_subscriber(s: zenoh.Session, data_key: str, callback) -> zenoh.ext.AdvancedSubscriber:
    """A transient-local subscription: an advanced subscriber that queries publishers' caches."""
    return zenoh.ext.declare_advanced_subscriber(
        s,
        data_key,
        callback,
        history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
    )


class BridgeRoute:
    """zenoh-bridge-ros2dds routing a DDS robot's transient-local topic to Zenoh.

    The key is the bare topic name (``/robot1/map`` -> ``robot1/map``, with no namespace
    configured); the publisher is an advanced one with a cache (the DDS reader's history depth
    times ``transient_local_cache_multiplier``, 10 by default) and publisher detection, so a
    late subscriber's history query gets the latched sample; each DDS sample is put as its
    CDR bytes, header included, with no attachment.
    """

    def __init__(self, s: zenoh.Session, topic: str, depth: int = 1) -> None:
        self.key = topic.lstrip("/")
        self.pub = zenoh.ext.declare_advanced_publisher(
            s,
            self.key,
            cache=zenoh.ext.CacheConfig(max_samples=depth * 10),
            publisher_detection=True,
        )

    def put(self, cdr: bytes) -> None:
        self.pub.put(cdr)

    def close(self) -> None:
        self.pub.undeclare()
