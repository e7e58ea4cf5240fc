"""pgvd.sampling: the one subsampling rule every stage uses."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pgvd.sampling import subsample


@given(n=st.integers(0, 5000), cap=st.integers(1, 700))
def test_subsample_keeps_at_most_the_cap_and_spreads_evenly(n, cap):
    points = np.arange(2 * n).reshape(n, 2)
    kept = subsample(points, cap)
    assert len(kept) <= cap
    if n <= cap:
        assert np.array_equal(kept, points)
    else:
        stride = kept[1, 0] - kept[0, 0] if len(kept) > 1 else 2 * n
        # an even stride, and the kept rows reach the last stride of the set
        assert np.all(np.diff(kept[:, 0]) == stride)
        assert kept[-1, 0] >= 2 * n - stride


def test_subsample_refuses_a_cap_below_one():
    with pytest.raises(ValueError, match="max_points must be >= 1, got 0"):
        subsample(np.zeros((3, 2)), 0)
