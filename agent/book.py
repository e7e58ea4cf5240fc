"""What one agent knows about its fleet: the latest local map of each robot and the links.

Shared between the thread that receives messages and the fusion worker, behind one lock;
readers take cheap snapshots (grids are immutable once stored). Whoever moves it forward wakes
the worker (:meth:`agent.worker.FusionWorker.wake`, on the core's ``Register`` action).
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from dataclasses import dataclass, field

from agent.links import EPOCH_SHIFT, LinkCache, LinkKey, LinkRecord, epoch_of, needed_key
from pgvd.grid import Grid

#: The minor part of a version (:func:`next_version`).
MINOR_MASK = (1 << EPOCH_SHIFT) - 1


def next_version(held: int | None, now: float, new_epoch: bool) -> int:
    """The version of a robot's next own map: ``epoch << 31 | minor``.

    A new registration epoch (:mod:`agent.links`) starts at ``max(now in s, previous
    epoch + 1)``; otherwise the minor part counts up.  Versions thus only move forward,
    and a robot whose state directory was lost starts an epoch newer than anything it
    published before (given a clock that did not jump back), so peers hear it again.
    """
    if held is None or new_epoch or (held & MINOR_MASK) == MINOR_MASK:
        epoch = int(now) if held is None else max(int(now), epoch_of(held) + 1)
        return epoch << EPOCH_SHIFT
    return held + 1


@dataclass(frozen=True)
class Snapshot:
    """A consistent view: ``maps`` ``{robot: (version, grid)}``, the links to use, settled;
    ``firsts`` ``{robot: first epoch}`` of the maps whose first epoch is known; ``finals``
    the robots whose map held is their source's last version."""

    maps: dict[str, tuple[int, Grid]]
    links: list[LinkRecord]
    settled: bool
    needed: list[LinkKey]
    alive: frozenset[str] | None
    firsts: dict[str, int] = field(default_factory=dict)
    #: The keys of ``needed`` whose link is held: candidates to check again at their pose.
    rechecks: frozenset[LinkKey] = frozenset()
    #: :attr:`agent.links.LinkRecord.identity` of ``links``, and of the accepted ones: what
    #: a worker's rebuilds and chains depend on, made once per change of the book.  A copy
    #: with other ``links`` (``dataclasses.replace``) keeps these of the book's links.
    link_ids: tuple[tuple[object, ...], ...] = ()
    accepted_ids: tuple[tuple[object, ...], ...] = ()
    #: The book's generation this snapshot lists: equal generations, equal maps, links used
    #: and keys needed (a worker reuses what it made of them).  None: not the book's.
    generation: int | None = None
    finals: frozenset[str] = frozenset()
    #: The accepted ones of the book's ``links`` (:meth:`accepted`).
    accepted_links: tuple[LinkRecord, ...] = ()
    #: The gated rejections of the book's ``links`` (:meth:`gated`).
    gated_links: tuple[LinkRecord, ...] = ()

    def accepted(self) -> tuple[LinkRecord, ...]:
        """The accepted links of ``links``: listed once per change of the book for its own
        snapshots (a worker's chains read them at each accepted link, some thousands of
        links held at 64 robots), picked out of ``links`` for any other."""
        if self.generation is None:
            return tuple(ln for ln in self.links if ln.accepted)
        return self.accepted_links

    def gated(self) -> tuple[LinkRecord, ...]:
        """The links of ``links`` the search gate gave (:attr:`LinkRecord.gated`), as
        :meth:`accepted` lists the accepted ones: a worker asks at each change of the book,
        and going over every link each time was a tenth of its CPU at 64 robots."""
        if self.generation is None:
            return tuple(ln for ln in self.links if ln.gated)
        return self.gated_links


@dataclass(frozen=True)
class _Listing:
    """What :meth:`FleetBook.snapshot` lists of the pairs, made once per change of the book."""

    generation: int
    links: list[LinkRecord]
    settled: bool
    needed: list[LinkKey]
    rechecks: frozenset[LinkKey]
    link_ids: tuple[tuple[object, ...], ...]
    accepted_ids: tuple[tuple[object, ...], ...]
    accepted: tuple[LinkRecord, ...]
    gated: tuple[LinkRecord, ...]


