"""Eq. (34), log-odds to probability, computed in float32: the float32 nearest the exact value."""

from __future__ import annotations

import warnings

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pgvd.grid import logodds_to_probability, probability_to_logodds
from pgvd.io import read_map

logodds = arrays(
    np.float32,
    st.integers(0, 70_000),  # beyond one 32768-cell chunk of the conversion
    elements=st.floats(width=32, allow_nan=False),  # the whole float32 range, and +-inf
)


@given(logodds)
def test_matches_the_float64_formula_to_float32_rounding(lo: np.ndarray) -> None:
    with np.errstate(over="ignore"):
        exact = 1.0 - 1.0 / (1.0 + np.exp(lo.astype(np.float64)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning from the extreme log-odds
        p = logodds_to_probability(lo)
    assert p.dtype == np.float32 and p.shape == lo.shape
    np.testing.assert_allclose(p, exact, rtol=2e-7, atol=1e-38)


def test_a_real_map_keeps_its_walls_free_space_and_unknown(shared) -> None:
    grid = read_map(shared / "maps" / "intel" / "intel.yaml")
    p = grid.probability()
    exact = 1.0 - 1.0 / (1.0 + np.exp(grid.logodds.astype(np.float64)))
    for threshold in (0.3, 0.65):  # the free and wall thresholds of the merge
        assert np.array_equal(p > threshold, exact > threshold)
    assert np.array_equal(p == 0.5, grid.logodds == 0)
    np.testing.assert_allclose(probability_to_logodds(p), grid.logodds, atol=1e-5)
