"""The receive queue between Zenoh's callback threads and the agent's main thread.

Bounded by count AND by bytes: with only a count bound, a stalled main thread could hold
20 000 messages of 64 KB (1.3 GB). :meth:`Inbox.offer` never blocks, because Zenoh runs a
subscriber's callbacks one at a time: a blocked callback stalls every later sample. What does not
fit is refused and counted as an ``overload`` drop (:func:`offer_or_drop`).
"""

from __future__ import annotations

import threading
from collections import deque

from agent.counters import Counters

#: Messages held at most (a flood of tiny messages is bounded by this).
MAX_ITEMS = 20_000
#: Bytes held at most, payloads and key strings plus :data:`ITEM_OVERHEAD` each.
MAX_BYTES = 64 << 20
#: What one queued entry costs beyond its payload and key: the tuple, the bytes and str
#: objects' headers (CPython: ~56 + 33 + 49 bytes) and the deque slot, rounded up.
ITEM_OVERHEAD = 160

Item = tuple[str, str, bytes]


class Inbox:
    """A FIFO of ``(kind, key, payload)`` bounded by ``max_items`` and ``max_bytes``.

    Thread-safe for any number of producers and one consumer.
    """

    def __init__(self, max_items: int = MAX_ITEMS, max_bytes: int = MAX_BYTES) -> None:
        if max_items < 1 or max_bytes < 1:
            raise ValueError("an inbox needs room for at least one item and one byte")
        self.max_items, self.max_bytes = max_items, max_bytes
        self._items: deque[tuple[Item, int]] = deque()
        self._bytes = 0
        self._ready = threading.Condition(threading.Lock())

    @staticmethod
    def cost(item: Item) -> int:
        """Bytes ``item`` is charged while queued."""
        kind, key, data = item
        return len(kind) + len(key) + len(data) + ITEM_OVERHEAD

    def offer(self, item: Item) -> bool:
        """Queue ``item`` unless it would exceed a bound; never blocks. False if refused."""
        cost = self.cost(item)
        with self._ready:
            if len(self._items) >= self.max_items or self._bytes + cost > self.max_bytes:
                return False
            self._items.append((item, cost))
            self._bytes += cost
            self._ready.notify()
        return True

    def get(self, timeout: float) -> Item | None:
        """The oldest item, waiting up to ``timeout`` s for one; None if there is none."""
        with self._ready:
            if not self._ready.wait_for(lambda: bool(self._items), timeout):
                return None
            item, cost = self._items.popleft()
            self._bytes -= cost
        return item

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)

    @property
    def queued_bytes(self) -> int:
        with self._ready:
            return self._bytes


def offer_or_drop(inbox: Inbox, item: Item, counters: Counters) -> bool:
    """Queue ``item`` for the main thread, or count an ``overload`` drop; never blocks."""
    if inbox.offer(item):
        return True
    detail = f"receive queue full ({len(inbox)} messages, {inbox.queued_bytes} B)"
    counters.drop("overload", item[1], detail)
    return False
