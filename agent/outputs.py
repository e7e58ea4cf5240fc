"""The global map out of the agent: to ROS 2 (OccupancyGrid, TF, link markers) and to a Foxglove
view.

What leaves is the component holding this agent's robot (:mod:`agent.globalmap`). Its merged
frame (``--ros-frame``, ROS: ``world``) is the metric frame of the component's anchor map, in
which the fused map's origin is expressed; each member robot's map frame ``<robot>/map`` is
placed in it from the component's pixel matrices and the maps' origins
(:func:`map_placements`). The map and the placements are published when they change, both
latched (nav2, a late RViz and tf2 listeners get them; the placements go on ``/tf_static``,
:meth:`agent.ros2_io.RosMapPublisher.publish_tf`); the view is sent again at the rate (a
viewer that connects late sees the fleet on the next send), and so are the links' markers
(:mod:`agent.linkmarks`), for RViz's MarkerArray display, volatile by default.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import zenoh

from agent.book import FleetBook
from agent.counters import Counters
from agent.globalmap import Component
from agent.linkmarks import link_line_lists, map_centres
from agent.ros2_io import RosLinksPublisher, RosMapPublisher, RosOptions
from agent.status import link_json
from pgvd.grid import Grid, map_frame_pose
from protocol.ros2.occupancy import Placement, robot_map_frame


@dataclass(frozen=True)
class OutputOptions:
    """Where the global map goes besides files; see :mod:`agent.cli.agent` for the flags.

    Attributes
    ----------
    ros : the ROS 2 network's domain, distro and key form (inputs and outputs alike).
    publish : the merged map topic (``--ros-publish``, e.g. ``/map_merged``), or None.
    frame : the merged frame's id (``--ros-frame``).
    rate : Hz at which a new global map is looked for and the view sent (``--ros-rate``;
        m-explore's ``merging_rate``).
    foxglove : ``(host, port)`` of the Foxglove WebSocket server, or None.
    links : the link markers' topic (``--ros-links``, e.g. ``/map_merged_links``), or None.
    """

    ros: RosOptions = field(default_factory=RosOptions)
    publish: str | None = None
    frame: str = "world"
    rate: float = 1.0
    foxglove: tuple[str, int] | None = None
    links: str | None = None

    @property
    def to_ros(self) -> bool:
        """True if anything is published on a ROS 2 topic."""
        return self.publish is not None or self.links is not None

    @property
    def active(self) -> bool:
        return self.to_ros or self.foxglove is not None


def map_placements(
    comp: Component, maps: Mapping[str, tuple[int, Grid]], frame: str
) -> list[Placement]:
    """Each member robot's map frame placed in the merged frame ``frame``.

    The merged frame is the anchor map's metric frame, so robot ``r``'s metric map frame
    reaches it through its pixels: :func:`pgvd.grid.map_frame_pose` of the component's ``r``
    pixel -> anchor pixel matrix, eqs. (1)-(2).

    Parameters
    ----------
    comp : the component whose global map is published.
    maps : ``{robot: (version, grid)}`` held now; a robot (or the anchor) whose map moved
        on since the component was built is left out until the next rebuild, as its pixel
        matrix belongs to the older map.

    Returns
    -------
    One :class:`Placement` per member, sorted by robot id.
    """
    anchor = maps.get(comp.anchor)
    if anchor is None or anchor[0] != comp.versions[comp.anchor]:
        return []
    out = []
    for robot in comp.members:
        held = maps.get(robot)
        if held is None or held[0] != comp.versions[robot]:
            continue
        x, y, yaw = map_frame_pose(anchor[1], held[1], comp.transforms[robot])
        out.append(Placement(frame, robot_map_frame(robot), x, y, yaw))
    return out


class Outputs:
    """Sends the global map and its links to ROS 2 and Foxglove, as :class:`OutputOptions` asks.

    Parameters
    ----------
    opts : what to serve.
    session : the agent's open Zenoh session (timestamping enabled) when publishing to ROS.
    counters : where the bytes sent to ROS are counted (``ros_map_bytes``, ``ros_tf_bytes``,
        ``ros_links_bytes``).
    """

    def __init__(
        self, opts: OutputOptions, session: zenoh.Session | None, counters: Counters
    ) -> None:
        self.opts = opts
        self.counters = counters
        self._digest: str | None = None
        self._placed = False
        self._placements: list[Placement] = []
        self._centres: dict[str, tuple[float, float]] = {}
        self._next = -math.inf
        self._ros: RosMapPublisher | None = None
        self._links: RosLinksPublisher | None = None
        self._view = None
        if opts.publish is not None:
            assert session is not None
            self._ros = RosMapPublisher(session, opts.publish, opts.frame, opts.ros)
        if opts.links is not None:
            assert session is not None
            self._links = RosLinksPublisher(session, opts.links, opts.frame, opts.ros)
        if opts.foxglove is not None:
            from agent.view import FoxgloveView

            self._view = FoxgloveView(*opts.foxglove, frame=opts.frame)

    def tick(self, now: float, comp: Component | None, book: FleetBook) -> None:
        """At the rate: publish ``comp``'s map and placements if they changed, send the links'
        markers and the view.

        ``now`` is monotonic seconds; ``book`` holds the maps and links of now.
        """
        if comp is None or now < self._next:
            return
        self._next = now + 1.0 / self.opts.rate
        stamp = time.time_ns()
        if comp.digest != self._digest:
            self._digest, self._placed = comp.digest, False
            if self._ros is not None:
                self.counters.add("ros_map_bytes", self._ros.publish_map(comp.grid, stamp))
                self.counters.add("ros_maps_published")
        if not self._placed:
            maps = {r: held for r in comp.members if (held := book.map_of(r)) is not None}
            placements = map_placements(comp, maps, self.opts.frame)
            # Until every member is placed (a map moved on since the rebuild), the previous
            # placements stand in: a robot missing from TF would vanish from RViz.
            self._placed = len(placements) == len(comp.members)
            if (self._placed or not self._placements) and placements != self._placements:
                self._placements = placements
                if self._ros is not None:
                    self.counters.add("ros_tf_bytes", self._ros.publish_tf(placements, stamp))
            if self._links is not None and (self._placed or not self._centres):
                self._centres = map_centres(comp, maps)
        if self._links is not None:
            # sent at every tick: RViz's marker display is volatile by default
            lines = link_line_lists(book.links(), book.versions(), self._centres)
            self.counters.add("ros_links_bytes", self._links.publish(lines, stamp))
        if self._view is not None:
            versions = book.versions()
            links = [link_json(rec, versions) for rec in book.links()]
            self._view.show(comp.grid, self._placements, links, stamp)

    def close(self) -> None:
        if self._ros is not None:
            self._ros.close()
        if self._links is not None:
            self._links.close()
        if self._view is not None:
            self._view.close()