class _Pairs:
    """Per pair of the robots held: the link used (:func:`agent.links.select_links`) and the
    key needed (:func:`agent.links.needed_keys`), each pair updated when its robots' maps or
    its links change.

    A worker asks for both at every step, and every map version or link received moves
    the book: going over every pair each time cost each agent O(N^2) per message.
    """

    def __init__(self) -> None:
        self.used: dict[tuple[str, str], LinkRecord] = {}
        self.needed: dict[tuple[str, str], LinkKey] = {}
        #: Pairs without a link of their current epochs.
        self.unsettled: set[tuple[str, str]] = set()
        #: The keys needed whose link is held (a candidate to check again), by pair.
        self.rechecks: dict[tuple[str, str], LinkKey] = {}
        #: The index of every pair of the robots held, sorted; None when the robots changed.
        self._slot: dict[tuple[str, str], int] | None = {}
        #: By index: the link used, its identity, that identity and the link if the link is
        #: accepted, the link if the search gate gave it, and the key needed, None where
        #: there is none; :meth:`listing` drops the Nones.
        self._columns: tuple[list[object], ...] = ([], [], [], [], [], [])

    def refresh(self, a: str, b: str, versions: Mapping[str, int], cache: LinkCache) -> None:
        """Look ``(a, b)`` up again in ``cache`` (``a < b``, both in ``versions``)."""
        pair = (a, b)
        rec = cache.used_for(a, b, versions)
        if rec is None:
            self.used.pop(pair, None)
        else:
            self.used[pair] = rec
        if rec is None or not rec.current(versions):
            self.unsettled.add(pair)
        else:
            self.unsettled.discard(pair)
        key = needed_key(a, b, versions, cache)
        if key is None:
            self.needed.pop(pair, None)
        else:
            self.needed[pair] = key
        if key is not None and rec is not None and rec.key == key:
            self.rechecks[pair] = key
        else:
            self.rechecks.pop(pair, None)
        if self._slot is not None:
            self._fill(self._slot[pair], pair)

    def _fill(self, slot: int, pair: tuple[str, str]) -> None:
        """Write the columns of ``pair`` at ``slot``."""
        rec = self.used.get(pair)
        used, ids, accepted, accepted_links, gated, needed = self._columns
        used[slot] = rec
        ids[slot] = None if rec is None else rec.identity
        in_map = rec is not None and rec.accepted
        accepted[slot] = rec.identity if in_map else None
        accepted_links[slot] = rec if in_map else None
        gated[slot] = rec if rec is not None and rec.gated else None
        needed[slot] = self.needed.get(pair)

    def refresh_robot(self, robot: str, versions: Mapping[str, int], cache: LinkCache) -> None:
        """:meth:`refresh` every pair of ``robot``, whose map changed (or arrived)."""
        for other in versions:
            if other != robot:
                self.refresh(min(robot, other), max(robot, other), versions, cache)

    def robots_changed(self) -> None:
        """A robot joined: the pairs are placed anew at the next :meth:`listing`."""
        self._slot = None

    def drop(self, robot: str) -> None:
        """Forget every pair of ``robot``."""
        for table in (self.used, self.needed, self.rechecks):
            for pair in [p for p in table if robot in p]:
                del table[pair]
        self.unsettled = {p for p in self.unsettled if robot not in p}
        self._slot = None

    def listing(self, generation: int, robots: list[str]) -> _Listing:
        """The links used and the keys needed, by pair, and whether all are settled; of
        ``robots``, the robots held, sorted."""
        if self._slot is None:
            order = [(a, b) for i, a in enumerate(robots) for b in robots[i + 1 :]]
            self._slot = {p: i for i, p in enumerate(order)}
            self._columns = tuple([None] * len(order) for _ in range(len(self._columns)))
            for slot, pair in enumerate(order):
                self._fill(slot, pair)
        used, ids, accepted, accepted_links, gated, needed = (
            list(filter(None, c)) for c in self._columns
        )
        rechecks = frozenset(self.rechecks.values())
        return _Listing(
            generation,
            used,  # type: ignore[arg-type]
            # a candidate waiting for its re-check may still enter the map: not settled
            not self.unsettled and not needed,
            needed,  # type: ignore[arg-type]
            rechecks,
            tuple(ids),  # type: ignore[arg-type]
            tuple(accepted),  # type: ignore[arg-type]
            tuple(accepted_links),  # type: ignore[arg-type]
            tuple(gated),  # type: ignore[arg-type]
        )


