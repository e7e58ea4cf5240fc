"""What the fleet core (:class:`agent.node.FleetNode`) asks its host to do.

The core decides; the host (:class:`agent.daemon.Agent` over Zenoh, or a test) carries the
actions out, in the order they come, and never decides anything itself. Each is a small frozen
record that a test can compare with ``==``.
"""

from __future__ import annotations

from dataclasses import dataclass

from agent.globalmap import Component
from agent.links import LinkRecord
from agent.state import StoredMap
from protocol.errors import REASONS

#: Why the core drops a message beyond what a decoder refused (:data:`protocol.errors.REASONS`):
#: ``foreign_fleet`` -- a message of another fleet on this fleet's keys;
#: ``unexpected_kind`` -- a message kind nobody publishes on the keys it came by;
#: ``key_mismatch`` -- a map message under another robot's key;
#: ``own_robot_id`` -- a peer publishes under this robot's id;
#: ``stale_version`` -- older than the version held;
#: ``bad_link`` -- a link that breaks the agent's rules (not rigid, bad covariance);
#: ``own_map_unencodable`` -- this robot's own map is beyond the wire's limits;
#: ``overload`` -- the receive queue is full (counted by :func:`agent.inbox.offer_or_drop`);
#: ``superseded`` -- queued tiles of a version a newer one superseded (:mod:`agent.inbox`).
RULE_REASONS = (
    "foreign_fleet",
    "unexpected_kind",
    "key_mismatch",
    "own_robot_id",
    "stale_version",
    "bad_link",
    "own_map_unencodable",
    "overload",
    "superseded",
)


@dataclass(frozen=True)
class Publish:
    """Put ``payload`` on ``key``; ``point`` names the failpoint reached once it is sent."""

    key: str
    payload: bytes
    point: str | None = None


@dataclass(frozen=True)
class Fetch:
    """Query ``selector`` (with selector ``parameters``) and feed every reply back as a message."""

    selector: str
    parameters: dict[str, str] | None = None


@dataclass(frozen=True)
class Reply:
    """Answer the query at hand with ``payload`` under ``key``, ``attachment`` alongside."""

    key: str
    payload: bytes
    attachment: bytes | None = None


@dataclass(frozen=True)
class PersistMap:
    """Write ``robot``'s map to the state directory; ``point`` names the failpoint mid-write.

    For this robot's own map, tell the core when it is on disk
    (:meth:`agent.node.FleetNode.on_persisted`): only then is it published.
    """

    robot: str
    stored: StoredMap
    point: str | None = None


@dataclass(frozen=True)
class PersistLinks:
    """Write every link held (all candidates) to the state directory."""

    records: tuple[LinkRecord, ...]


@dataclass(frozen=True)
class ForgetMap:
    """Delete ``robot``'s persisted map: the robot left long ago and is forgotten."""

    robot: str


@dataclass(frozen=True)
class PersistGlobal:
    """Write the global map of this robot's component (YAML, image and PNG) for people."""

    component: Component


@dataclass(frozen=True)
class WriteStatus:
    """Write the status (:meth:`agent.node.FleetNode.status`) now."""


@dataclass(frozen=True)
class Register:
    """The fleet's maps, links or members moved: the fusion worker has pairs to register or a
    global map to rebuild."""


@dataclass(frozen=True)
class Drop:
    """A message refused: count it under ``reason`` (logged once per reason and sender)."""

    reason: str
    sender: str
    detail: str

    def __post_init__(self) -> None:
        if self.reason not in REASONS + RULE_REASONS:
            raise ValueError(f"unknown drop reason {self.reason!r}")


#: Any action of the core.
Action = (
    Publish
    | Fetch
    | Reply
    | PersistMap
    | PersistLinks
    | ForgetMap
    | PersistGlobal
    | WriteStatus
    | Register
    | Drop
)
