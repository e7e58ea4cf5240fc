"""The retry of a rejected merge of raw map images, with their lone wall cells (speckle)
read as unknown (``ReadingParams.speckle_retry``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

from pgvd.grid import Grid
from pgvd.params import MergeParams
from pgvd.result import MergeResult
from pgvd.speckle import DESPECKLE_RADIUS, radius_cells, speckle_share

Progress = Callable[[str], None] | None
#: One search and decision of two maps (:func:`pgvd.merge.merge` without its retry).
MergePass = Callable[[Grid, Grid, MergeParams, Progress], MergeResult]


def retried(
    a: Grid,
    b: Grid,
    first: MergeResult,
    params: MergeParams,
    progress: Progress,
    merge_pass: MergePass,
) -> MergeResult:
    """The rejection ``first`` tried again by ``merge_pass`` with speckle read as unknown if
    a map is raw (``params.reading.speckle_retry``), else as it is; measuring the maps is
    timed into its total (``timings_ms["speckle_share"]``)."""
    t0 = time.perf_counter()
    share = _raw_share(a, b, params)
    first = first.with_time("speckle_share", 1e3 * (time.perf_counter() - t0))
    if share < params.reading.speckle_retry:
        return first
    if progress is not None:
        progress(
            f"{share:.1%} of a map's free cells are lone wall cells (a raw map?): trying "
            "again with them read as unknown (as --despeckle)"
        )
    try:
        again = merge_pass(a, b, replace(params, speckle_radius=DESPECKLE_RADIUS), progress)
    except ValueError as exc:  # e.g. every wall of a map was lone: nothing left to register
        why = f"{first.reason}; with lone wall cells read as unknown: {exc}"
        return replace(first, reason=why)
    return _after_retry(first, again, share)


def _raw_share(a: Grid, b: Grid, params: MergeParams) -> float:
    """The larger share of lone wall cells among the two maps' free cells, read as the
    despeckle reading finds them (:func:`pgvd.speckle.speckle_share`)."""
    return max(
        speckle_share(
            g.probability(),
            params.reading.occupied,
            params.reading.free,
            radius_cells(DESPECKLE_RADIUS, g.resolution),
            params.reading.speckle_cells,
        )
        for g in (a, b)
    )


def _after_retry(first: MergeResult, again: MergeResult, share: float) -> MergeResult:
    """The outcome of a merge retried with speckle read as unknown: the retry's, its reason
    saying so (and, if it too is rejected, why the maps as drawn were), its stages' times,
    the first pass's total as ``as_drawn`` and the total of both."""
    read = f"lone wall cells read as unknown ({share:.1%} of free cells)"
    if again.accepted:
        reason = f"accepted with {read}"
    else:
        reason = f"{again.reason}, with {read}; as drawn: {first.reason}"
    return replace(again.with_time("as_drawn", first.timings_ms["total"]), reason=reason)
