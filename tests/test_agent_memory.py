"""agent.memory: freed heap pages go back to the OS (measured on a real process's RSS)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.memory import fix_mmap_threshold, release_free_memory

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


def test_a_blur_on_another_canvas_holds_no_geometry_of_the_last_one(shared: Path) -> None:
    """A fusion blurs each map on a canvas of its own: the geometry cached for the last one
    is dropped before the next is built, so the peak of a blur does not grow with the blur
    before it (as it did by ~20 MB on a 550 x 550 global map). Traced memory, real map."""
    import tracemalloc

    from pgvd.io import read_map
    from pgvd.uncertainty import release_caches, rotation_blur

    image = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml").logodds

    def peak_of_blur(previous: np.ndarray | None) -> int:
        """Traced bytes at the blur's peak, what the blur before it still holds included."""
        release_caches()
        tracemalloc.start()
        try:
            if previous is not None:
                rotation_blur(previous, 0.02, center=(250.0, 200.0))
            tracemalloc.reset_peak()
            rotation_blur(image, 0.02, center=(300.0, 280.0))
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    alone = peak_of_blur(None)
    after_another = peak_of_blur(image[:500, :520])
    assert after_another <= alone * 1.02, (after_another, alone)


# Where a 12 MB array lands once a larger one was freed: glibc then raised its threshold past
# it, and without a fixed one the array comes from the heap, among whatever the heap holds.
PLACEMENT = """
import sys
import numpy as np
from agent.memory import fix_mmap_threshold

if sys.argv[1] == "fixed":
    assert fix_mmap_threshold()
np.ones(3 << 20).sum()  # a 24 MB array, mapped and freed
array = np.ones(3 << 19)  # 12 MB
with open("/proc/self/maps") as f:
    heap = [l.split()[0] for l in f if l.rstrip().endswith("[heap]")]
lo, hi = (int(x, 16) for x in heap[0].split("-"))
print(lo <= array.ctypes.data < hi)
"""


@pytest.mark.skipif(not fix_mmap_threshold(), reason="this C library has no mallopt")
def test_a_fixed_mmap_threshold_keeps_large_arrays_off_the_heap() -> None:
    """A merge's arrays mapped on their own are unmapped when freed; from the heap they leave
    holes the next job's arrays may not fit, and the peak RSS grows (see agent.memory)."""
    in_heap = {}
    for mode in ("fixed", "default"):
        out = subprocess.run(
            [sys.executable, "-c", PLACEMENT, mode],
            cwd=ROOT, capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert out.returncode == 0, out.stderr
        in_heap[mode] = out.stdout.strip()
    assert in_heap == {"fixed": "False", "default": "True"}
