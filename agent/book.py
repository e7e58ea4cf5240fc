"""What one agent knows about its fleet: the latest local map of each robot and the links.

Shared between the thread that receives messages and the fusion worker, behind one lock;
readers take cheap snapshots (grids are immutable once stored). Whoever moves it forward wakes
the worker (:meth:`agent.worker.FusionWorker.wake`, on the core's ``Register`` action).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from agent.links import (
    EPOCH_SHIFT,
    LinkCache,
    LinkKey,
    LinkRecord,
    epoch_of,
    needed_keys,
    select_links,
)
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
    ``firsts`` ``{robot: first epoch}`` of the maps whose first epoch is known."""

    maps: dict[str, tuple[int, Grid]]
    links: list[LinkRecord]
    settled: bool
    needed: list[LinkKey]
    alive: frozenset[str] | None
    firsts: dict[str, int] = field(default_factory=dict)


class FleetBook:
    """Latest maps, each with its robot's first epoch when known, and link cache."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._maps: dict[str, tuple[int, Grid]] = {}
        self._firsts: dict[str, int] = {}
        self._links = LinkCache()
        self._alive: frozenset[str] | None = None

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

    def put_map(self, robot: str, version: int, grid: Grid, first_epoch: int | None = None) -> bool:
        """Store ``grid`` if ``version`` is newer than what is held; True if stored.

        ``first_epoch`` is the epoch of the robot's first version, as the version's
        manifest said (None: unknown); it goes with the version.
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
            self._links.prune({r: v for r, (v, _) in self._maps.items()})
        return True

    def forget(self, robot: str) -> bool:
        """Drop ``robot``'s map and links; True if a map was held."""
        with self._lock:
            held = self._maps.pop(robot, None)
            self._firsts.pop(robot, None)
            self._links.forget(robot)
        return held is not None

    def add_link(self, rec: LinkRecord) -> bool:
        """Cache ``rec``; True if it is now the link used for its epochs."""
        with self._lock:
            held = {r: epoch_of(v) for r, (v, _) in self._maps.items()}
            if rec.key[1] < held.get(rec.a, -1) or rec.key[3] < held.get(rec.b, -1):
                return False  # superseded already: useless, and must not be re-chosen
            return self._links.add(rec)

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
            maps = dict(self._maps)
            versions = {r: v for r, (v, _) in maps.items()}
            chosen, settled = select_links(versions, self._links)
            needed = needed_keys(versions, self._links)
            # a candidate waiting for its re-check may still enter the map: not settled
            firsts = dict(self._firsts)
            return Snapshot(maps, chosen, settled and not needed, needed, self._alive, firsts)
