"""Where a ROS 2 topic lives in Zenoh's key space, for rmw_zenoh and for zenoh-bridge-ros2dds.

rmw_zenoh (the design document of the ros2/rmw_zenoh repository, and its
``liveliness_utils.cpp``):

- data: ``<domain>/<topic without the leading slash>/<DDS type name>/<type hash>``;
- liveliness, one token per entity:
  ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<MP|MS>/<enclave>/<namespace>/<node>``
  then ``/<topic>/<DDS type name>/<type hash>/<qos>``,
  where every ``/`` inside a field is written ``%`` and an empty namespace or enclave is ``%``.

zenoh-bridge-ros2dds keys a topic by its bare name (``/map`` -> ``map``) and sends no
attachment; robots still on DDS reach Zenoh that way.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from protocol.ros2.types import dds_type_name, type_hash

#: Key forms: rmw_zenoh's (the default) and zenoh-bridge-ros2dds's bare topic names.
FORMS = ("rmw_zenoh", "bridge")
#: A ROS 2 topic name: absolute, tokens of [A-Za-z0-9_] separated by single slashes
#: (design.ros2.org "Topic and Service name mapping"); ``~`` and substitutions are resolved
#: by the node before anything reaches the wire, so they are refused here.
_TOPIC = re.compile(r"/[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*")
#: rmw_zenoh's default QoS is reliable, volatile, keep-last 42; its token writes only what
#: differs. Transient-local depth 1 (``/map``'s latched profile) is therefore this:
QOS_TRANSIENT_LOCAL_1 = ":1:,1:,:,:,,"


def check_topic(topic: str) -> str:
    """Return ``topic`` if it is an absolute ROS 2 topic name, else raise ``ValueError``."""
    if not _TOPIC.fullmatch(topic):
        raise ValueError(f"not an absolute ROS 2 topic name: {topic!r} (expected e.g. /robot1/map)")
    return topic


def check_domain(domain: int) -> int:
    """Return ``domain`` if it is a ROS_DOMAIN_ID (0..232), else raise ``ValueError``."""
    if not 0 <= domain <= 232:
        raise ValueError(f"ROS domain id must be in 0..232, got {domain}")
    return domain


def data_key(
    topic: str, msgtype: str, *, domain: int = 0, distro: str = "jazzy", form: str = "rmw_zenoh"
) -> str:
    """The Zenoh key of ``topic``'s samples.

    Parameters
    ----------
    topic : absolute ROS 2 topic name, e.g. ``/robot1/map``.
    msgtype : ``pkg/msg/Name``.
    domain : ROS_DOMAIN_ID (rmw_zenoh only).
    distro : ``humble``, ``jazzy`` or ``kilted`` (rmw_zenoh only: the type-hash field).
    form : ``rmw_zenoh`` or ``bridge``.
    """
    bare = check_topic(topic)[1:]
    if form == "bridge":
        return bare
    if form != "rmw_zenoh":
        raise ValueError(f"unknown ROS key form {form!r}, expected one of {', '.join(FORMS)}")
    return f"{check_domain(domain)}/{bare}/{dds_type_name(msgtype)}/{type_hash(msgtype, distro)}"


def _mangle(name: str) -> str:
    """A name as one liveliness-token field: ``/`` -> ``%``, empty -> ``%``."""
    return name.replace("/", "%") or "%"


@dataclass(frozen=True)
class RosNode:
    """The node an agent appears as in the ROS 2 graph.

    Attributes
    ----------
    zid : the Zenoh session id, as ``str(session.zid())``.
    name : node name, e.g. ``pgvd_agent``.
    namespace : ``/`` or e.g. ``/robot1``.
    node_id : rmw_zenoh's per-context node counter.
    domain : ROS_DOMAIN_ID.
    """

    zid: str
    name: str
    namespace: str = "/"
    node_id: int = 0
    domain: int = 0

    def token(self) -> str:
        """The node's own ``NN`` liveliness token."""
        return f"{self._prefix(self.node_id, 'NN')}"

    def entity_token(
        self,
        kind: str,
        entity_id: int,
        topic: str,
        msgtype: str,
        *,
        distro: str = "jazzy",
        qos: str = QOS_TRANSIENT_LOCAL_1,
    ) -> str:
        """The liveliness token of a publisher (``MP``) or subscription (``MS``) of ``topic``."""
        if kind not in ("MP", "MS"):
            raise ValueError(f"entity kind must be MP or MS, got {kind!r}")
        return (
            f"{self._prefix(entity_id, kind)}/{_mangle(check_topic(topic))}/"
            f"{dds_type_name(msgtype)}/{type_hash(msgtype, distro)}/{qos}"
        )

    def _prefix(self, entity_id: int, kind: str) -> str:
        namespace = "" if self.namespace == "/" else self.namespace
        return (
            f"@ros2_lv/{self.domain}/{self.zid}/{self.node_id}/{entity_id}/{kind}/%/"
            f"{_mangle(namespace)}/{self.name}"
        )
