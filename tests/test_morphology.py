"""grow and grow_max equal scipy's dilations; surface is a mask less its erosion; drop_small
removes what scikit-image removes."""

import inspect

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage as ndi

from pgvd.io import read_map
from pgvd.morphology import drop_small, grow, grow_max, surface


@settings(max_examples=60)
@given(
    mask=arrays(bool, st.tuples(st.integers(1, 24), st.integers(1, 24))),
    cells=st.integers(1, 3),
)
def test_grow_equals_scipy_square_dilation(mask, cells):
    expected = ndi.binary_dilation(mask, np.ones((3, 3), bool), iterations=cells)
    assert np.array_equal(grow(mask, cells), expected)


@settings(max_examples=60)
@given(
    values=arrays(
        np.float64,
        st.tuples(st.integers(1, 20), st.integers(1, 20)),
        elements=st.floats(0.0, 1.0, allow_nan=False),
    ),
    cells=st.integers(1, 3),
)
def test_grow_max_equals_scipy_grey_dilation_inside_a_zero_border(values, cells):
    # the edge sub-matrices of pgvd.edge_matching are padded by as many zeros as they grow
    padded = np.pad(values, cells)
    expected = ndi.grey_dilation(padded, size=2 * cells + 1)
    assert np.array_equal(grow_max(padded, cells), expected)


def test_grow_max_refuses_bad_input():
    with pytest.raises(ValueError, match="cells"):
        grow_max(np.zeros((3, 3)), -1)
    with pytest.raises(ValueError, match="2-D"):
        grow_max(np.zeros(3))


def test_grow_zero_is_a_copy_and_bad_input_is_refused():
    mask = np.eye(4, dtype=bool)
    out = grow(mask, 0)
    assert np.array_equal(out, mask) and out is not mask
    with pytest.raises(ValueError, match="cells"):
        grow(mask, -1)
    with pytest.raises(ValueError, match="2-D"):
        grow(np.ones(3, bool))


@pytest.mark.parametrize("building", ["intel", "fr079_albertB"])
@pytest.mark.parametrize("max_size", [0, 1, 4, 30])
def test_drop_small_removes_what_skimage_removes(shared, building: str, max_size: int) -> None:
    morphology = pytest.importorskip("skimage.morphology")
    if "max_size" not in inspect.signature(morphology.remove_small_objects).parameters:
        pytest.skip("scikit-image < 0.26 has no max_size to compare with")
    path = sorted((shared / "maps" / building).glob("*.yaml"))[0]
    free = read_map(path).probability() < 0.3
    expected = morphology.remove_small_objects(free, max_size=max_size)
    np.testing.assert_array_equal(drop_small(free, max_size), expected)
    holes = morphology.remove_small_holes(free, max_size=max_size)
    np.testing.assert_array_equal(~drop_small(~free, max_size), holes)


@settings(max_examples=60)
@given(mask=arrays(bool, st.tuples(st.integers(1, 24), st.integers(1, 24))))
def test_surface_is_the_mask_less_its_erosion(mask):
    # the edge counts as inside: erode with a border of True
    cross = ndi.generate_binary_structure(2, 1)
    expected = mask & ~ndi.binary_erosion(mask, cross, border_value=1)
    assert np.array_equal(surface(mask), expected)


def test_surface_of_a_thick_wall_is_its_two_faces():
    wall = np.zeros((9, 12), bool)
    wall[3:8, :] = True  # five cells thick, running off both ends
    faces = surface(wall)
    assert np.array_equal(np.flatnonzero(faces.any(axis=1)), [3, 7])
    assert faces[3].all() and faces[7].all()
    with pytest.raises(ValueError, match="2-D"):
        surface(np.ones(3, bool))
