"""Make the golden CDR files of tests/test_protocol_ros2.py with real rclpy (run once, by hand).

    python3 -m venv /tmp/rclpy && /tmp/rclpy/bin/pip install ros-rclpy ros-nav-msgs \
        ros-rmw-fastrtps-cpp
    /tmp/rclpy/bin/python tests/golden/ros2/make_golden.py

The registry's ROS 2 wheels (Kilted era) have nav_msgs and geometry_msgs but no tf2_msgs or
sensor_msgs, so TFMessage and LaserScan have no golden file; one TransformStamped (the
element of a TFMessage) stands in for TF. The messages are described by numbers only, so
this script shares no code with the project.
"""

from __future__ import annotations

import math
from pathlib import Path

from geometry_msgs.msg import TransformStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.serialization import serialize_message

HERE = Path(__file__).resolve().parent
STAMP = (1_700_000_000, 123_456_789)
WIDTH, HEIGHT = 7, 5
# Row 0 is the map's lowest row (REP 103): a wall along the bottom, free space, unknown top.
CELLS = [100] * 7 + [100, 0, 0, 0, 0, 0, 100] * 2 + [100, 0, 0, -1, 0, 0, 100] + [-1] * 7


def occupancy_grid() -> OccupancyGrid:
    msg = OccupancyGrid()
    msg.header.stamp.sec, msg.header.stamp.nanosec = STAMP
    msg.header.frame_id = "world"
    msg.info.map_load_time.sec, msg.info.map_load_time.nanosec = STAMP
    msg.info.resolution = 0.05
    msg.info.width, msg.info.height = WIDTH, HEIGHT
    msg.info.origin.position.x, msg.info.origin.position.y = 1.5, -2.25
    msg.info.origin.orientation.z = math.sin(0.15)
    msg.info.origin.orientation.w = math.cos(0.15)
    msg.data = CELLS
    return msg


def transform_stamped() -> TransformStamped:
    msg = TransformStamped()
    msg.header.stamp.sec, msg.header.stamp.nanosec = STAMP
    msg.header.frame_id = "world"
    msg.child_frame_id = "robot2/map"
    msg.transform.translation.x, msg.transform.translation.y = 3.0, -1.5
    msg.transform.rotation.z, msg.transform.rotation.w = math.sin(0.25), math.cos(0.25)
    return msg


if __name__ == "__main__":
    (HERE / "occupancy_grid.cdr").write_bytes(serialize_message(occupancy_grid()))
    (HERE / "transform_stamped.cdr").write_bytes(serialize_message(transform_stamped()))
