"""Laser scans with their poses from a ROS 2 bag (rosbag2, sqlite3 or MCAP), for ray casting.

The scans come from a ``sensor_msgs/msg/LaserScan`` topic. Each scan's pose is the laser
frame's pose in the root of the bag's TF tree at the scan's stamp: dynamic transforms from
``/tf`` (interpolated between their stamps, the way tf2 does), static ones from
``/tf_static``. A bag without TF to the laser may carry ``nav_msgs/msg/Odometry`` instead
(``/odom``): its pose of ``child_frame_id`` then stands in for the dynamic part.

A bag may instead hold a SLAM node's maps (``nav_msgs/msg/OccupancyGrid``, e.g. ``/map``):
:func:`read_rosbag_grids` gives their raw CDR with their bag times, for the caller to decode.

A ROS scan is turned into the CARMEN form :mod:`pgvd.integrate` casts (beams evenly spread
over a field of view centred on the pose's heading): the heading is turned by the middle of
``angle_min..angle_max``; NaN, infinite and below-``range_min`` ranges become "no return".
Reading bags needs ``rosbags`` (the ``ros2`` extra).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pgvd.carmen import LaserScan

SCAN = "sensor_msgs/msg/LaserScan"
GRID = "nav_msgs/msg/OccupancyGrid"
TF_TYPES = ("tf2_msgs/msg/TFMessage",)
ODOMETRY = "nav_msgs/msg/Odometry"


class BagFormatError(ValueError):
    """A bag that cannot give scans with poses; the message says which and why, in one line."""


@dataclass
class _Track:
    """One child frame's transforms from its parent: stamps (s) and (x, y, yaw) rows."""

    parent: str
    stamps: list[float] = field(default_factory=list)
    poses: list[tuple[float, float, float]] = field(default_factory=list)
    _t: np.ndarray = field(default_factory=lambda: np.empty(0))
    _p: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))

    def freeze(self) -> None:
        """Sort by stamp and unwrap the yaw once, before any lookup."""
        order = np.argsort(self.stamps, kind="stable")
        self._t = np.asarray(self.stamps)[order]
        self._p = np.asarray(self.poses, dtype=np.float64)[order]
        self._p[:, 2] = np.unwrap(self._p[:, 2])

    def at(self, t: float) -> tuple[float, float, float] | None:
        """The pose at ``t``, interpolated; None outside the recorded stamps (no extrapolation)."""
        if self._t.size == 1:  # a static transform
            return tuple(self._p[0])
        if not self._t[0] <= t <= self._t[-1]:
            return None
        return tuple(float(np.interp(t, self._t, self._p[:, k])) for k in range(3))


def _yaw(q: Any) -> float:
    # Planar yaw of a quaternion (ZYX convention), as tf2::getYaw.
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _compose(
    a: tuple[float, float, float], b: tuple[float, float, float]
) -> tuple[float, float, float]:
    """Pose ``b`` (given in frame ``a``) in ``a``'s parent frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def _stamp(header: Any) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


class _TfTree:
    """Dynamic and static transforms by child frame; a child has one parent (tf2's rule)."""

    def __init__(self) -> None:
        self.tracks: dict[str, _Track] = {}

    def add(self, parent: str, child: str, t: float, pose: tuple[float, float, float]) -> None:
        track = self.tracks.setdefault(child.lstrip("/"), _Track(parent.lstrip("/")))
        track.stamps.append(t)
        track.poses.append(pose)

    def freeze(self) -> None:
        for track in self.tracks.values():
            track.freeze()

    def lookup(self, frame: str, t: float) -> tuple[float, float, float] | None:
        """``frame``'s pose in the root of its tree at ``t``; None where TF does not reach."""
        pose = (0.0, 0.0, 0.0)
        seen = set()
        frame = frame.lstrip("/")
        while frame in self.tracks and frame not in seen:
            seen.add(frame)
            step = self.tracks[frame].at(t)
            if step is None:
                return None
            pose = _compose(step, pose)
            frame = self.tracks[frame].parent
        return pose if seen else None


def scan_from_ros(msg: Any, pose: tuple[float, float, float], t: float) -> LaserScan:
    """A ``sensor_msgs/msg/LaserScan`` taken at the laser ``pose`` as a castable CARMEN scan.

    Raises
    ------
    BagFormatError
        For a scan with no beams or a non-finite angle.
    """
    ranges = np.asarray(msg.ranges, dtype=np.float32).copy()
    n = ranges.size
    fov = float(msg.angle_increment) * max(n - 1, 0)
    middle = float(msg.angle_min) + fov / 2.0
    # finite angles can still overflow: a huge increment times the beams is inf
    if n == 0 or not (math.isfinite(fov) and math.isfinite(middle)):
        raise BagFormatError(f"scan at {t:.3f} s has no beams or a non-finite angle")
    if fov < 0:  # beams listed clockwise: CARMEN's are counter-clockwise
        ranges = ranges[::-1].copy()
    bad = ~np.isfinite(ranges) | (ranges < msg.range_min)
    ranges[bad] = np.inf  # no return: integrate drops ranges >= its no_return bound
    ranges[ranges > msg.range_max] = np.inf
    carmen_pose = np.array([pose[0], pose[1], pose[2] + middle])
    return LaserScan(
        timestamp=t, ranges=ranges, pose=carmen_pose, odom=carmen_pose.copy(), fov=abs(fov)
    )


def read_rosbag_scans(path: str | Path, topic: str | None = None) -> list[LaserScan]:
    """The scans of a rosbag2 with their poses, ready for :func:`pgvd.integrate.integrate`.

    Parameters
    ----------
    path : the bag's directory (or its ``.mcap``/``.db3`` file's directory).
    topic : the LaserScan topic; None takes the bag's only LaserScan topic.

    Returns
    -------
    Scans in time order, each with the laser's pose in the TF root frame; scans at stamps TF
    does not cover are skipped (tf2 does not extrapolate either).

    Raises
    ------
    BagFormatError
        No such bag, no or several LaserScan topics, no TF or odometry reaching the laser,
        or a message that does not decode.
    """
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_JAZZY)
    path = Path(path)
    reader = _open(path)
    try:
        scan_topic = _scan_topic(reader.connections, topic, path)
        tree, scans = _TfTree(), []
        wanted = [
            c
            for c in reader.connections
            if c.topic == scan_topic or c.msgtype in TF_TYPES or c.msgtype == ODOMETRY
        ]
        for conn, _, raw in reader.messages(connections=wanted):
            try:
                msg = store.deserialize_cdr(raw, conn.msgtype)
            except Exception as exc:
                raise BagFormatError(
                    f"{path}: a {conn.msgtype} on {conn.topic} does not decode: {exc}"
                ) from None
            if conn.topic == scan_topic:
                scans.append(msg)
            else:
                _add_transforms(tree, conn.msgtype, msg)
    finally:
        reader.close()
    return _place(scans, tree, path)


