"""Known-cell footprints: which pairs a prediction places near enough to be worth a check."""

from __future__ import annotations

import numpy as np

from agent.footprints import CELL_M, MARGIN_M, Footprint, FootprintCache
from agent.worker import verify_check
from pgvd.grid import Grid, rigid_matrix


def known_columns(grid: Grid) -> tuple[int, int]:
    """First and last column holding a known cell."""
    cols = np.flatnonzero((grid.logodds != 0).any(axis=0))
    return int(cols[0]), int(cols[-1])


def test_a_map_shifted_beside_itself_is_near_within_the_margin_only(intel_split) -> None:
    """B = A moved right until the gap between their known cells is ``gap`` metres."""
    a = intel_split.a
    first, last = known_columns(a)
    fp = Footprint.of(a)
    px = 1.0 / a.resolution

    def at_gap(gap_m: float) -> bool:
        shift = (last - first) + 1 + gap_m * px
        return fp.comes_near(fp, rigid_matrix(0.0, shift, 0.0))

    assert fp.comes_near(fp, np.eye(3))
    assert at_gap(0.0) and at_gap(MARGIN_M - 0.1)  # never skips a pair within the margin
    assert not at_gap(MARGIN_M + 3 * CELL_M)  # coarse blocks err on the side of a check
    turned = rigid_matrix(np.radians(37.0), 0.0, 0.0)
    assert fp.comes_near(fp, turned)


def test_a_map_without_known_cells_comes_near_nothing(intel_split) -> None:
    empty = Footprint.of(Grid(np.zeros((40, 30), np.float32), intel_split.a.resolution))
    full = Footprint.of(intel_split.a)
    assert not empty.comes_near(full, np.eye(3)) and not full.comes_near(empty, np.eye(3))


def test_poses_placed_apart_are_exactly_those_the_check_finds_no_overlap_at(intel_split) -> None:
    """On real maps, at poses from the truth to far off: wherever the footprints are apart,
    the check (pgvd.verify) finds no wall on the other's known space either."""
    a, b, truth = intel_split.a, intel_split.b, intel_split.truth
    fa, fb = Footprint.of(a), Footprint.of(b)
    check = verify_check()
    rng = np.random.default_rng(5)
    apart = 0
    for shift in (0.0, 200.0, 400.0, 800.0, 1600.0):
        turn, angle = rng.uniform(-np.pi, np.pi, 2)
        move = shift * np.array([np.cos(angle), np.sin(angle)])
        predicted = rigid_matrix(turn, *move) @ truth
        if fa.comes_near(fb, predicted):
            continue
        apart += 1
        verdict = check(a, b, predicted)
        assert verdict is not None and not verdict.accepted
        assert verdict.reason.startswith("the predicted pose overlaps 0.0 m of walls")
    assert fa.comes_near(fb, truth) and apart >= 2


def test_the_cache_makes_a_footprint_once_per_version(intel_split, monkeypatch) -> None:
    made: list[int] = []
    making = Footprint.of

    def counted(grid: Grid, margin_m: float = MARGIN_M) -> Footprint:
        made.append(id(grid))
        return making(grid, margin_m)

    monkeypatch.setattr(Footprint, "of", staticmethod(counted))
    cache = FootprintCache()
    first = cache.get("r1", 1, intel_split.a)
    assert cache.get("r1", 1, intel_split.a) is first and len(made) == 1
    assert cache.get("r1", 2, intel_split.b) is not first and len(made) == 2
    cache.forget_except({"r2"})
    cache.get("r1", 2, intel_split.b)
    assert len(made) == 3
