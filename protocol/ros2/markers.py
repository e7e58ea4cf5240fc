"""``visualization_msgs/msg/MarkerArray`` of line lists: lines RViz draws with no code.

One ``LINE_LIST`` marker per :class:`LineList`, its namespace the list's name and its id 0, so
that each message replaces the whole of a namespace: a list with segments is added (or
modified), a list with none is deleted (RViz warns of a line list without points, and the
lines of a namespace that emptied must go). The lines lie in the plane ``z = LIFT`` of the
frame, above a map drawn at ``z = 0``, and last until replaced (``lifetime`` 0).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from protocol.ros2.occupancy import header
from protocol.ros2.types import MARKER_ARRAY, typestore

#: Height of the lines above the frame's plane, m: a map drawn at z = 0 does not hide them.
LIFT = 0.05

#: ``(x, y)`` in metres.
Point2 = tuple[float, float]
#: One line, between two points.
Segment = tuple[Point2, Point2]
#: The empty ``uint8[]`` of the texture and mesh fields, which a line list leaves unset.
_NO_BYTES = np.zeros(0, dtype=np.uint8)


@dataclass(frozen=True)
class LineList:
    """The lines of one namespace, in one colour.

    Attributes
    ----------
    ns : the marker's namespace, which RViz lists as a checkbox of its own.
    rgba : colour, each of red, green, blue and alpha in [0, 1].
    segments : the lines, each between two ``(x, y)`` points of the frame, metres.
    """

    ns: str
    rgba: tuple[float, float, float, float]
    segments: tuple[Segment, ...] = ()

    def __post_init__(self) -> None:
        if not self.ns:
            raise ValueError("a marker namespace must not be empty")
        if len(self.rgba) != 4 or not all(0.0 <= c <= 1.0 for c in self.rgba):
            raise ValueError(f"rgba must be four values in [0, 1], got {self.rgba}")
        coords = [c for seg in self.segments for point in seg for c in point]
        if len(coords) != 4 * len(self.segments) or not all(math.isfinite(c) for c in coords):
            raise ValueError(f"{self.ns}: each segment must be two finite (x, y) points")


def _marker(lines: LineList, frame_id: str, stamp_ns: int, width: float) -> Any:
    types = typestore().types
    marker = types["visualization_msgs/msg/Marker"]
    point = types["geometry_msgs/msg/Point"]
    red, green, blue, alpha = (float(c) for c in lines.rgba)
    return marker(
        header=header(frame_id, stamp_ns),
        ns=lines.ns,
        id=0,
        type=marker.LINE_LIST,
        action=marker.ADD if lines.segments else marker.DELETE,
        pose=types["geometry_msgs/msg/Pose"](
            position=point(x=0.0, y=0.0, z=0.0),
            # RViz refuses a marker whose orientation is not a unit quaternion
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        ),
        # a line list's width is scale.x; y and z are unused
        scale=types["geometry_msgs/msg/Vector3"](x=float(width), y=0.0, z=0.0),
        color=types["std_msgs/msg/ColorRGBA"](r=red, g=green, b=blue, a=alpha),
        lifetime=types["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False,
        points=[point(x=float(x), y=float(y), z=LIFT) for seg in lines.segments for (x, y) in seg],
        colors=[],
        texture_resource="",
        texture=types["sensor_msgs/msg/CompressedImage"](
            header=header("", 0), format="", data=_NO_BYTES
        ),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=types["visualization_msgs/msg/MeshFile"](filename="", data=_NO_BYTES),
        mesh_use_embedded_materials=False,
    )


def encode_line_lists(
    lists: Sequence[LineList], frame_id: str, stamp_ns: int, width: float = 0.2
) -> bytes:
    """CDR bytes (encapsulation header first) of a ``visualization_msgs/msg/MarkerArray``.

    Parameters
    ----------
    lists : one ``LINE_LIST`` marker each, in this order; namespaces must differ.
    frame_id : the frame of every point, e.g. ``world``.
    stamp_ns : ``header.stamp``, ns since the epoch.
    width : the lines' width, m (``scale.x``).

    Raises
    ------
    ValueError
        If two lists share a namespace or ``width`` is not > 0.
    """
    names = [lines.ns for lines in lists]
    if len(set(names)) != len(names):
        raise ValueError(f"marker namespaces must differ, got {names}")
    if not (math.isfinite(width) and width > 0):
        raise ValueError(f"line width must be > 0, got {width}")
    ts = typestore()
    msg = ts.types[MARKER_ARRAY](
        markers=[_marker(lines, frame_id, stamp_ns, width) for lines in lists]
    )
    return bytes(ts.serialize_cdr(msg, MARKER_ARRAY))
