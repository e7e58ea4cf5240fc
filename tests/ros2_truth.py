"""Intel segments as a SLAM node's ROS maps, and how far a received ``/tf`` is from the truth.

Shared by the fleet tests whose ROS 2 side is a test peer (tests/ros2_peer.py) or an outside
rmw_zenoh client (zenoh-ros2-sdk): both publish these maps and check the TF they get back.
"""

from __future__ import annotations

import math

import numpy as np
import ros2_peer

from agent.scenario import LOG
from pgvd.carmen import read_carmen
from pgvd.integrate import frame_for, integrate_scan, se2, select_segment

RESOLUTION = 0.1  # metres per cell, as slam_toolbox's default


def ros_map(segment: tuple[float, float], frame_deg: tuple[float, float, float]) -> dict:
    """An Intel segment mapped in ``frame_deg`` as a SLAM node would publish it.

    Returns
    -------
    dict
        ``cells`` (int8, ROS order: row 0 is the lowest row, -1/0/100), ``shape`` (h, w),
        ``origin`` (x, y of cell (0, 0)'s corner), ``world_to_map`` (the true 3x3 pose of the
        map frame) and ``cdr`` (the OccupancyGrid as tests/ros2_peer.py serializes it).
    """
    x, y, deg = frame_deg
    world_to_map = se2(x, y, math.radians(deg))
    scans = select_segment(read_carmen(LOG), segment)
    frame = frame_for(scans, RESOLUTION, world_to_map)
    logodds = frame.empty()
    for scan in scans:
        integrate_scan(logodds, scan, frame)
    prob = frame.grid(logodds).probability()
    cells = np.full(prob.shape, -1, dtype=np.int8)
    cells[prob > 0.65], cells[prob < 0.196] = 100, 0
    h, w = prob.shape
    ros_cells = np.flipud(cells).ravel()
    cdr = ros2_peer.grid_cdr(ros_cells, w, h, RESOLUTION, frame.origin)
    return {
        "cells": ros_cells,
        "cdr": cdr,
        "world_to_map": world_to_map,
        "shape": (h, w),
        "origin": frame.origin,
    }


def assert_tf_places_maps(tf_msg, maps: dict[str, dict], anchor: str) -> None:
    """Each ``<robot>/map`` of a TFMessage lies within 2 cells and 0.5 degree of the truth.

    ``tf_msg`` is any decoded ``tf2_msgs/msg/TFMessage`` (attribute access only); ``maps``
    are :func:`ros_map` results by robot; ``anchor`` is the robot whose map frame the merged
    (``world``) frame is. The cell error is the largest displacement of a map corner.
    """
    placed = {t.child_frame_id: t for t in tf_msg.transforms}
    assert sorted(placed) == sorted(f"{r}/map" for r in maps)
    world_to_anchor = maps[anchor]["world_to_map"]
    for robot, truth_map in maps.items():
        t = placed[f"{robot}/map"]
        assert t.header.frame_id == "world"
        q = t.transform.rotation
        yaw = 2.0 * math.atan2(q.z, q.w)
        got = se2(t.transform.translation.x, t.transform.translation.y, yaw)
        truth = world_to_anchor @ np.linalg.inv(truth_map["world_to_map"])
        deg = math.degrees(math.atan2(got[1, 0], got[0, 0]) - math.atan2(truth[1, 0], truth[0, 0]))
        assert abs((deg + 180.0) % 360.0 - 180.0) <= 0.5, (robot, deg)
        h, w = truth_map["shape"]
        ox, oy = truth_map["origin"]
        size_x, size_y = w * RESOLUTION, h * RESOLUTION
        corners = np.array(
            [[ox, oy, 1], [ox + size_x, oy, 1], [ox, oy + size_y, 1], [ox + size_x, oy + size_y, 1]]
        ).T
        cells = np.linalg.norm((got @ corners - truth @ corners)[:2], axis=0).max() / RESOLUTION
        assert cells <= 2.0, (robot, cells)


def one_global_map(statuses: dict[str, dict | None], robots: tuple[str, ...]) -> bool:
    """True when every agent is settled on one global map whose members are ``robots``."""
    return all(
        s and s["global"] and s["global"]["members"] == list(robots) and s["settled"]
        for s in statuses.values()
    )
