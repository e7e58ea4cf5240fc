"""``nav_msgs/msg/OccupancyGrid`` <-> :class:`pgvd.grid.Grid`, and the TF that places maps.

OccupancyGrid cells are int8: -1 unknown, 0..100 the occupancy probability in percent.
Inbound, they take map_server's ``raw`` semantics (the same reader as a PGM in ``mode:
raw``): 0..100 spread linearly over [P_FREE, P_OCCUPIED], so that a SLAM's 0/100 cells
carry the same bounded confidence as a saved map rather than log-odds of +-infinity;
unknown stays exactly 0 log-odds. Outbound, the map is trinary, as map_server publishes a
map it loaded in ``mode: trinary`` and as slam_toolbox publishes its own: 100 where p > 0.65,
0 where p < 0.196, -1 elsewhere (p from eq. (9)). nav2's static layer reads exactly these
three values (a graded 90 would be free space below its lethal threshold of 100).

Row 0 of ``data`` is the map's lowest row (y up, REP 103); row 0 of a Grid is the top row of
the image, as in map_server files, so the rows are flipped both ways. ``info.origin`` is the
pose of cell (0, 0)'s outer corner: its yaw (from the quaternion, which must be a rotation
about z) becomes ``Grid.origin``'s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from pgvd.grid import Grid, probability_to_logodds
from pgvd.map_shades import FREE_THRESH, OCCUPIED_THRESH, shade_to_probability
from protocol.errors import ProtocolError
from protocol.limits import Limits
from protocol.ros2.types import OCCUPANCY_GRID, TF_MESSAGE, typestore


class GridRefused(ProtocolError):
    """An OccupancyGrid refused, with what in it was wrong (``what``) besides the reason.

    ``what`` is one of :data:`REFUSALS`, so that a ROS user's status tells a truncated
    message from a bad resolution, which the protocol's coarser ``reason`` does not.
    """

    def __init__(self, message: str, reason: str, what: str) -> None:
        super().__init__(message, reason)
        self.what = what

    def __reduce__(self) -> tuple[type, tuple[str, str, str]]:
        return type(self), (str(self), self.reason, self.what)


#: What :func:`decode_occupancy_grid` refuses: unparsable bytes, a size over the limits,
#: ``width * height != len(data)``, a resolution <= 0, a non-finite or tilted origin, a cell
#: outside -1..100.
REFUSALS = ("cdr", "limit", "size", "resolution", "origin", "cells")


@dataclass(frozen=True)
class RosMap:
    """One received OccupancyGrid.

    Attributes
    ----------
    grid : the map in log-odds, eq. (9), with the message's resolution and origin.
    frame_id : ``header.frame_id``.
    stamp_ns : ``header.stamp`` in nanoseconds.
    """

    grid: Grid
    frame_id: str
    stamp_ns: int


def _deserialize(cdr: bytes, msgtype: str, limits: Limits) -> Any:
    if len(cdr) > limits.max_cells + 4096:
        raise GridRefused(f"{msgtype} of {len(cdr)} bytes is over the cell limit", "limit", "limit")
    if len(cdr) < 4 or cdr[:2] not in (b"\x00\x01", b"\x00\x00"):
        raise GridRefused(f"{msgtype}: no CDR encapsulation header", "framing", "cdr")
    try:
        return typestore().deserialize_cdr(bytes(cdr), msgtype)
    # rosbags raises SerdeError on truncation, but hostile bytes reach struct, numpy and
    # the str decoder first (lengths, UTF-8): whatever it raises, the message is malformed.
    except Exception as exc:
        raise GridRefused(f"{msgtype}: CDR does not parse: {exc}", "framing", "cdr") from None


def _yaw(q: Any) -> float:
    """Yaw of a quaternion that must be a rotation about z (a 2-D map's origin)."""
    values = (q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in values):
        raise GridRefused("OccupancyGrid origin orientation is not finite", "value", "origin")
    norm = math.sqrt(sum(v * v for v in values))
    if not abs(norm - 1.0) < 1e-3 or abs(q.x) > 1e-6 or abs(q.y) > 1e-6:
        raise GridRefused(
            "OccupancyGrid origin orientation is not a unit rotation about z", "value", "origin"
        )
    return 2.0 * math.atan2(q.z, q.w)


def decode_occupancy_grid(cdr: bytes, limits: Limits | None = None) -> RosMap:
    """Decode the CDR bytes of a ``nav_msgs/msg/OccupancyGrid`` into a log-odds grid.

    Parameters
    ----------
    cdr : the sample's payload, 4-byte encapsulation header first.
    limits : the cell bound of :class:`~protocol.limits.Limits` applies.

    Returns
    -------
    RosMap

    Raises
    ------
    GridRefused
        A :class:`~protocol.errors.ProtocolError`: ``framing`` for bytes that do not parse as
        the type; ``limit`` past the cell bound; ``value`` for ``width * height !=
        len(data)``, a resolution <= 0 or not finite, a non-finite origin, or a cell outside
        -1..100. Its ``what`` (:data:`REFUSALS`) says which.
    """
    limits = limits or Limits()
    msg = _deserialize(cdr, OCCUPANCY_GRID, limits)
    info = msg.info
    width, height, data = int(info.width), int(info.height), np.asarray(msg.data)
    if width * height > limits.max_cells or max(width, height) > limits.max_side:
        raise GridRefused(
            f"OccupancyGrid of {width}x{height} cells is over the limit", "limit", "limit"
        )
    if width * height != data.size or data.size == 0:
        raise GridRefused(
            f"OccupancyGrid is {width}x{height} but carries {data.size} cells", "value", "size"
        )
    if not (math.isfinite(info.resolution) and info.resolution > 0):
        raise GridRefused(
            f"OccupancyGrid resolution must be > 0, got {info.resolution}", "value", "resolution"
        )
    position = info.origin.position
    if not all(math.isfinite(v) for v in (position.x, position.y, position.z)):
        raise GridRefused("OccupancyGrid origin is not finite", "value", "origin")
    yaw = _yaw(info.origin.orientation)
    cells = data.astype(np.int16).reshape(height, width)
    if cells.min() < -1 or cells.max() > 100:
        raise GridRefused(
            f"OccupancyGrid cells must be in -1..100, found {cells.min()}..{cells.max()}",
            "value",
            "cells",
        )
    # -1 becomes 255 as map_server's raw shade: beyond 100, hence unknown.
    shade = np.flipud(cells).astype(np.uint8)
    prob = shade_to_probability(shade, None, mode="raw")
    grid = Grid(
        probability_to_logodds(prob),
        float(info.resolution),
        (float(position.x), float(position.y), yaw),
    )
    stamp = msg.header.stamp
    return RosMap(grid, str(msg.header.frame_id), int(stamp.sec) * 10**9 + int(stamp.nanosec))


def _time(stamp_ns: int) -> Any:
    Time = typestore().types["builtin_interfaces/msg/Time"]
    return Time(sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9))


