"""Giving freed heap memory back to the operating system after each fusion job.

A merge allocates and frees arrays of a few MB by the hundred. glibc keeps freed heap pages,
and after the first large free it raises its mmap threshold, so later large arrays come from
the heap as well: an agent's RSS ratchets up to the high-water mark of its largest merge plus
fragmentation, and keeps it. On a robot that memory is wanted elsewhere. The blur's cached
polar geometry (:func:`pgvd.uncertainty.release_caches`, tens of MB after a fusion) is dropped
first, then ``malloc_trim(0)`` returns the free pages; it costs microseconds on an idle heap.
Where the C library has no ``malloc_trim`` (musl, macOS) only the caches go.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from collections.abc import Callable


def _find_malloc_trim() -> Callable[[int], int] | None:
    try:
        trim = ctypes.CDLL(ctypes.util.find_library("c")).malloc_trim
    except (OSError, AttributeError, TypeError):
        return None
    trim.argtypes, trim.restype = [ctypes.c_size_t], ctypes.c_int
    return trim


_MALLOC_TRIM = _find_malloc_trim()


def release_free_memory() -> bool:
    """Drop the method's caches, return freed heap pages to the OS; False where the C
    library cannot (the caches are dropped anyway)."""
    blur = sys.modules.get("pgvd.uncertainty")  # not imported: nothing cached, no scipy to load
    if blur is not None:
        blur.release_caches()
    if _MALLOC_TRIM is None:
        return False
    _MALLOC_TRIM(0)
    return True
