"""ROS 2 topics over Zenoh: a robot's OccupancyGrid in, the merged map and its TF out.

A ROS 2 robot on rmw_zenoh already publishes every topic as a Zenoh key, so joining it to the
fleet needs no ROS code: :class:`RosMapSubscription` subscribes to its map topic the way a
ROS 2 subscriber on rmw_zenoh does, :class:`RosMapPublisher` publishes the global map and
TF and :class:`RosLinksPublisher` the links between robots' maps as RViz markers, the way a
ROS 2 publisher does (keys, attachment and liveliness tokens from :mod:`protocol.ros2`).
Robots still on DDS reach Zenoh through zenoh-bridge-ros2dds, whose keys are bare topic names
with no attachment and no tokens (``form="bridge"``).

Transient local: a map topic is latched in ROS 2 (slam_toolbox, map_server). rmw_zenoh keeps a
latched topic's last sample in a Zenoh advanced publisher's cache, which an advanced
subscriber with history queries on start; both sides here do the same. A token of the
subscription (``MS``) is declared because slam_toolbox publishes ``/map`` only while it counts
a subscriber, and on rmw_zenoh that count comes from these tokens.
"""

from __future__ import annotations

import itertools
import secrets
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import zenoh
import zenoh.ext

from pgvd.grid import Grid
from protocol.errors import ProtocolError
from protocol.ros2.attachment import Attachment, decode_attachment, encode_attachment
from protocol.ros2.keys import RosNode, data_key
from protocol.ros2.markers import LineList, encode_line_lists
from protocol.ros2.occupancy import (
    GridRefused,
    Placement,
    RosMap,
    decode_occupancy_grid,
    encode_occupancy_grid,
    encode_tf,
)
from protocol.ros2.types import MARKER_ARRAY, OCCUPANCY_GRID, TF_MESSAGE

#: Where the robots' placements go: latched, as tf2's StaticTransformBroadcaster sends.
TF_STATIC = "/tf_static"

#: ``on_drop(reason, detail)``: a sample was refused; reason is what was wrong with it:
#: ``type_hash``, ``attachment`` or one of :data:`protocol.ros2.occupancy.REFUSALS`.
DropFn = Callable[[str, str], None]


@dataclass(frozen=True)
class RosOptions:
    """How the agent appears on a ROS 2 network.

    Attributes
    ----------
    domain : ROS_DOMAIN_ID.
    distro : ``humble``, ``jazzy`` or ``kilted`` (the type-hash field of keys and tokens).
    form : ``rmw_zenoh`` (keys, attachment, tokens) or ``bridge`` (zenoh-bridge-ros2dds).
    node : node name the agent's tokens carry (:func:`agent_node_name` of its robot).
    namespace : the node's namespace, ``/`` or e.g. ``/robot1``.
    """

    domain: int = 0
    distro: str = "jazzy"
    form: str = "rmw_zenoh"
    node: str = "pgvd_agent"
    namespace: str = "/"

    def ros_node(self, session: zenoh.Session) -> RosNode:
        return RosNode(str(session.zid()), self.node, self.namespace, 0, self.domain)


def agent_node_name(robot: str) -> str:
    """The ROS 2 node name of ``robot``'s agent, ``pgvd_agent_<robot>``.

    One name per robot: agents sharing a ROS graph (robots' routers linked, a site router)
    would otherwise be one node name many times over, which ``ros2 node list`` flags and
    tools that address a node by name cannot tell apart. A robot id may hold ``-``, which a
    ROS name may not: it becomes ``_``.
    """
    return "pgvd_agent_" + robot.replace("-", "_")


def declare_node(session: zenoh.Session, opts: RosOptions) -> zenoh.LivelinessToken | None:
    """The agent's ROS 2 node token (``NN``), None for the bridge's key form (no tokens).

    One token for the node whatever it publishes or subscribes, declared before its
    entities' tokens and undeclared after them: rmw_zenoh's graph cache warns of a node
    removed before its publishers and subscriptions, on every ROS node, at each shutdown.

    Parameters
    ----------
    session : the agent's open Zenoh session.
    opts : domain, node name and namespace.
    """
    if opts.form != "rmw_zenoh":
        return None
    return session.liveliness().declare_token(opts.ros_node(session).token())


