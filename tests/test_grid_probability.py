"""Eq. (34), log-odds to probability, computed in float32: within a few float32 ulps of exact."""

from __future__ import annotations

import warnings

import numpy as np
from hypothesis import example, given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from pgvd.grid import logodds_to_probability, probability_to_logodds
from pgvd.io import read_map

logodds = arrays(
    np.float32,
    st.integers(0, 70_000),  # beyond one 32768-cell chunk of the conversion
    elements=st.floats(width=32, allow_nan=False),  # the whole float32 range, and +-inf
)


def _exact(lo: np.ndarray) -> np.ndarray:
    """Eq. (34) in float64, in the form ``1 / (1 + exp(-l))`` that does not cancel for l << 0."""
    return 1.0 / (1.0 + np.exp(-lo.astype(np.float64)))


@given(logodds)
# -24 failed a tolerance of one ulp; -37.08 is the sweep's worst; +-88.8 overflow exp
@example(np.array([-24.0, -37.08397, -88.8, 88.8], np.float32))
def test_matches_the_float64_formula_to_float32_rounding(lo: np.ndarray) -> None:
    with np.errstate(over="ignore"):
        exact = _exact(lo)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no overflow warning from the extreme log-odds
        p = logodds_to_probability(lo)
    assert p.dtype == np.float32 and p.shape == lo.shape
    # exp, the sum and the reciprocal each round: over a sweep of 2e7 log-odds in [-110, 110]
    # the largest error was 3.5 float32 ulps (2.4e-7 relative) on this machine's SIMD exp;
    # 5 ulps leaves room for numpy's other exp paths.  Subnormal p has absolute error.
    np.testing.assert_allclose(p, exact, rtol=6e-7, atol=1e-38)


def test_a_real_map_keeps_its_walls_free_space_and_unknown(shared) -> None:
    grid = read_map(shared / "maps" / "intel" / "intel.yaml")
    p = grid.probability()
    exact = _exact(grid.logodds)
    for threshold in (0.3, 0.65):  # the free and wall thresholds of the merge
        assert np.array_equal(p > threshold, exact > threshold)
    assert np.array_equal(p == 0.5, grid.logodds == 0)
    np.testing.assert_allclose(probability_to_logodds(p), grid.logodds, atol=1e-5)
