"""Failpoints: named places in the agent where a test can stop it dead, as fail(9) or fail-rs do.

A crash test that kills an agent "a few ms after it published" hits a write only by luck.
A failpoint makes the kill land exactly where the test means: the environment variable
``PGVD_FAILPOINT`` names one point (read once at import); when the agent reaches that point it
writes ``FAILPOINT <name> <pid>`` to stderr and blocks until the test ``kill -9``s it. Every later
hit blocks too: the process is about to be killed, so there is nothing to count or resume.
Unarmed, :func:`failpoint` is a dictionary-free comparison and does nothing.
"""

from __future__ import annotations

import os
import sys
import time

#: Every point the agent can stop at (``pgvd agent`` refuses any other ``PGVD_FAILPOINT``).
POINTS = {
    "state-write": "half of the own map file's temporary copy written, before fsync and rename",
    "tiles-send": "the first tile of a new own version sent, the other tiles and manifest not",
}
ENV = "PGVD_FAILPOINT"
ARMED: str = os.environ.get(ENV, "")


def check_armed() -> None:
    """Raise ValueError unless ``PGVD_FAILPOINT`` is unset, empty or one of :data:`POINTS`."""
    if ARMED and ARMED not in POINTS:
        raise ValueError(f"unknown {ENV} {ARMED!r}: expected one of {', '.join(sorted(POINTS))}")


def failpoint(name: str) -> None:
    """Announce on stderr and block forever if ``name`` is the armed point; else return at once."""
    if name != ARMED:
        return
    sys.stderr.write(f"FAILPOINT {name} {os.getpid()}\n")
    sys.stderr.flush()
    while True:
        time.sleep(3600)
