"""Keeping an agent's heap from holding freed memory: a fixed mmap threshold, and a trim after
each fusion job.

A merge allocates and frees arrays of a few MB by the hundred. glibc keeps freed heap pages,
and after the first large free it raises its mmap threshold, so later large arrays come from
the heap as well: an agent's RSS ratchets up to the high-water mark of its largest merge plus
fragmentation, and keeps it. On a robot that memory is wanted elsewhere. The blur's cached
polar geometry (:func:`pgvd.uncertainty.release_caches`, tens of MB after a fusion) is dropped
first, then ``malloc_trim(0)`` returns the free pages; it costs microseconds on an idle heap.
Where the C library has no ``malloc_trim`` (musl, macOS) only the caches go.

The trim cannot lower the peak: a merge's or a rebuild's arrays that came from the heap leave
it fragmented, and the next job's arrays are placed above the holes. :func:`fix_mmap_threshold`
keeps every allocation of :data:`MMAP_THRESHOLD` or more out of the heap, mapped and unmapped
on its own. ``python3 -m bench fleet --robots 16``, two runs each on a shared machine, the
agent without and with it: peak RSS per agent 253-261 -> 241-242 MB, private memory 147-155
-> 124-128 MB; CPU per agent within the runs' spread (3.7-4.4 s without, 4.0-4.2 s with:
pages are mapped and zeroed anew). A 1 MB threshold saved no more memory (228-239 MB) for
more CPU (4.2-4.7 s), as did glibc's starting 128 KB (5.2 s).
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

#: Bytes from which glibc maps an allocation on its own (it starts at 128 KB and raises it,
#: up to 32 MB, after each large free): a merge's arrays of a few MB stay on the heap, the
#: rotation blur's polar bins of a global map (~10 MB each) are mapped.
MMAP_THRESHOLD = 8 << 20
#: ``mallopt``'s parameter number for it (``M_MMAP_THRESHOLD`` in ``<malloc.h>``).
_M_MMAP_THRESHOLD = -3


def _find_mallopt() -> Callable[[int, int], int] | None:
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c")).mallopt
    except (OSError, AttributeError, TypeError):
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


def fix_mmap_threshold() -> bool:
    """Map every allocation of :data:`MMAP_THRESHOLD` bytes or more on its own, for good
    (glibc's ``mallopt``); False where the C library has no ``mallopt`` or refused."""
    mallopt = _find_mallopt()
    return mallopt is not None and mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD) == 1


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
