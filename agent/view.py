"""A live view of the fleet for Foxglove or Lichtblick, through foxglove-sdk's WebSocket server.

Three channels, in the ROS conventions those viewers already render:

- ``/pgvd/global_map``: the global map as a ``foxglove.Grid`` of int8 occupancy (100 occupied,
  0 free, -1 unknown; rows from the map's lowest, as in a ROS OccupancyGrid), placed at the
  map's origin in the merged frame; pick the Grid's "map" colour mode;
- ``/tf``: ``foxglove.FrameTransforms`` from the merged frame to each robot's map frame;
- ``/pgvd/links``: JSON, one entry per link with its robots, score and lifecycle state
  (``accepted``, ``candidate``, ``confirmed``, ``rejected``, ``withdrawn``, with its margin
  and reason: :func:`agent.status.link_json`), so a candidate kept out of the map shows apart.

The server keeps no history, so :meth:`FoxgloveView.show` is called again at the view's rate:
a viewer that connects late sees the fleet on the next call.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from pgvd.grid import Grid
from protocol.ros2.occupancy import Placement, occupancy_values

GRID_TOPIC = "/pgvd/global_map"
TF_TOPIC = "/tf"
LINKS_TOPIC = "/pgvd/links"


def parse_endpoint(text: str) -> tuple[str, int]:
    """``HOST:PORT`` -> ``(host, port)``; ``ValueError`` with one line for anything else."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"expected HOST:PORT (e.g. 127.0.0.1:8765), got {text!r}")
    return host, int(port)


class FoxgloveView:
    """A foxglove-sdk WebSocket server with the fleet's channels, on a context of its own.

    Parameters
    ----------
    host, port : where to listen; port 0 picks a free one (see :attr:`port`).
    frame : the merged frame's id, as ``--ros-frame`` (ROS: ``world``).
    """

    def __init__(self, host: str, port: int, frame: str = "world") -> None:
        # foxglove-sdk is an extra: imported only by agents that serve a view.
        import foxglove
        from foxglove.channels import FrameTransformsChannel, GridChannel

        self.frame = frame
        self._context = foxglove.Context()
        self._server = foxglove.start_server(
            name="pgvd", host=host, port=port, context=self._context
        )
        self._grid = GridChannel(GRID_TOPIC, context=self._context)
        self._tf = FrameTransformsChannel(TF_TOPIC, context=self._context)
        self._links = foxglove.Channel(LINKS_TOPIC, message_encoding="json", context=self._context)

    @property
    def port(self) -> int:
        """The port the server listens on."""
        return int(self._server.port)

    def show(
        self,
        grid: Grid,
        placements: Sequence[Placement],
        links: Sequence[dict[str, Any]],
        stamp_ns: int,
    ) -> None:
        """Send the global map, each robot map frame's placement and the links' state."""
        from foxglove.messages import FrameTransforms

        self._grid.log(self._grid_message(grid, stamp_ns), log_time=stamp_ns)
        self._tf.log(
            FrameTransforms(transforms=[_transform(p, stamp_ns) for p in placements]),
            log_time=stamp_ns,
        )
        self._links.log({"links": list(links)}, log_time=stamp_ns)

    def _grid_message(self, grid: Grid, stamp_ns: int) -> Any:
        from foxglove.messages import Grid as FoxgloveGrid
        from foxglove.messages import (
            PackedElementField,
            PackedElementFieldNumericType,
            Pose,
            Vector2,
            Vector3,
        )

        ox, oy, yaw = grid.origin
        return FoxgloveGrid(
            timestamp=_timestamp(stamp_ns),
            frame_id=self.frame,
            pose=Pose(position=Vector3(x=ox, y=oy, z=0.0), orientation=_quaternion(yaw)),
            column_count=grid.shape[1],
            cell_size=Vector2(x=grid.resolution, y=grid.resolution),
            row_stride=grid.shape[1],
            cell_stride=1,
            fields=[
                PackedElementField(
                    name="occupancy", offset=0, type=PackedElementFieldNumericType.Int8
                )
            ],
            data=occupancy_values(grid).tobytes(),
        )

    def close(self) -> None:
        """Stop the server; connected viewers see it go."""
        self._server.stop()


def _timestamp(stamp_ns: int) -> Any:
    from foxglove.messages import Timestamp

    return Timestamp(sec=stamp_ns // 10**9, nsec=stamp_ns % 10**9)


def _quaternion(yaw: float) -> Any:
    from foxglove.messages import Quaternion

    return Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _transform(p: Placement, stamp_ns: int) -> Any:
    from foxglove.messages import FrameTransform, Vector3

    return FrameTransform(
        timestamp=_timestamp(stamp_ns),
        parent_frame_id=p.parent,
        child_frame_id=p.child,
        translation=Vector3(x=p.x, y=p.y, z=0.0),
        rotation=_quaternion(p.yaw),
    )
