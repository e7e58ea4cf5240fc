"""The receive queue between Zenoh's callback threads and the agent's main thread.

Bounded by count AND by bytes: with only a count bound, a stalled main thread could hold
20 000 messages of 64 KB (1.3 GB). :meth:`Inbox.offer` never blocks, because Zenoh runs a
subscriber's callbacks one at a time: a blocked callback stalls every later sample. What does not
fit is refused and counted as an ``overload`` drop (:func:`offer_or_drop`).

A map message may come with its :class:`MapTag` (robot and version, read from its authenticated
header). Tiles of a version that a newer one of the same robot superseded are not worth decoding:
when a tile message or manifest of a newer version is offered, the older tiles still queued are
removed, and tiles of an older version than one queued are refused; both count as
``superseded`` drops. The receiver fetches what a delta then lacks (:mod:`agent.fetching`).
Nor is a message of the version already held (:func:`held_already`): every peer re-announces
its manifest, and at 16 robots nine in ten map messages are such repeats.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
from collections.abc import Callable
from dataclasses import dataclass

from agent.counters import Counters
from agent.keys import FleetKeys
from agent.wire import Inbound

#: Messages held at most (a flood of tiny messages is bounded by this).
MAX_ITEMS = 20_000
#: Bytes held at most, payloads and key strings plus :data:`ITEM_OVERHEAD` each.
MAX_BYTES = 64 << 20
#: What one queued entry costs beyond its payload and key: the tuple, the bytes and str
#: objects' headers (CPython: ~56 + 33 + 49 bytes) and the deque slot, rounded up.
ITEM_OVERHEAD = 160

Item = tuple[str, str, bytes]


@dataclass(frozen=True)
class MapTag:
    """What the inbox knows of a queued map message: whose, which version, tiles or manifest."""

    robot: str
    version: int
    tiles: bool


class Inbox:
    """A FIFO of ``(kind, key, payload)`` bounded by ``max_items`` and ``max_bytes``.

    Thread-safe for any number of producers and one consumer.
    """

    def __init__(self, max_items: int = MAX_ITEMS, max_bytes: int = MAX_BYTES) -> None:
        if max_items < 1 or max_bytes < 1:
            raise ValueError("an inbox needs room for at least one item and one byte")
        self.max_items, self.max_bytes = max_items, max_bytes
        self._items: deque[tuple[Item, int, MapTag | None]] = deque()
        self._bytes = 0
        self._versions: dict[str, Counter[int]] = {}  # robot -> version -> tagged items queued
        self._ready = threading.Condition(threading.Lock())

    @staticmethod
    def cost(item: Item) -> int:
        """Bytes ``item`` is charged while queued."""
        kind, key, data = item
        return len(kind) + len(key) + len(data) + ITEM_OVERHEAD

    def offer(self, item: Item, tag: MapTag | None = None) -> bool:
        """Queue ``item`` unless it would exceed a bound; never blocks. False if refused."""
        cost = self.cost(item)
        with self._ready:
            if len(self._items) >= self.max_items or self._bytes + cost > self.max_bytes:
                return False
            self._items.append((item, cost, tag))
            self._bytes += cost
            if tag is not None:
                self._versions.setdefault(tag.robot, Counter())[tag.version] += 1
            self._ready.notify()
        return True

    def supersede(self, tag: MapTag) -> tuple[int, bool]:
        """Remove the queued tiles of ``tag.robot`` older than ``tag.version``; their count,
        and whether the message ``tag`` stands for is itself superseded (tiles of an older
        version than one queued), so that it need not be queued."""
        with self._ready:
            queued = self._versions.get(tag.robot)
            if not queued:
                return 0, False
            stale = tag.tiles and max(queued) > tag.version
            if min(queued) >= tag.version:
                return 0, stale
            kept: deque[tuple[Item, int, MapTag | None]] = deque()
            removed = 0
            for entry in self._items:
                old = entry[2]
                if (
                    old is None
                    or old.robot != tag.robot
                    or old.version >= tag.version
                    or not old.tiles
                ):
                    kept.append(entry)
                    continue
                removed += 1
                self._forget(entry)
            self._items = kept
            return removed, stale

    def get(self, timeout: float) -> Item | None:
        """The oldest item, waiting up to ``timeout`` s for one; None if there is none."""
        got = self.get_tagged(timeout)
        return None if got is None else got[0]

    def get_tagged(self, timeout: float) -> tuple[Item, MapTag | None] | None:
        """The oldest item with the tag it was offered with, as :meth:`get`."""
        with self._ready:
            if not self._ready.wait_for(lambda: bool(self._items), timeout):
                return None
            entry = self._items.popleft()
            self._forget(entry)
        return entry[0], entry[2]

    def _forget(self, entry: tuple[Item, int, MapTag | None]) -> None:
        """Take a removed entry out of the accounting (the lock held)."""
        _, cost, tag = entry
        self._bytes -= cost
        if tag is not None:
            queued = self._versions[tag.robot]
            queued[tag.version] -= 1
            if not queued[tag.version]:
                del queued[tag.version]
            if not queued:
                del self._versions[tag.robot]

    def __len__(self) -> int:
        with self._ready:
            return len(self._items)

    @property
    def queued_bytes(self) -> int:
        with self._ready:
            return self._bytes


def map_tag(inbound: Inbound, keys: FleetKeys, key: str, data: bytes) -> MapTag | None:
    """The tag of ``data`` if it is an authentic map message that came under its own robot's
    key (as the core admits only those), else None: a stranger or a peer publishing for
    another robot can then remove no queued tiles but its own."""
    peeked = inbound.peek(data)
    if peeked is None or peeked[1] != keys.robot_of(key):
        return None
    tiles, robot, version = peeked
    return MapTag(robot, version, tiles)


def held_already(tag: MapTag | None, me: str, held: Callable[[str], int | None]) -> bool:
    """True for a peer's map message of the very version held of its robot (``held(robot)``):
    a re-announced manifest or a duplicate reply, which the core would decode only to find
    nothing new.  An older version is not: the core counts it as a ``stale_version`` drop."""
    return tag is not None and tag.robot != me and held(tag.robot) == tag.version


def offer_or_drop(inbox: Inbox, item: Item, counters: Counters, tag: MapTag | None = None) -> bool:
    """Queue ``item`` for the receiving thread, or count an ``overload`` drop; never blocks.

    With a ``tag``, the tiles it supersedes are dropped from the queue (or the item itself, if
    a newer version is queued), each counted as a ``superseded`` drop.
    """
    if tag is not None:
        removed, stale = inbox.supersede(tag)
        for _ in range(removed):
            counters.drop("superseded", tag.robot, f"tiles older than v{tag.version} queued")
        if stale:
            counters.drop("superseded", tag.robot, f"tiles of v{tag.version}: newer queued")
            return False
    if inbox.offer(item, tag):
        return True
    detail = f"receive queue full ({len(inbox)} messages, {inbox.queued_bytes} B)"
    counters.drop("overload", item[1], detail)
    return False
