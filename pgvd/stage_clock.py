"""The clock of one merge's stages (``timings_ms``), apart from the result it ends in, so
that every stage can time itself without importing the result."""

from __future__ import annotations

import time
from collections.abc import Callable


class StageClock:
    """Milliseconds per stage of one merge (``timings_ms``), told to ``progress`` as they end."""

    def __init__(self, progress: Callable[[str], None] | None) -> None:
        self.timings: dict[str, float] = {}
        self.progress = progress
        self.t0 = self.last = time.perf_counter()

    def lap(self, stage: str) -> None:
        """Add the time since the last lap to ``stage``; progress shows both (a stage such as
        gamma runs once per searched heading, so its running total alone reads as steps)."""
        now = time.perf_counter()
        step = 1e3 * (now - self.last)
        self.timings[stage] = self.timings.get(stage, 0.0) + step
        self.last = now
        if self.progress is not None:
            self.progress(f"{stage}: {step:.1f} ms ({self.timings[stage]:.1f} ms so far)")

    def total(self) -> dict[str, float]:
        """The timings so far, with ``"total"`` the time since the clock started."""
        self.timings["total"] = 1e3 * (time.perf_counter() - self.t0)
        return self.timings
