"""agent.memory: freed heap pages go back to the OS (measured on a real process's RSS)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.memory import release_free_memory

ROOT = Path(__file__).resolve().parents[1]
# 100 MB of arrays below glibc's mmap threshold (so they live on the heap), all freed but the
# last, which pins the top of the heap: only malloc_trim's release of inner pages can help.
PROBE = """
import sys
import numpy as np
from agent.memory import release_free_memory

def rss_mb():
    with open("/proc/self/status") as f:
        return next(int(l.split()[1]) // 1024 for l in f if l.startswith("VmRSS"))

arrays = [np.ones(12_500) for _ in range(1000)]
last = arrays[-1]
del arrays
before = rss_mb()
done = release_free_memory()
print(before, rss_mb(), done)
"""


@pytest.mark.skipif(not release_free_memory(), reason="this C library has no malloc_trim")
def test_freed_heap_arrays_are_returned_to_the_os() -> None:
    out = subprocess.run(
        [sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    before, after, done = out.stdout.split()
    assert done == "True"
    assert int(before) - int(after) > 50, (before, after)  # of the ~100 MB freed


def test_the_blurs_polar_geometry_is_dropped_after_a_job() -> None:
    """The blur of a fusion (pgvd.uncertainty.rotation_blur) about a centre far off the map
    caches polar bins over the whole circle; release_free_memory drops them."""
    from pgvd.uncertainty import _blurred_totals, _polar_geometry, rotation_blur

    image = np.zeros((300, 300), np.float32)
    image[100:200, 150] = 1.0
    rotation_blur(image, 0.01, center=(-400.0, -300.0))
    assert _polar_geometry.cache_info().currsize == _blurred_totals.cache_info().currsize == 1
    release_free_memory()
    assert _polar_geometry.cache_info().currsize == _blurred_totals.cache_info().currsize == 0