class FleetBook:
    """Latest maps, each with its robot's first epoch when known and whether it is the
    robot's last, and link cache."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._maps: dict[str, tuple[int, Grid]] = {}
        self._firsts: dict[str, int] = {}
        self._finals: set[str] = set()
        self._links = LinkCache()
        self._pairs = _Pairs()
        self._alive: frozenset[str] | None = None
        #: Bumped whenever the maps or the links used change (:meth:`snapshot`).
        self._generation = 0
        #: What the last snapshot listed of the pairs (:meth:`snapshot`).
        self._listing: _Listing | None = None

    def set_alive(self, robots: set[str]) -> None:
        """The robots whose agents are up (liveliness), this one included."""
        with self._lock:
            self._alive = frozenset(robots)

    def version(self, robot: str) -> int | None:
        with self._lock:
            held = self._maps.get(robot)
            return None if held is None else held[0]

    def versions(self) -> dict[str, int]:
        with self._lock:
            return {r: v for r, (v, _) in self._maps.items()}

    def map_of(self, robot: str) -> tuple[int, Grid] | None:
        with self._lock:
            return self._maps.get(robot)

    def put_map(
        self,
        robot: str,
        version: int,
        grid: Grid,
        first_epoch: int | None = None,
        final: bool = False,
    ) -> bool:
        """Store ``grid`` if ``version`` is newer than what is held; True if stored.

        ``first_epoch`` is the epoch of the robot's first version, as the version's
        manifest said (None: unknown), and ``final`` whether the manifest marked the
        version the robot's last; both go with the version.
        """
        with self._lock:
            held = self._maps.get(robot)
            if held is not None and held[0] >= version:
                return False
            self._maps[robot] = (version, grid)
            if first_epoch is None:
                self._firsts.pop(robot, None)
            else:
                self._firsts[robot] = first_epoch
            if final:
                self._finals.add(robot)
            else:
                self._finals.discard(robot)
            versions = {r: v for r, (v, _) in self._maps.items()}
            self._links.prune(versions, robot)
            if held is None:
                self._pairs.robots_changed()
            self._pairs.refresh_robot(robot, versions, self._links)
            self._generation += 1
        return True

    def forget(self, robot: str) -> bool:
        """Drop ``robot``'s map and links; True if a map was held."""
        with self._lock:
            held = self._maps.pop(robot, None)
            self._firsts.pop(robot, None)
            self._finals.discard(robot)
            self._links.forget(robot)
            self._pairs.drop(robot)
            self._generation += 1
        return held is not None

    def add_link(self, rec: LinkRecord) -> bool:
        """Cache ``rec``; True if it is now the link used for its epochs."""
        with self._lock:
            if rec.key[1] < self._epoch(rec.a) or rec.key[3] < self._epoch(rec.b):
                return False  # superseded already: useless, and must not be re-chosen
            used = self._links.add(rec)
            # a candidate stored but not preferred leaves the links used as they were
            if used and rec.a in self._maps and rec.b in self._maps:
                versions = {r: self._maps[r][0] for r in rec.pair}
                self._pairs.refresh(rec.a, rec.b, versions, self._links)
            if used:
                self._generation += 1
            return used

    def _epoch(self, robot: str) -> int:
        """The epoch of ``robot``'s map held, -1 without one (lock held)."""
        held = self._maps.get(robot)
        return -1 if held is None else epoch_of(held[0])

    def link_candidates(self) -> list[LinkRecord]:
        """Every link held (all candidates), for persistence and peers' queries."""
        with self._lock:
            return self._links.candidates()

    def links(self) -> list[LinkRecord]:
        with self._lock:
            return self._links.records()

    def snapshot(self) -> Snapshot:
        """The maps, chosen links and the pairs still lacking a link of the latest versions."""
        with self._lock:
            # listed anew only when the book moved: a worker steps at every wake and poll
            held = self._listing
            if held is None or held.generation != self._generation:
                held = self._listing = self._pairs.listing(self._generation, sorted(self._maps))
            return Snapshot(
                dict(self._maps),
                # fresh lists: a snapshot's owner may change them
                list(held.links),
                held.settled,
                list(held.needed),
                self._alive,
                dict(self._firsts),
                held.rechecks,
                held.link_ids,
                held.accepted_ids,
                held.generation,
                frozenset(self._finals),
                held.accepted,
                held.gated,
            )