class RosMapSubscription:
    """The latest ``nav_msgs/msg/OccupancyGrid`` of one topic, and every refusal counted.

    Parameters
    ----------
    session : an open Zenoh session with timestamping enabled (advanced subscribers need it).
    topic : absolute topic name, e.g. ``/robot1/map``.
    opts : key form, domain, distro and node name.
    on_drop : called for every refused sample, from Zenoh's callback thread.
    entity_id : the subscription's id within the node (tokens must not collide).
    """

    def __init__(
        self,
        session: zenoh.Session,
        topic: str,
        opts: RosOptions,
        on_drop: DropFn,
        entity_id: int = 1,
    ) -> None:
        self.topic = topic
        self.opts = opts
        self._on_drop = on_drop
        self._lock = threading.Lock()
        self._latest: RosMap | None = None
        self._fresh = False
        self._expected = data_key(
            topic, OCCUPANCY_GRID, domain=opts.domain, distro=opts.distro, form=opts.form
        )
        # Any type and hash: a publisher of the wrong type or hash is counted, not ignored.
        watched = (
            self._expected if opts.form == "bridge" else (self._expected.rsplit("/", 2)[0] + "/*/*")
        )
        self._sub = zenoh.ext.declare_advanced_subscriber(
            session,
            watched,
            self._on_sample,
            history=zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=1),
        )
        self._token = None
        if opts.form == "rmw_zenoh":
            token = opts.ros_node(session).entity_token(
                "MS", entity_id, topic, OCCUPANCY_GRID, distro=opts.distro
            )
            self._token = session.liveliness().declare_token(token)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            ros = self._decode(str(sample.key_expr), sample.payload.to_bytes(), sample.attachment)
        except GridRefused as exc:
            self._on_drop(exc.what, str(exc))
            return
        with self._lock:
            self._latest, self._fresh = ros, True

    def _decode(self, key: str, payload: bytes, attachment: zenoh.ZBytes | None) -> RosMap:
        if key != self._expected:
            raise GridRefused(
                f"{self.topic}: sample on {key}, expected type and hash of {self._expected}",
                "schema",
                "type_hash",
            )
        if self.opts.form == "rmw_zenoh":
            # rmw_zenoh's own subscribers drop a sample without one ("Unable to obtain
            # attachment"): a publisher that sends none is not a ROS 2 publisher.
            if attachment is None:
                raise GridRefused(
                    f"{self.topic}: sample without an rmw_zenoh attachment", "framing", "attachment"
                )
            try:
                decode_attachment(attachment.to_bytes())
            except ProtocolError as exc:
                raise GridRefused(f"{self.topic}: {exc}", exc.reason, "attachment") from None
        return decode_occupancy_grid(payload)

    def take(self) -> RosMap | None:
        """The map received since the last call, or None."""
        with self._lock:
            fresh, self._fresh = self._fresh, False
            return self._latest if fresh else None

    def close(self) -> None:
        """Undeclare (an advanced subscriber left declared hangs the session's close)."""
        if self._token is not None:
            self._token.undeclare()
        self._sub.undeclare()


class _LatchedTopic:
    """One latched (transient local, depth 1) publisher of rmw_zenoh: key, token, attachment.

    rmw_zenoh numbers each publisher's messages on its own, from 1, under a GID of its own: a
    restarted agent is a new publisher, whose numbering from 1 again must not read as
    thousands of messages lost under the old one's GID.
    """

    def __init__(
        self, session: zenoh.Session, topic: str, msgtype: str, opts: RosOptions, entity_id: int
    ) -> None:
        self._form = opts.form
        self._seq, self._gid = itertools.count(1), secrets.token_bytes(16)
        key = data_key(topic, msgtype, domain=opts.domain, distro=opts.distro, form=opts.form)
        # a late subscriber's history query gets the last sample
        self._pub = zenoh.ext.declare_advanced_publisher(
            session, key, cache=zenoh.ext.CacheConfig(max_samples=1), publisher_detection=True
        )
        self._token = None
        if opts.form == "rmw_zenoh":
            token = opts.ros_node(session).entity_token(
                "MP", entity_id, topic, msgtype, distro=opts.distro
            )
            self._token = session.liveliness().declare_token(token)

    def put(self, cdr: bytes, stamp_ns: int) -> int:
        """Send ``cdr``, with rmw_zenoh's attachment; returns its size."""
        attachment = None
        if self._form == "rmw_zenoh":
            attachment = encode_attachment(Attachment(next(self._seq), stamp_ns, self._gid))
        self._pub.put(cdr, attachment=attachment)
        return len(cdr)

    def close(self) -> None:
        """Undeclare the token, then the publisher."""
        if self._token is not None:
            self._token.undeclare()
        self._pub.undeclare()


