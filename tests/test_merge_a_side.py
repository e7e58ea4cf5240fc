"""The merge's per-map rejection of map A (:func:`pgvd.merge.a_side_rejection`): a fleet
skips the search of a pair whose map A fails it, so it must be exactly the merge's own."""

from __future__ import annotations

import numpy as np
import pytest

from pgvd import read_map
from pgvd.grid import Grid
from pgvd.merge import a_side_rejection, merge
from pgvd.params import MergeParams

#: Crops of the bundled Intel map A, (rows, cols) in cells of 5 cm: from a few metres square
#: (as a robot's first maps are) to most of the map.
CROPS = [
    (slice(380, 420), slice(380, 420)),
    (slice(300, 380), slice(400, 470)),
    (slice(100, 190), slice(200, 320)),
    (slice(0, 808), slice(0, 60)),
    (slice(200, 600), slice(200, 600)),
]


def crop(grid: Grid, rows: slice, cols: slice) -> Grid:
    return Grid(np.ascontiguousarray(grid.logodds[rows, cols]), grid.resolution, grid.origin)


@pytest.fixture(scope="module")
def maps() -> tuple[Grid, Grid]:
    return read_map("examples/intel_a.yaml"), read_map("examples/intel_b.yaml")


@pytest.mark.parametrize("params", [MergeParams(diagnostics=False), MergeParams()])
def test_a_map_rejected_on_its_own_is_rejected_by_every_merge(
    maps: tuple[Grid, Grid], params: MergeParams
) -> None:
    """Every crop the per-map test rejects is rejected by the merge against B, for the
    same reason, and at least one crop of each kind is met."""
    a, b = maps
    verdicts = []
    for rows, cols in CROPS:
        small = crop(a, rows, cols)
        why = a_side_rejection(small, params)
        verdicts.append(why is None)
        if why is None:
            continue
        try:
            res = merge(small, b, params)
        except ValueError as exc:  # the merge refuses an unreadable map outright
            assert str(exc) == why
        else:
            assert not res.accepted and res.reason.startswith(why)
    assert any(verdicts) and not all(verdicts)


def test_a_readable_map_with_walls_is_not_rejected_on_its_own(maps: tuple[Grid, Grid]) -> None:
    a, b = maps
    assert a_side_rejection(a) is None
    assert merge(a, b).accepted
