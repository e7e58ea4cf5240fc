"""Opt-in CPU profiles of an agent's threads, for finding where a running fleet's CPU goes.

Set ``PGVD_PROFILE`` to a directory and every agent started with it (``pgvd agent``, or the
agents ``python3 -m bench fleet`` launches, which inherit the environment) profiles its main,
receiving and fusion threads with :mod:`cProfile` in CPU time (:func:`time.thread_time`: on a
shared machine wall time would count the waits for a core), each on its own (a profiler sees
only the thread that enabled it), and writes ``ROBOT-THREAD.prof`` there when the thread ends.  Read
them with ``python3 -m pstats FILE``, or merged: ``pstats.Stats(*files)``.  Unset, nothing is
profiled and nothing is written.
"""

from __future__ import annotations

import cProfile
import logging
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

log = logging.getLogger("pgvd.agent")

#: The environment variable naming the directory profiles go to.
ENV = "PGVD_PROFILE"

T = TypeVar("T")


def profile_dir() -> Path | None:
    """The directory of :data:`ENV`, or None when profiling is off."""
    where = os.environ.get(ENV, "")
    return Path(where) if where else None


def profiled(robot: str, thread: str, run: Callable[[], T]) -> T:
    """``run()``, profiled into ``ROBOT-THREAD.prof`` when :data:`ENV` names a directory.

    A profile that cannot be written is logged, never raised: it must not stop the agent.
    """
    where = profile_dir()
    if where is None:
        return run()
    prof = cProfile.Profile(time.thread_time)
    prof.enable()
    try:
        return run()
    finally:
        prof.disable()
        try:
            where.mkdir(parents=True, exist_ok=True)
            prof.dump_stats(where / f"{robot}-{thread}.prof")
        except OSError as exc:
            log.error("cannot write the %s profile to %s: %s", thread, where, exc)
