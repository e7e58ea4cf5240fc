"""Optional fleet key (HMAC-SHA256) and replay protection, both sans-I/O.

Without a key a message ends in a CRC-32, which catches corruption but not
forgery; with a key it ends in an HMAC-SHA256 over everything before it, so
only holders of the fleet key can produce a message a keyed receiver accepts.
:class:`ReplayGuard` then refuses any message whose version does not move
forward, so a recorded old message cannot roll a receiver back.
"""

from __future__ import annotations

import hashlib
import hmac
import zlib

from protocol.errors import ProtocolError
from protocol.messages import Heartbeat, Link, Manifest, MapTiles, Message, Status

MAC_BYTES = 32
CRC_BYTES = 4


def check_key(key: object) -> bytes | None:
    """Return ``key`` if it is None or non-empty bytes, else raise ProtocolError."""
    if key is None:
        return None
    if not isinstance(key, (bytes, bytearray)) or not key:
        raise ProtocolError("a fleet key must be non-empty bytes", reason="value")
    return bytes(key)


def seal(data: bytes, key: bytes | None) -> bytes:
    """The trailer for ``data``: its HMAC-SHA256 under ``key``, or its CRC-32 without one."""
    if key is None:
        return zlib.crc32(data).to_bytes(CRC_BYTES, "big")
    return hmac.new(key, data, hashlib.sha256).digest()


def unseal(data: bytes, keyed: bool, key: bytes | None) -> bytes:
    """Check the trailer of ``data`` and return what it covers.

    ``keyed`` is the sender's flag saying a MAC (not a CRC) ends the message.

    Raises
    ------
    ProtocolError
        If the MAC presence does not match the configured key, the message is
        too short to hold its trailer, or the trailer does not match.
    """
    if key is not None and not keyed:
        raise ProtocolError("message carries no MAC but a fleet key is configured", reason="auth")
    if key is None and keyed:
        raise ProtocolError("message carries a MAC but no fleet key is configured", reason="auth")
    size = MAC_BYTES if keyed else CRC_BYTES
    if len(data) < size:
        raise ProtocolError("truncated message: trailer incomplete", reason="framing")
    covered, trailer = data[:-size], data[-size:]
    if not hmac.compare_digest(seal(covered, key), trailer):
        raise ProtocolError(
            "wrong MAC" if keyed else "corrupted message: CRC mismatch",
            reason="auth" if keyed else "framing",
        )
    return covered


def replay_keys(msg: Message) -> list[tuple[tuple[str, ...], tuple[int, ...]]]:
    """The (key, version) pairs by which :class:`ReplayGuard` orders ``msg``.

    A MapTiles message is ordered per tile (many messages share one map
    version); full and delta tiles, and full and delta manifests, are ordered
    separately so that a receiver that could not apply a delta can still
    fetch the same version in full.
    A Link is ordered by its pair of map versions, which both only grow.
    """
    if isinstance(msg, MapTiles):
        return [
            ((msg.robot, "tiles", str(t.index), "delta" if t.is_delta else "full"), (msg.version,))
            for t in msg.tiles
        ]
    if isinstance(msg, Manifest):
        return [((msg.robot, "manifest", "delta" if msg.is_delta else "full"), (msg.version,))]
    if isinstance(msg, Link):
        pair = (msg.decided_by, "link", msg.robot_a, msg.robot_b)
        return [(pair, (msg.version_a, msg.version_b))]
    if isinstance(msg, (Heartbeat, Status)):
        return [((msg.robot, type(msg).__name__.lower()), (msg.seq,))]
    raise ProtocolError(f"no replay rule for {type(msg).__name__}", reason="schema")


def _forward(new: tuple[int, ...], old: tuple[int, ...]) -> bool:
    """True when no component of ``new`` is older and at least one is newer."""
    return all(n >= o for n, o in zip(new, old, strict=True)) and new != old


class ReplayGuard:
    """Refuses messages whose version does not move forward per (robot, kind).

    Stateful but sans-I/O: :meth:`admit` either records the message's versions
    or raises.  Call it after a message was decoded and authenticated, and
    persist :attr:`state` across restarts if replays across restarts matter.
    """

    def __init__(self, state: dict[tuple[str, ...], tuple[int, ...]] | None = None) -> None:
        self.state: dict[tuple[str, ...], tuple[int, ...]] = dict(state or {})

    def check(self, msg: Message) -> None:
        """Raise ProtocolError if ``msg`` is a replay; record nothing."""
        for key, version in replay_keys(msg):
            last = self.state.get(key)
            if last is not None and not _forward(version, last):
                raise ProtocolError(
                    f"replayed {key[1]} from {key[0]}: version {_fmt(version)} "
                    f"is not newer than {_fmt(last)}",
                    reason="replay",
                )

    def admit(self, msg: Message) -> None:
        """Check ``msg`` and, if it is not a replay, record its versions."""
        self.check(msg)
        for key, version in replay_keys(msg):
            self.state[key] = version


def _fmt(version: tuple[int, ...]) -> str:
    return "/".join(str(v) for v in version)
