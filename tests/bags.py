"""Write a rosbag2 from a CARMEN log, as a robot's recording would hold it (tests only).

``/scan`` (sensor_msgs/LaserScan, frame ``laser``), ``/tf`` (odom -> base_link at each scan;
or instead ``/odom``, nav_msgs/Odometry of base_link in odom, as a bag without TF records it),
``/tf_static`` (base_link -> laser, 0.12 m ahead of the base). Written with rosbags' Writer
and messages built from its type store, so the reader under test shares no code with it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

TS = get_typestore(Stores.ROS2_JAZZY)
T = TS.types
LASER_AHEAD = 0.12


def _header(t: float, frame: str):
    sec = int(t)
    return T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=round((t - sec) * 1e9)),
        frame_id=frame,
    )


def _tf(t: float, parent: str, child: str, x: float, y: float, yaw: float):
    return T["geometry_msgs/msg/TransformStamped"](
        header=_header(t, parent),
        child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=x, y=y, z=0.0),
            rotation=T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
            ),
        ),
    )


def _odometry(t: float, x: float, y: float, yaw: float):
    """base_link's pose in odom, as a wheel-odometry node publishes it on ``/odom``."""
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=T["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)
        ),
    )
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return T["nav_msgs/msg/Odometry"](
        header=_header(t, "odom"),
        child_frame_id="base_link",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](
            twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
            covariance=np.zeros(36),
        ),
    )


def write_scan_bag(path: Path, scans, storage: str = "mcap", odometry: bool = False) -> None:
    """``scans``: CARMEN scans (180 deg, ``pose`` = the laser's pose in the log's frame).

    ``odometry`` records the base's motion as ``/odom`` Odometry instead of ``/tf``.
    """
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    motion = ("/odom", "nav_msgs/msg/Odometry") if odometry else ("/tf", "tf2_msgs/msg/TFMessage")
    with Writer(path, version=9, storage_plugin=plugin) as writer:
        conns = {
            topic: writer.add_connection(topic, msgtype, typestore=TS)
            for topic, msgtype in [
                ("/scan", "sensor_msgs/msg/LaserScan"),
                motion,
                ("/tf_static", "tf2_msgs/msg/TFMessage"),
            ]
        }

        def write(topic: str, t: float, msg) -> None:
            writer.write(conns[topic], int(t * 1e9), TS.serialize_cdr(msg, conns[topic].msgtype))

        t0 = scans[0].timestamp
        write(
            "/tf_static",
            t0,
            T["tf2_msgs/msg/TFMessage"](
                transforms=[_tf(t0, "base_link", "laser", LASER_AHEAD, 0.0, 0.0)]
            ),
        )
        for scan in scans:
            x, y, th = scan.pose
            base = (x - LASER_AHEAD * math.cos(th), y - LASER_AHEAD * math.sin(th), th)
            if odometry:
                write("/odom", scan.timestamp, _odometry(scan.timestamp, *base))
            else:
                write(
                    "/tf",
                    scan.timestamp,
                    T["tf2_msgs/msg/TFMessage"](
                        transforms=[_tf(scan.timestamp, "odom", "base_link", *base)]
                    ),
                )
            n = scan.ranges.size
            write(
                "/scan",
                scan.timestamp,
                T["sensor_msgs/msg/LaserScan"](
                    header=_header(scan.timestamp, "laser"),
                    angle_min=-scan.fov / 2,
                    angle_max=scan.fov / 2,
                    angle_increment=scan.fov / (n - 1),
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=0.0,
                    range_max=81.0,
                    ranges=np.asarray(scan.ranges, dtype=np.float32),
                    intensities=np.zeros(0, dtype=np.float32),
                ),
            )


def write_grid_bag(path: Path, maps: list[tuple[float, bytes]], topic: str = "/map") -> None:
    """A SLAM node's recorded maps: ``(bag time in s, OccupancyGrid CDR)`` on ``topic``."""
    with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(topic, "nav_msgs/msg/OccupancyGrid", typestore=TS)
        for t, cdr in maps:
            writer.write(conn, int(t * 1e9), cdr)
