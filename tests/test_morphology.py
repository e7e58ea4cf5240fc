"""grow: the separable square dilation equals scipy's binary_dilation."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import ndimage as ndi

from pgvd.morphology import grow


@settings(max_examples=60, deadline=None)
@given(
    mask=arrays(bool, st.tuples(st.integers(1, 24), st.integers(1, 24))),
    cells=st.integers(1, 3),
)
def test_grow_equals_scipy_square_dilation(mask, cells):
    expected = ndi.binary_dilation(mask, np.ones((3, 3), bool), iterations=cells)
    assert np.array_equal(grow(mask, cells), expected)


def test_grow_zero_is_a_copy_and_bad_input_is_refused():
    mask = np.eye(4, dtype=bool)
    out = grow(mask, 0)
    assert np.array_equal(out, mask) and out is not mask
    with pytest.raises(ValueError, match="cells"):
        grow(mask, -1)
    with pytest.raises(ValueError, match="2-D"):
        grow(np.ones(3, bool))
