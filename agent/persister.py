"""Writing the state directory on a thread of its own, so that no receiving thread waits for a disk.

At 16 robots, writing every peer version received (a ``.npz`` of a few MB each) on the thread
that drains the inbox made it fall seconds behind. The :class:`Persister` takes the core's
persistence actions without blocking and writes them in this order:

1. the robot's own versions, one by one, each fsynced, and never coalesced: the core publishes
   a version only once it is durable (fleet invariant 4), so :meth:`Persister.save_map` reports
   each one back (``on_saved``) after it is on disk;
2. peers' maps, newest only: a peer version that a newer one superseded before it was written
   is not written at all (a restarted agent fetches a peer's latest anyway), and forgetting a
   robot cancels its pending write;
3. the links, the last set only.

What is pending is bounded by the robots held, not by the versions received. :meth:`close`
writes everything still pending, so a clean shutdown loses nothing.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from functools import partial

from agent.counters import Counters
from agent.links import LinkRecord
from agent.state import StateDir, StoredMap

log = logging.getLogger("pgvd.agent")

#: Seconds between two attempts to write an own version the disk refused (full, read-only).
RETRY_S = 1.0

#: A peer's pending operation: its newest map, or None to delete its file.
_PeerOp = StoredMap | None


class Persister:
    """The state directory's writer thread (see the module docstring).

    Parameters
    ----------
    state : the directory written.
    me : this robot's id: its maps are written durably and in order.
    on_saved : called with ``(robot, version)`` on the writer thread once an own version is
        on disk.
    counters : where ``writes_coalesced`` counts the peer versions never written because a
        newer one superseded them first.
    """

    def __init__(
        self,
        state: StateDir,
        me: str,
        on_saved: Callable[[str, int], None],
        counters: Counters,
    ) -> None:
        self.state, self.me, self.on_saved, self.counters = state, me, on_saved, counters
        self._ready = threading.Condition(threading.Lock())
        self._own: deque[tuple[StoredMap, str | None]] = deque()
        self._peers: dict[str, _PeerOp] = {}
        self._links: tuple[LinkRecord, ...] | None = None
        self._closing = False
        self._thread = threading.Thread(target=self._run, name="pgvd-persist", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def save_map(self, robot: str, stored: StoredMap, point: str | None = None) -> None:
        """Queue ``robot``'s map; ``point`` names the failpoint mid-write (own maps)."""
        with self._ready:
            if robot == self.me:
                self._own.append((stored, point))
            else:
                if self._peers.get(robot) is not None:
                    self.counters.add("writes_coalesced")
                self._peers[robot] = stored
            self._ready.notify()

    def forget_map(self, robot: str) -> None:
        """Queue the deletion of ``robot``'s map; a write of it still pending is cancelled."""
        with self._ready:
            self._peers[robot] = None
            self._ready.notify()

    def save_links(self, records: tuple[LinkRecord, ...]) -> None:
        """Queue the links; only the last set queued is written."""
        with self._ready:
            self._links = records
            self._ready.notify()

    def close(self, timeout: float = 10.0) -> bool:
        """Write what is pending, then stop; False if that took longer than ``timeout`` s."""
        with self._ready:
            self._closing = True
            self._ready.notify()
        if self._thread.is_alive():
            self._thread.join(timeout)
        else:
            self._drain()
        return not self._thread.is_alive()

    def _count(self) -> int:
        return len(self._own) + len(self._peers) + (self._links is not None)

    def _run(self) -> None:
        while True:
            with self._ready:
                self._ready.wait_for(lambda: self._count() or self._closing)
                if self._closing and not self._count():
                    return
            if not self._write_next():
                with self._ready:  # an own version the disk refused: retry, but not in a loop
                    self._ready.wait_for(lambda: self._closing, RETRY_S)
                    if self._closing:
                        return

    def _drain(self) -> None:
        while self._write_next():
            pass

    def _write_next(self) -> bool:
        """Write the most urgent pending item; False if nothing was written."""
        with self._ready:
            job = self._take()
        return job is not None and job()

    def _take(self) -> Callable[[], bool] | None:
        """The next write, own versions first; a peer's or the links' leaves the queue now."""
        if self._own:
            return partial(self._write_own, *self._own[0])
        if self._peers:
            return partial(self._write_peer, *self._peers.popitem())
        if self._links is not None:
            records, self._links = self._links, None
            return partial(self._write_links, records)
        return None

    def _write_own(self, stored: StoredMap, point: str | None) -> bool:
        """Write an own version durably and report it; False (kept queued) if the disk refused."""
        try:
            self.state.save_map(self.me, stored, point, durable=True)
        except OSError as exc:
            log.error("cannot persist own map v%d: %s (retrying)", stored.version, exc)
            return False
        with self._ready:
            self._own.popleft()
        self.on_saved(self.me, stored.version)
        return True

    def _write_peer(self, robot: str, op: _PeerOp) -> bool:
        try:
            if op is None:
                self.state.forget_map(robot)
            else:
                self.state.save_map(robot, op)
        except OSError as exc:  # a peer's map is fetched again after a restart
            log.error("cannot persist %s's map: %s", robot, exc)
        return True

    def _write_links(self, records: tuple[LinkRecord, ...]) -> bool:
        try:
            self.state.save_links(list(records))
        except OSError as exc:  # links are fetched from peers after a restart
            log.error("cannot persist the links: %s", exc)
        return True