def header(frame_id: str, stamp_ns: int) -> Any:
    """A ``std_msgs/msg/Header`` (a ``rosbags`` message) of ``frame_id`` at ``stamp_ns``."""
    return typestore().types["std_msgs/msg/Header"](stamp=_time(stamp_ns), frame_id=frame_id)


def _quaternion(yaw: float) -> Any:
    Quaternion = typestore().types["geometry_msgs/msg/Quaternion"]
    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def occupancy_values(grid: Grid) -> np.ndarray:
    """OccupancyGrid ``data`` of ``grid``, trinary: 100 occupied, 0 free, -1 unknown."""
    prob = grid.probability()
    cells = np.full(grid.shape, -1, dtype=np.int8)
    cells[prob > OCCUPIED_THRESH] = 100
    cells[prob < FREE_THRESH] = 0
    return np.flipud(cells).ravel()


def encode_occupancy_grid(grid: Grid, frame_id: str, stamp_ns: int) -> bytes:
    """The CDR bytes (encapsulation header first) of ``grid`` as a ``nav_msgs/msg/OccupancyGrid``.

    Parameters
    ----------
    grid : a log-odds map, eq. (9).
    frame_id : ``header.frame_id``, e.g. ``world``.
    stamp_ns : ``header.stamp`` and ``info.map_load_time``, ns since the epoch.
    """
    ts = typestore()
    ox, oy, yaw = grid.origin
    Point = ts.types["geometry_msgs/msg/Point"]
    info = ts.types["nav_msgs/msg/MapMetaData"](
        map_load_time=_time(stamp_ns),
        resolution=float(grid.resolution),
        width=grid.shape[1],
        height=grid.shape[0],
        origin=ts.types["geometry_msgs/msg/Pose"](
            position=Point(x=float(ox), y=float(oy), z=0.0), orientation=_quaternion(yaw)
        ),
    )
    msg = ts.types[OCCUPANCY_GRID](
        header=header(frame_id, stamp_ns), info=info, data=occupancy_values(grid)
    )
    return bytes(ts.serialize_cdr(msg, OCCUPANCY_GRID))


def robot_map_frame(robot: str) -> str:
    """The TF frame of ``robot``'s own map (REP 105's ``map``, namespaced by robot)."""
    return f"{robot}/map"


@dataclass(frozen=True)
class Placement:
    """One transform of a TF tree: ``child`` frame's pose in ``parent``'s, metres/radians."""

    parent: str
    child: str
    x: float
    y: float
    yaw: float


def transform_stamped(placement: Placement, stamp_ns: int) -> Any:
    """``placement`` as a ``geometry_msgs/msg/TransformStamped`` (a ``rosbags`` message)."""
    types = typestore().types
    return types["geometry_msgs/msg/TransformStamped"](
        header=header(placement.parent, stamp_ns),
        child_frame_id=placement.child,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](
                x=float(placement.x), y=float(placement.y), z=0.0
            ),
            rotation=_quaternion(placement.yaw),
        ),
    )


def encode_tf(placements: list[Placement], stamp_ns: int) -> bytes:
    """CDR bytes of a ``tf2_msgs/msg/TFMessage`` of ``placements``, all stamped ``stamp_ns``."""
    ts = typestore()
    msg = ts.types[TF_MESSAGE](transforms=[transform_stamped(p, stamp_ns) for p in placements])
    return bytes(ts.serialize_cdr(msg, TF_MESSAGE))
