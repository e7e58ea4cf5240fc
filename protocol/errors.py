"""The one exception every decoder in :mod:`protocol` raises."""

from __future__ import annotations


class ProtocolError(ValueError):
    """A message that cannot be accepted: malformed, over a limit, unauthenticated or replayed.

    The message is one precise line meant for a log; decoders never raise anything else.
    """
