"""``refused(reason, match)``: ``pytest.raises(ProtocolError, match=...)`` that also checks why."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import pytest

from protocol import ProtocolError


@contextlib.contextmanager
def refused(reason: str, match: str) -> Iterator[pytest.ExceptionInfo[ProtocolError]]:
    """Expect a ProtocolError whose text matches ``match`` and whose category is ``reason``."""
    with pytest.raises(ProtocolError, match=match) as err:
        yield err
    assert err.value.reason == reason, (err.value.reason, str(err.value))
