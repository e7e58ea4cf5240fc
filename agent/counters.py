"""Traffic and drop counters of one agent, safe to bump from Zenoh callback threads.

Fleet invariant 5: a bad message is dropped, logged once (per reason and sender) and
counted; the counts by reason are part of the status. Reasons are the categories of
:data:`protocol.errors.REASONS` for what a decoder refused, plus the agent's own rules
(``foreign_fleet``, ``key_mismatch``, ``stale_version``, ``overload``, ...).
"""

from __future__ import annotations

import logging
import threading
from collections import Counter

log = logging.getLogger("pgvd.agent")

#: (reason, sender) pairs remembered as logged; past this, only a new reason is logged, so a
#: peer forging many sender ids can neither grow this set nor flood the log.
MAX_LOGGED = 64


class Counters:
    """Named counters plus drops by reason; :meth:`snapshot` is what status shows."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._drops: Counter[str] = Counter()
        self._logged: set[tuple[str, str]] = set()
        self._logged_reasons: set[str] = set()

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._counts[name] += n

    def drop(self, reason: str, sender: str, detail: str) -> None:
        """Count a dropped message; log the first one of each ``(reason, sender)``.

        Past :data:`MAX_LOGGED` pairs, only the first drop of a reason not yet logged is.
        """
        with self._lock:
            self._drops[reason] += 1
            pair = (reason, sender)
            room = len(self._logged) < MAX_LOGGED
            first = pair not in self._logged and (room or reason not in self._logged_reasons)
            if first:
                self._logged_reasons.add(reason)
                if room:
                    self._logged.add(pair)
        if first:
            log.warning("dropped message (%s) from %s: %s", reason, sender, detail)

    def get(self, name: str) -> int:
        with self._lock:
            return self._counts[name]

    def snapshot(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {"counts": dict(self._counts), "drops": dict(self._drops)}