class RosMapPublisher:
    """Publishes a map as ``nav_msgs/msg/OccupancyGrid`` and placements on ``/tf_static``,
    both latched (transient local, depth 1).

    The node's own token is :func:`declare_node`'s; this declares its two publishers'.

    Parameters
    ----------
    session : an open Zenoh session with timestamping enabled.
    topic : e.g. ``/map_merged``.
    frame : the map's and TF's parent frame, e.g. ``world``.
    opts : key form, domain, distro and node name.
    """

    def __init__(self, session: zenoh.Session, topic: str, frame: str, opts: RosOptions) -> None:
        self.frame = frame
        self.opts = opts
        # a late tf2 listener gets the last placements, as a late map subscriber the last map
        self._map = _LatchedTopic(session, topic, OCCUPANCY_GRID, opts, 10)
        self._tf = _LatchedTopic(session, TF_STATIC, TF_MESSAGE, opts, 11)

    def publish(self, grid: Grid, placements: list[Placement], stamp_ns: int | None = None) -> int:
        """Publish ``grid`` and the TF of ``placements``; returns the map's bytes."""
        stamp_ns = time.time_ns() if stamp_ns is None else stamp_ns
        size = self.publish_map(grid, stamp_ns)
        self.publish_tf(placements, stamp_ns)
        return size

    def publish_map(self, grid: Grid, stamp_ns: int) -> int:
        """Publish ``grid`` on the latched map topic; returns its CDR bytes."""
        return self._map.put(encode_occupancy_grid(grid, self.frame, stamp_ns), stamp_ns)

    def publish_tf(self, placements: list[Placement], stamp_ns: int) -> int:
        """Publish ``placements`` on ``/tf_static`` (nothing if empty); returns the bytes sent.

        A placement moves only when the global map is rebuilt, so it is a static transform
        to tf2, sent again whole when it changes: a static transform holds at every time,
        where one on ``/tf`` sent at 1 Hz with the wall clock's stamp made tf2 refuse
        lookups at a sensor's newer stamp (it does not extrapolate) and every lookup under
        ``use_sim_time``. One message holds all the placements, as tf2's
        StaticTransformBroadcaster sends them, because the topic keeps only the last.
        """
        if not placements:
            return 0
        return self._tf.put(encode_tf(placements, stamp_ns), stamp_ns)

    def close(self) -> None:
        self._map.close()
        self._tf.close()


class RosLinksPublisher:
    """Publishes line lists as a latched ``visualization_msgs/msg/MarkerArray``.

    RViz's MarkerArray display draws them with no code; the agent sends one line list per
    link state (:mod:`agent.linkmarks`).

    Parameters
    ----------
    session : an open Zenoh session with timestamping enabled.
    topic : e.g. ``/map_merged_links``.
    frame : the frame of the lines' points, e.g. ``world``.
    opts : key form, domain, distro and node name.
    """

    def __init__(self, session: zenoh.Session, topic: str, frame: str, opts: RosOptions) -> None:
        self.frame = frame
        self._links = _LatchedTopic(session, topic, MARKER_ARRAY, opts, 12)

    def publish(self, lists: Sequence[LineList], stamp_ns: int) -> int:
        """Publish ``lists``, each list's markers replacing the last; returns the bytes sent."""
        return self._links.put(encode_line_lists(lists, self.frame, stamp_ns), stamp_ns)

    def close(self) -> None:
        self._links.close()
