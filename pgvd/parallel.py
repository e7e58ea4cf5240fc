"""One computation on both maps of a pair at once.

The per-map stages of a merge on large maps -- the probabilities (34) of the
log-odds, pooling, the wall maps of the decision -- are long NumPy, SciPy and
OpenCV array loops, which release the GIL, so on two threads the two maps take
little more than the time of one.  On the scaling pair of ``python3 -m
bench.merge`` (two cores, median of 9 merges, interleaved) the three stages
took 168 ms for both maps one after the other and 97 ms on two threads: the
whole merge 0.54 s against 0.48 s at 2001^2 cells, 0.37 s against 0.36 s at
1000^2.  The results are the same either way: each call sees only its own map.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")


def both(fn: Callable[[T], R], x: T, y: T) -> tuple[R, R]:
    """``(fn(x), fn(y))``, ``fn(y)`` on a thread of its own while this one computes ``fn(x)``.

    Parameters
    ----------
    fn : callable
        A function of one argument that shares no mutable state between calls.
    x, y : object
        Its two arguments (A's and B's).

    Returns
    -------
    tuple
        ``(fn(x), fn(y))``.

    Raises
    ------
    Exception
        Whatever ``fn(x)`` raised, else whatever ``fn(y)`` raised: an error in A is
        reported before one in B, as one after the other.  Both calls have ended by then.
    """
    if (os.cpu_count() or 1) < 2:
        return fn(x), fn(y)
    out: dict[str, object] = {}

    def second() -> None:
        try:
            out["value"] = fn(y)
        except BaseException as error:  # re-raised on the caller's thread below
            out["error"] = error

    thread = threading.Thread(target=second, name="pgvd-map-b", daemon=True)
    thread.start()
    try:
        first = fn(x)
    finally:
        thread.join()
    if "error" in out:
        raise out["error"]  # type: ignore[misc]
    return first, out["value"]  # type: ignore[return-value]
