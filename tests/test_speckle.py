"""Lone wall cells (speckle) of raw maps, read as unknown for registration (pgvd.speckle)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pgvd.grid import Grid
from pgvd.merge import MergeParams, registration_probability
from pgvd.speckle import DESPECKLE_RADIUS, lone_walls, without_speckle

OCCUPIED = MergeParams().occupied


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
    """Two parts of willow's image, each with its own 0.5 % of free cells made lone walls."""
    from bench.mapimages import RESOLUTION, part_pairs
    from bench.merge import evaluate
    from bench.pairs import speckled_pair
    from pgvd.io import read_map
    from pgvd.merge import merge
    from pgvd.transform import resample

    grid = resample(
        read_map(shared / "maps" / "willow" / "willow-2010-02-18-0.10.yaml"), RESOLUTION
    )
    (pair,) = part_pairs("willow-sim", grid.probability(), 1, np.random.default_rng(21))
    pair = speckled_pair(pair, 0.005, 21)
    for radius, right in ((DESPECKLE_RADIUS, True), (0.0, False)):
        res = merge(pair.a, pair.b, MergeParams(diagnostics=False, speckle_radius=radius))
        assert evaluate(pair, res.accepted, res.matrix)["success"] is right, (radius, res.reason)


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
