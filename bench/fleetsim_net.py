"""The fleet simulator's clock and network: a heap of timed events and a model of Zenoh.

No threads, sockets or sleeps: :class:`EventLoop` runs callbacks in simulated time order, and
:class:`Network` decides when (and whether) a message reaches each robot:

- a put fans out to every other robot present and reachable (Zenoh delivers a put to every
  subscriber of its key expression; every agent subscribes to the fleet's tiles, manifests
  and links), one copy per receiver;
- a query goes to its one target and each reply comes back the same way (request/reply);
- each copy waits for the sender's uplink, then takes ``latency`` plus a uniform jitter, then
  waits for the receiver's downlink: both links carry ``bandwidth`` bytes/s, first come
  first served, so a robot that receives a lot receives it late;
- it is lost with probability ``loss`` (best-effort), and dropped when sender and receiver
  are apart at sending or at arrival: one of them is offline (churn), or a partition in force
  puts them in different groups.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np


class EventLoop:
    """Callbacks at simulated times, run in time order (ties in the order they were set)."""

    def __init__(self) -> None:
        self.now = 0.0
        self._heap: list[tuple[float, int, Callable[..., None], tuple[object, ...]]] = []
        self._seq = itertools.count()

    def at(self, when: float, fn: Callable[..., None], *args: object) -> None:
        """Run ``fn(*args)`` at ``when`` (now, if ``when`` has passed)."""
        heapq.heappush(self._heap, (max(when, self.now), next(self._seq), fn, args))

    def run(self, until: float, stop: Callable[[], bool] = lambda: False) -> None:
        """Run events up to time ``until``, or until ``stop()`` is true after one."""
        while self._heap and self._heap[0][0] <= until:
            when, _, fn, args = heapq.heappop(self._heap)
            self.now = when
            fn(*args)
            if stop():
                return
        self.now = max(self.now, until)

    def __len__(self) -> int:
        return len(self._heap)


@dataclass(frozen=True)
class Partition:
    """From ``start`` to ``end`` s, only robots of one group hear each other.

    A robot in no group is cut off from every other.
    """

    start: float
    end: float
    groups: tuple[frozenset[str], ...]

    def apart(self, a: str, b: str, t: float) -> bool:
        """Whether the partition separates ``a`` and ``b`` at time ``t``."""
        if not self.start <= t < self.end:
            return False
        return not any(a in g and b in g for g in self.groups)


@dataclass(frozen=True)
class NetParams:
    """The network model (module docstring); times in s, bandwidth in bytes/s."""

    latency: float = 0.002
    jitter: float = 0.002
    loss: float = 0.0
    bandwidth: float = 12.5e6
    partitions: tuple[Partition, ...] = ()
    seed: int = 0

    def __post_init__(self) -> None:
        if min(self.latency, self.jitter) < 0 or not 0 <= self.loss < 1 or self.bandwidth <= 0:
            raise ValueError(
                "latency and jitter must be >= 0, loss in [0, 1), bandwidth > 0: "
                f"got {self.latency}, {self.jitter}, {self.loss}, {self.bandwidth}"
            )


#: ``deliver(receiver, key, payload)``, called at the arrival time.
Deliver = Callable[[str, str, bytes], None]
#: ``on_query(target, asker, selector)``, called when a query reaches its target.
OnQuery = Callable[[str, str, str], None]
#: What a copy's arrival calls: ``handler(sender, receiver, key, payload)``.
Handler = Callable[[str, str, str, bytes], None]


@dataclass
class Traffic:
    """What one robot's links carried: messages and bytes, each way."""

    sent_messages: int = 0
    sent_bytes: int = 0
    received_messages: int = 0
    received_bytes: int = 0
    lost: int = 0


@dataclass
class Network:
    """Robots' links over one :class:`EventLoop` (see the module docstring).

    ``online`` is who is connected now (churn edits it); ``deliver`` is called for each copy
    that arrives, ``on_query`` for each query's request.
    """

    loop: EventLoop
    params: NetParams
    deliver: Deliver
    on_query: OnQuery
    online: set[str] = field(default_factory=set)
    traffic: dict[str, Traffic] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.params.seed)
        self._up_free: dict[str, float] = {}
        self._down_free: dict[str, float] = {}

    def reachable(self, a: str, b: str, t: float) -> bool:
        """Whether ``a`` and ``b`` hear each other at ``t`` (both online, not partitioned)."""
        if a not in self.online or b not in self.online:
            return False
        return not any(p.apart(a, b, t) for p in self.params.partitions)

    def put(self, sender: str, key: str, payload: bytes, robots: Sequence[str]) -> None:
        """Fan ``payload`` out to every robot of ``robots`` but the sender."""
        self._count_sent(sender, payload)
        for receiver in robots:
            if receiver != sender:
                self._send(sender, receiver, key, payload, self._received)

    def reply(self, sender: str, receiver: str, key: str, payload: bytes) -> None:
        """A reply to ``receiver``'s query."""
        self._count_sent(sender, payload)
        self._send(sender, receiver, key, payload, self._received)

    def query(self, asker: str, target: str, selector: str) -> None:
        """Send ``selector`` to ``target``, whose answers come back by :meth:`reply`."""
        self._send(asker, target, selector, selector.encode(), self._asked)

    def _count_sent(self, sender: str, payload: bytes) -> None:
        out = self.traffic.setdefault(sender, Traffic())
        out.sent_messages += 1
        out.sent_bytes += len(payload)

    def _asked(self, asker: str, target: str, selector: str, payload: bytes) -> None:
        del payload  # the selector, as bytes on the wire
        self.on_query(target, asker, selector)

    def _send(self, sender: str, receiver: str, key: str, payload: bytes, handler: Handler) -> None:
        """One copy from ``sender`` to ``receiver``, queued, delayed, maybe lost."""
        now, size = self.loop.now, len(payload)
        if not self.reachable(sender, receiver, now):
            return
        if self.params.loss and self._rng.random() < self.params.loss:
            self.traffic.setdefault(sender, Traffic()).lost += 1
            return
        leaves = max(now, self._up_free.get(sender, 0.0)) + size / self.params.bandwidth
        self._up_free[sender] = leaves
        flight = self.params.latency + self.params.jitter * float(self._rng.random())
        self.loop.at(leaves + flight, self._arrive, sender, receiver, key, payload, handler)

    def _arrive(
        self, sender: str, receiver: str, key: str, payload: bytes, handler: Handler
    ) -> None:
        if not self.reachable(sender, receiver, self.loop.now):
            return
        free = max(self.loop.now, self._down_free.get(receiver, 0.0))
        done = self._down_free[receiver] = free + len(payload) / self.params.bandwidth
        self.loop.at(done, handler, sender, receiver, key, payload)

    def _received(self, sender: str, receiver: str, key: str, payload: bytes) -> None:
        del sender  # the key names it
        if receiver not in self.online:
            return
        got = self.traffic.setdefault(receiver, Traffic())
        got.received_messages += 1
        got.received_bytes += len(payload)
        self.deliver(receiver, key, payload)