def _open(path: Path) -> Any:
    """An open rosbags ``Reader`` of ``path``; :class:`BagFormatError` if it cannot be."""
    from rosbags.rosbag2 import Reader

    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:
        raise BagFormatError(f"{path}: not a readable rosbag2: {exc}") from None
    return reader


def topic_types(path: str | Path) -> dict[str, str]:
    """Each topic a bag records -> its message type; :class:`BagFormatError` if unreadable."""
    reader = _open(Path(path))
    try:
        return {c.topic: c.msgtype for c in reader.connections}
    finally:
        reader.close()


def read_rosbag_grids(path: str | Path, topic: str) -> list[tuple[float, bytes]]:
    """The maps recorded on an OccupancyGrid ``topic``: (bag time in s, raw CDR), in order.

    They are left undecoded so that the caller refuses and counts a bad map as it does on a
    live topic (:func:`protocol.ros2.occupancy.decode_occupancy_grid`), and holds a long
    recording as int8 cells rather than as decoded grids.

    Raises
    ------
    BagFormatError
        No such bag, or ``topic`` is not an OccupancyGrid topic of it.
    """
    path = Path(path)
    reader = _open(path)
    try:
        conns = [c for c in reader.connections if c.topic == topic and c.msgtype == GRID]
        if not conns:
            grids = sorted({c.topic for c in reader.connections if c.msgtype == GRID})
            raise BagFormatError(f"{path}: no OccupancyGrid topic {topic} (has: {grids or 'none'})")
        return [(t_ns / 1e9, bytes(raw)) for _, t_ns, raw in reader.messages(connections=conns)]
    finally:
        reader.close()


def _scan_topic(connections: Iterable[Any], topic: str | None, path: Path) -> str:
    topics = sorted({c.topic for c in connections if c.msgtype == SCAN})
    if topic is not None:
        if topic not in topics:
            raise BagFormatError(f"{path}: no LaserScan topic {topic} (has: {topics or 'none'})")
        return topic
    if len(topics) != 1:
        raise BagFormatError(f"{path}: {len(topics)} LaserScan topics {topics}; name one")
    return topics[0]


def _add_transforms(tree: _TfTree, msgtype: str, msg: Any) -> None:
    if msgtype == ODOMETRY:
        p = msg.pose.pose
        tree.add(
            msg.header.frame_id,
            msg.child_frame_id,
            _stamp(msg.header),
            (p.position.x, p.position.y, _yaw(p.orientation)),
        )
        return
    for tf in msg.transforms:
        tr = tf.transform
        tree.add(
            tf.header.frame_id,
            tf.child_frame_id,
            _stamp(tf.header),
            (tr.translation.x, tr.translation.y, _yaw(tr.rotation)),
        )


def _place(scans: list[Any], tree: _TfTree, path: Path) -> list[LaserScan]:
    tree.freeze()
    out = []
    for msg in scans:
        t = _stamp(msg.header)
        pose = tree.lookup(msg.header.frame_id, t)
        if pose is not None:
            out.append(scan_from_ros(msg, pose, t))
    if scans and not out:
        raise BagFormatError(
            f"{path}: no scan's frame {scans[0].header.frame_id!r} is reached by TF or odometry"
        )
    out.sort(key=lambda s: s.timestamp)
    return out
