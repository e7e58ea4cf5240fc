"""The attachment rmw_zenoh puts on every published sample, and reads from every one it takes.

33 bytes, little-endian: int64 sequence number, int64 source timestamp in nanoseconds, the
byte 16 (the GID's length) and a 16-byte GID (rmw_zenoh ``attachment_helpers.cpp``). A ROS 2
subscriber on rmw_zenoh drops a sample that carries none ("Unable to obtain attachment").
The GID only feeds lost-message tracking and ``message_info``, so any stable 16 bytes do.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from protocol.errors import ProtocolError

GID_LENGTH = 16
_HEAD = struct.Struct("<qqB")
SIZE = _HEAD.size + GID_LENGTH


@dataclass(frozen=True)
class Attachment:
    """One sample's attachment.

    Attributes
    ----------
    sequence : the publisher's message counter (starts at 1 in rmw_zenoh).
    timestamp_ns : source time of the sample, ns since the epoch.
    gid : the publisher's 16-byte global id.
    """

    sequence: int
    timestamp_ns: int
    gid: bytes

    def __post_init__(self) -> None:
        if len(self.gid) != GID_LENGTH:
            raise ValueError(f"a GID has {GID_LENGTH} bytes, got {len(self.gid)}")
        for name in ("sequence", "timestamp_ns"):
            if not -(2**63) <= getattr(self, name) < 2**63:
                raise ValueError(f"{name} must fit int64, got {getattr(self, name)}")


def encode_attachment(att: Attachment) -> bytes:
    """The 33 bytes of ``att``."""
    return _HEAD.pack(att.sequence, att.timestamp_ns, GID_LENGTH) + att.gid


def decode_attachment(data: bytes) -> Attachment:
    """Parse the 33 bytes of an rmw_zenoh attachment.

    Raises
    ------
    ProtocolError
        ``framing`` if the size is not 33 bytes; ``value`` if the GID length byte is not 16.
    """
    if len(data) != SIZE:
        raise ProtocolError(f"an rmw_zenoh attachment has {SIZE} bytes, got {len(data)}", "framing")
    sequence, timestamp_ns, gid_length = _HEAD.unpack_from(data)
    if gid_length != GID_LENGTH:
        raise ProtocolError(f"attachment GID length is {gid_length}, expected 16", "value")
    return Attachment(sequence, timestamp_ns, bytes(data[_HEAD.size :]))
