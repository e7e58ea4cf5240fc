"""The one exception every decoder in :mod:`protocol` raises, with why it refused."""

from __future__ import annotations

#: What a refused message broke, for counting drops by reason:
#: ``framing`` -- the envelope: bytes, magic, truncation, trailer CRC, a stream that does not parse;
#: ``auth`` -- a missing, unexpected or wrong MAC;
#: ``schema`` -- schema version, flags, message kind, field count or field types;
#: ``limit`` -- a bound of :class:`~protocol.limits.Limits` (bytes, cells, side, tiles, id
#: length, decompressed size);
#: ``value`` -- a well-typed field with an impossible value: NaN/inf, out of range, shape vs
#: geometry, checksum mismatch, a tile that contradicts its manifest;
#: ``replay`` -- a version that does not move forward (:class:`~protocol.auth.ReplayGuard`).
REASONS = ("framing", "auth", "schema", "limit", "value", "replay")


class ProtocolError(ValueError):
    """A message that cannot be accepted: malformed, over a limit, unauthenticated or replayed.

    Parameters
    ----------
    message : one precise line meant for a log; decoders never raise anything else.
    reason : one of :data:`REASONS`, machine-readable (``exc.reason``).
    """

    def __init__(self, message: str, reason: str) -> None:
        if reason not in REASONS:
            raise ValueError(f"unknown ProtocolError reason {reason!r}, expected one of {REASONS}")
        super().__init__(message)
        self.reason = reason

    def __reduce__(self) -> tuple[type, tuple[str, str]]:
        # Exceptions pickle as cls(*args); args holds only the message.
        return type(self), (str(self), self.reason)
