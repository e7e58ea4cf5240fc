"""``refused(reason, match)``: ``pytest.raises(ProtocolError, match=...)`` that also checks why;
``refused_within(...)`` also bounds the memory the refusal may allocate."""

from __future__ import annotations

import contextlib
import tracemalloc
from collections.abc import Iterator

import pytest

from protocol import ProtocolError


@contextlib.contextmanager
def refused(reason: str, match: str) -> Iterator[pytest.ExceptionInfo[ProtocolError]]:
    """Expect a ProtocolError whose text matches ``match`` and whose category is ``reason``."""
    with pytest.raises(ProtocolError, match=match) as err:
        yield err
    assert err.value.reason == reason, (err.value.reason, str(err.value))


@contextlib.contextmanager
def refused_within(reason: str, match: str, max_bytes: int) -> Iterator[None]:
    """:func:`refused`, and the peak allocation while refusing stays under ``max_bytes``."""
    tracemalloc.start()
    try:
        with refused(reason, match):
            yield
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < max_bytes, f"refusing allocated {peak} bytes"
