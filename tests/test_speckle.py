"""Lone wall cells (speckle) of raw maps, read as unknown for registration (pgvd.speckle)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pgvd.grid import Grid
from pgvd.inputs import registration_probability
from pgvd.params import MergeParams
from pgvd.speckle import DESPECKLE_RADIUS, lone_walls, radius_cells, speckle_share, without_speckle

OCCUPIED = MergeParams().occupied
FREE = MergeParams().free
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _window_counts(walls: np.ndarray, radius: int) -> np.ndarray:
    """Wall cells in the square around every cell, by summing shifted copies (the reference)."""
    h, w = walls.shape
    padded = np.pad(walls.astype(int), radius)
    side = 2 * radius + 1
    return sum(padded[dy : dy + h, dx : dx + w] for dy in range(side) for dx in range(side))


@given(
    arrays(bool, st.tuples(st.integers(1, 24), st.integers(1, 24))),
    st.integers(1, 4),
    st.integers(1, 5),
)
def test_lone_walls_are_the_walls_with_few_walls_around(walls, radius, most):
    lone = lone_walls(walls, radius, most)
    assert np.array_equal(lone, walls & (_window_counts(walls, radius) <= most))


def test_a_wall_even_one_drawn_every_other_cell_is_no_speckle():
    walls = np.zeros((20, 40), bool)
    walls[5, 2:38] = True  # a wall
    walls[12, 2:38:2] = True  # a wall a laser drew at a grazing angle: every other cell
    walls[17, 10] = walls[17, 20] = walls[17, 30] = True  # three lone cells
    walls[0, 0] = walls[0, 1] = True  # a lone pair in a corner
    lone = set(zip(*np.nonzero(lone_walls(walls, 3, 2)), strict=True))
    # the dotted wall's two end dots have one dot within 3 cells: they go with the speckle
    ends = {(12, 2), (12, 36)}
    assert lone == {(0, 0), (0, 1), (17, 10), (17, 20), (17, 30)} | ends


def test_bad_radius_or_count_is_refused():
    with pytest.raises(ValueError, match=r"radius must be in 1\.\.127 and most >= 1"):
        lone_walls(np.zeros((3, 3), bool), 0, 2)


@given(
    arrays(
        np.float32,
        st.tuples(st.integers(1, 20), st.integers(1, 20)),
        elements=st.sampled_from([0.125, 0.5, 0.875]),
    )
)
def test_without_speckle_only_turns_lone_walls_unknown(p):
    out, n = without_speckle(p, OCCUPIED, 2, 2)
    changed = out != p
    assert out.dtype == p.dtype and n == int(changed.sum())
    assert np.array_equal(changed, lone_walls(p > OCCUPIED, 2, 2))
    assert np.all(out[changed] == 0.5)


def test_registration_reads_speckle_unknown_only_when_asked_and_says_so():
    p = np.full((60, 60), 0.1, np.float32)
    p[10, 5:55] = 0.9  # a wall
    p[30, 30] = p[45, 12] = 0.9  # speckle
    p[50:, :] = 0.5  # unknown, so the map is not read as painted free
    grid = Grid.from_probability(p, 0.05)
    said: list[str] = []
    on = MergeParams(speckle_radius=DESPECKLE_RADIUS)
    prob = registration_probability(grid, on, said.append)
    assert prob[30, 30] == prob[45, 12] == 0.5 and np.all(prob[10, 5:55] > OCCUPIED)
    assert said == ["2 lone wall cells (speckle) read as unknown"]
    assert np.array_equal(registration_probability(grid, MergeParams(), said.append), p)
    assert len(said) == 1  # off by default, and silent


def test_a_speckled_map_image_merges_right_only_despeckled(shared):
    """Two parts of willow's image, each with its own 0.5 % of free cells made lone walls:
    wrong or rejected as drawn, right despeckled, and so by default, through the retry."""
    from bench.data.pairs import speckled_pair
    from bench.mapimages import RESOLUTION, part_pairs
    from bench.merge import evaluate
    from pgvd.io import read_map
    from pgvd.merge import merge
    from pgvd.transform import resample

    grid = resample(
        read_map(shared / "maps" / "willow" / "willow-2010-02-18-0.10.yaml"), RESOLUTION
    )
    (pair,) = part_pairs("willow-sim", grid.probability(), 1, np.random.default_rng(21))
    pair = speckled_pair(pair, 0.005, 21)
    despeckled = MergeParams(diagnostics=False, speckle_radius=DESPECKLE_RADIUS)
    as_drawn = MergeParams(diagnostics=False, speckle_retry=0.0)
    by_default = MergeParams(diagnostics=False)
    for params, right in ((despeckled, True), (as_drawn, False), (by_default, True)):
        res = merge(pair.a, pair.b, params)
        assert evaluate(pair, res.accepted, res.matrix)["success"] is right, (params, res.reason)
    assert res.reason.startswith("accepted with lone wall cells read as unknown")


def test_a_painted_raw_map_is_despeckled_and_restored():
    """The unknown share is read before speckle turns unknown: heavy speckle on a map painted
    free must not pass for unexplored space and skip the restoration."""
    p = np.full((80, 80), 0.1, np.float32)  # painted free: no unknown cell
    p[20, 20:60] = p[60, 20:60] = p[20:61, 20] = p[20:61, 60] = 0.9  # a room
    rng = np.random.default_rng(3)
    lone = rng.choice(np.flatnonzero(p < 0.5), 200, replace=False)  # 3 % speckle
    p.flat[lone] = 0.9
    said: list[str] = []
    on = MergeParams(speckle_radius=DESPECKLE_RADIUS)
    registration_probability(Grid.from_probability(p, 0.05), on, said.append)
    assert len(said) == 2 and said[1].startswith("no unknown cells"), said


def test_at_a_coarse_resolution_a_dotted_wall_keeps_its_dots():
    """0.15 m is 1.5 cells at 0.1 m/cell: the square keeps a half-side of 2 cells, where a
    wall drawn every other cell is no speckle (in 3x3 squares it all would be)."""
    p = np.full((30, 60), 0.5, np.float32)
    p[10:20, :] = 0.1
    p[15, 4:56:2] = 0.9  # a dotted wall
    p[12, 30] = 0.9  # a lone cell
    on = MergeParams(speckle_radius=DESPECKLE_RADIUS)
    prob = registration_probability(Grid.from_probability(p, 0.1), on)
    assert prob[12, 30] == 0.5
    assert np.count_nonzero(prob[15] > OCCUPIED) >= 24  # all but the two end dots at most


def test_speckle_share_is_lone_walls_per_free_cell():
    p = np.full((20, 20), 0.1, np.float32)
    p[0, :] = 0.9  # a wall: its cells have many walls around
    p[8, 4] = p[8, 12] = p[15, 8] = 0.9  # three lone cells, more than 3 cells apart
    p[19, :] = 0.5  # unknown: neither free nor wall
    free = 20 * 20 - 20 - 3 - 20
    assert speckle_share(p, OCCUPIED, FREE, 3, 2) == pytest.approx(3 / free)
    assert speckle_share(np.full((5, 5), 0.9), OCCUPIED, FREE, 3, 2) == 0.0  # no free cell


def test_the_speckle_square_is_at_least_two_cells():
    assert radius_cells(DESPECKLE_RADIUS, 0.05) == 3
    assert radius_cells(DESPECKLE_RADIUS, 0.1) == 2 and radius_cells(DESPECKLE_RADIUS, 1.0) == 2


def _raw(grid: Grid, share: float, seed: int) -> Grid:
    """``grid`` with ``share`` of its free cells turned into lone walls, as a raw map."""
    p = grid.probability().copy()
    free = np.flatnonzero(p < FREE)
    rng = np.random.default_rng(seed)
    p.flat[rng.choice(free, round(share * free.size), replace=False)] = 0.95
    return Grid.from_probability(p, grid.resolution, grid.origin)


def test_a_raw_pair_rejected_as_drawn_is_merged_by_the_retry():
    """The bundled Intel pair with 2 % of each map's free cells made walls: as drawn its
    best pose does not stand out (margin ~0.52); read despeckled it does (~0.67)."""
    from pgvd.io import read_map
    from pgvd.merge import merge

    a = _raw(read_map(EXAMPLES / "intel_a.yaml"), 0.02, 103)
    b = _raw(read_map(EXAMPLES / "intel_b.yaml"), 0.02, 203)
    assert speckle_share(b.probability(), OCCUPIED, FREE, 3, 2) >= MergeParams().speckle_retry
    as_drawn = merge(a, b, MergeParams(diagnostics=False, speckle_retry=0.0))
    assert not as_drawn.accepted, as_drawn.reason
    said: list[str] = []
    res = merge(a, b, MergeParams(diagnostics=False), progress=said.append)
    assert res.accepted and res.reason.startswith("accepted with lone wall cells read as unknown")
    assert any("trying again with them read as unknown" in line for line in said)
    times = res.timings_ms
    assert times["as_drawn"] > 0 and times["total"] > times["as_drawn"]
    truth = np.array(json.loads((EXAMPLES / "truth.json").read_text())["matrix"])
    rows, cols = np.nonzero(read_map(EXAMPLES / "intel_b.yaml").probability() > OCCUPIED)
    walls = np.stack([cols, rows, np.ones_like(cols)])
    assert np.hypot(*((res.matrix - truth) @ walls)[:2]).mean() < 1.5


def test_a_clean_rejection_is_not_retried():
    """Maps as a laser draws them have few lone walls: a rejection of them stands as it is,
    decided once (here the bundled map B against its own mirror image, a building that does
    not exist)."""
    from pgvd.io import read_map
    from pgvd.merge import merge

    b = read_map(EXAMPLES / "intel_b.yaml")
    mirror = Grid(b.logodds[:, ::-1].copy(), b.resolution, b.origin)
    said: list[str] = []
    res = merge(read_map(EXAMPLES / "intel_a.yaml"), mirror, progress=said.append)
    assert not res.accepted and "as_drawn" not in res.timings_ms
    assert not any("read as unknown" in line for line in said)


def test_a_map_of_lone_walls_only_is_rejected_not_refused():
    """Every wall of this map is lone, so the retry reads it empty; the merge stays a
    rejection (exit 3 for ``pgvd merge``), not an error about the input."""
    from pgvd.merge import merge

    p = np.full((60, 60), 0.1, np.float32)
    p[::10, ::10] = 0.9  # a wall dot every 10 cells
    p[50:, :] = 0.5  # unknown, so the map is not read as painted free
    grid = Grid.from_probability(p, 0.05)
    res = merge(grid, grid, MergeParams(diagnostics=False))
    assert not res.accepted
    assert "with lone wall cells read as unknown: map A has no occupied cells" in res.reason
    assert res.timings_ms["speckle_share"] > 0


def test_a_retry_that_is_rejected_too_gives_both_reasons():
    """A raw map against its own mirror image: rejected as drawn and despeckled."""
    from pgvd.io import read_map
    from pgvd.merge import merge

    b = _raw(read_map(EXAMPLES / "intel_b.yaml"), 0.02, 203)
    mirror = Grid(b.logodds[:, ::-1].copy(), b.resolution, b.origin)
    res = merge(_raw(read_map(EXAMPLES / "intel_a.yaml"), 0.02, 103), mirror)
    assert not res.accepted
    assert ", with lone wall cells read as unknown (" in res.reason and "; as drawn: " in res.reason
    assert res.timings_ms["total"] > res.timings_ms["as_drawn"] > 0


def test_the_bench_records_the_pass_that_decided_a_retried_merge():
    """bench.capture's watchers keep the last pass of a retried merge: the headings it
    searched are those the result reports, and its finalists are the despeckled maps'."""
    from bench.capture import Finalists, SearchedHeadings
    from pgvd.io import read_map
    from pgvd.merge import merge

    a = _raw(read_map(EXAMPLES / "intel_a.yaml"), 0.02, 103)
    b = _raw(read_map(EXAMPLES / "intel_b.yaml"), 0.02, 203)
    searched, finalists = SearchedHeadings(), Finalists()
    with searched.watching(), finalists.watching():
        res = merge(a, b, MergeParams(diagnostics=False))
    assert "as_drawn" in res.timings_ms
    assert searched.degrees == pytest.approx(list(res.headings_deg))
    assert finalists.matrices and len(finalists.matrices) <= MergeParams().finalists
