"""When to fetch a peer's latest map from its ``latest`` queryable instead of waiting for tiles.

Tiles and manifests are pushed; a fetch is the fallback. A receiver whose version of a peer
is incomplete (a tile lost, or one that contradicts its manifest) waits a little, since the
tiles may still be in flight, then fetches. A robot is fetched at most once a second unless it
just joined, so that a lossy link cannot turn every lost tile into a query.
"""

from __future__ import annotations

#: Seconds to wait for tiles in flight before fetching.
IN_FLIGHT_S = 0.3
#: Seconds between two fetches of one robot, other than the one when it joins.
MIN_INTERVAL_S = 1.0


class FetchSchedule:
    """Per robot: when a fetch is due, and when the last one went out (monotonic seconds)."""

    def __init__(self) -> None:
        self._due: dict[str, float] = {}
        self._last: dict[str, float] = {}

    def later(self, robot: str, now: float, delay: float = IN_FLIGHT_S) -> None:
        """Fetch ``robot`` at ``now + delay`` unless a fetch is already due earlier or later."""
        self._due.setdefault(robot, now + delay)

    def cancel(self, robot: str) -> None:
        """``robot``'s map is complete: no fetch is due."""
        self._due.pop(robot, None)

    def pop_due(self, now: float) -> list[str]:
        """The robots whose fetch is due at ``now``, forgotten as due."""
        due = [robot for robot, when in self._due.items() if now >= when]
        for robot in due:
            del self._due[robot]
        return due

    def allows(self, robot: str, now: float) -> bool:
        """Whether :data:`MIN_INTERVAL_S` passed since ``robot`` was last fetched."""
        return now - self._last.get(robot, -float("inf")) >= MIN_INTERVAL_S

    def sent(self, robot: str, now: float) -> None:
        """A fetch of ``robot`` went out at ``now``."""
        self._last[robot] = now
