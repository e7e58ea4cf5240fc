"""pgvd.unexplored: a map image with no unknown cells gets its unexplored space back.

The hull is checked against scikit-image's ``convex_hull_image``; the merge on a
real development map image whose unexplored area was painted white.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pgvd.unexplored import restore_unexplored, unknown_share, wall_hull, wall_share

FREE, OCCUPIED = 0.3, 0.65

# free, unknown and wall values exact in float32: hypothesis at its lowest supported version
# refuses an element that float32 would round
maps = arrays(
    np.float32,
    st.tuples(st.integers(1, 24), st.integers(1, 24)),
    elements=st.sampled_from([0.0625, 0.125, 0.5, 0.875, 0.9375]),
)


@given(maps)
def test_hull_holds_every_wall_and_lies_in_the_pixel_hull(p):
    from skimage.morphology import convex_hull_image

    walls = p > OCCUPIED
    hull = wall_hull(walls)
    assert hull.shape == walls.shape and hull.dtype == bool
    assert not np.any(walls & ~hull)
    if walls.any():
        # scikit-image's hull covers the walls' whole pixels: a superset of the centres'
        assert not np.any(hull & ~convex_hull_image(walls))
    else:
        assert not hull.any()


@given(maps)
def test_restore_only_turns_free_cells_outside_the_hull_unknown(p):
    out = restore_unexplored(p, FREE, OCCUPIED)
    changed = out != p
    assert out.dtype == p.dtype
    assert np.all(out[changed] == 0.5)
    assert np.array_equal(changed, (p < FREE) & ~wall_hull(p > OCCUPIED))


@given(maps, st.floats(0.0, 1.0))
def test_registration_restores_only_maps_without_unknown_and_says_so(p, min_unknown):
    from pgvd.grid import Grid
    from pgvd.inputs import registration_probability
    from pgvd.params import MergeParams

    grid = Grid.from_probability(p, 0.05)
    params = MergeParams(free=FREE, occupied=OCCUPIED, min_unknown=min_unknown)
    said: list[str] = []
    out = registration_probability(grid, params, said.append)
    drawn = grid.probability()
    if unknown_share(drawn, FREE, OCCUPIED) >= min_unknown:
        assert np.array_equal(out, drawn) and not said
    else:
        assert np.array_equal(out, restore_unexplored(drawn, FREE, OCCUPIED))
        assert len(said) == 1 and "no unknown cells" in said[0]


def test_an_l_shaped_building_painted_free_keeps_its_floor_and_bay():
    p = np.full((60, 60), 0.02, np.float32)  # no unknown cell at all
    p[10, 10:50] = p[10:50, 10] = p[49, 10:31] = p[30, 30:50] = 0.97
    p[10:31, 49] = p[30:50, 30] = 0.97
    assert unknown_share(p, FREE, OCCUPIED) == 0.0
    out = restore_unexplored(p, FREE, OCCUPIED)
    assert np.all(out[11:30, 11:49] == 0.02) and np.all(out[30:49, 11:30] == 0.02)  # floor
    assert np.all(out[:10] == 0.5) and np.all(out[:, :10] == 0.5)  # outside the building
    assert np.all(out[35, 32:40] == 0.02)  # the bay between the wings: inside the hull
    assert np.all(out[45, 40:50] == 0.5)  # the bay beyond the hull
    assert np.array_equal(out > OCCUPIED, p > OCCUPIED)


def test_a_painted_map_image_merges_right_and_read_as_drawn_does_not(shared):
    from bench.data.pairs import painted_pair
    from bench.mapimages import part_pairs
    from bench.merge import evaluate
    from pgvd.io import read_map
    from pgvd.merge import merge
    from pgvd.params import MergeParams

    p = read_map(shared / "maps" / "intel" / "intel.yaml").probability()
    (pair,) = part_pairs("intel", p, 1, np.random.default_rng(21))
    pair = painted_pair(pair)
    assert unknown_share(pair.a.probability(), FREE, OCCUPIED) < 0.01
    restored = evaluate(pair, *_outcome(merge(pair.a, pair.b, MergeParams(diagnostics=False))))
    as_drawn = merge(pair.a, pair.b, MergeParams(diagnostics=False, min_unknown=0.0))
    assert restored["success"], restored
    assert not evaluate(pair, *_outcome(as_drawn))["success"]


def _outcome(result) -> tuple[bool, np.ndarray]:
    return result.accepted, result.matrix


def test_wall_share_counts_walls_among_known_cells_only() -> None:
    p = np.full((10, 10), 0.5)  # unknown
    p[0, :4] = 0.9  # 4 walls
    p[1:3, :] = 0.1  # 20 free
    assert wall_share(p, 0.3, 0.65) == 4 / 24
    assert wall_share(np.full((3, 3), 0.5), 0.3, 0.65) == 0.0
