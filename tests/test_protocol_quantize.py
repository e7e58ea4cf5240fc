"""protocol.quantize: log-odds <-> int8 with a fixed scale; unknown stays 0, knowledge stays."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from pgvd.grid import LOGODDS_LIMIT
from protocol.quantize import SCALE, dequantise, quantise

logodds = hnp.arrays(
    np.float32,
    hnp.array_shapes(max_dims=2, max_side=30),
    elements=st.floats(-2 * LOGODDS_LIMIT, 2 * LOGODDS_LIMIT, width=32),
)


def test_every_step_survives_a_round_trip():
    q = np.arange(-127, 128, dtype=np.int8)
    assert np.array_equal(quantise(dequantise(q)), q)
    assert dequantise(np.array([127], np.int8))[0] == pytest.approx(LOGODDS_LIMIT)


@given(logodds)
def test_quantise_is_nearest_step_but_never_erases_knowledge(lo):
    q = quantise(lo)
    assert q.dtype == np.int8 and q.shape == lo.shape
    assert np.array_equal(q == 0, lo == 0)  # unknown stays unknown, knowledge stays
    assert np.array_equal(np.sign(q), np.sign(lo).astype(np.int8))
    inside = np.abs(lo) <= LOGODDS_LIMIT
    err = np.abs(dequantise(q) - np.clip(lo, -LOGODDS_LIMIT, LOGODDS_LIMIT))
    # Half a step of rounding, or up to one step where weak evidence is pushed to +-1.
    assert (err[inside & (np.abs(lo) >= SCALE / 2)] <= SCALE / 2 + 1e-5).all()
    assert (err <= SCALE + 1e-5).all()
    assert (np.abs(q) <= 127).all()


def test_tiny_evidence_becomes_one_step_and_extremes_saturate():
    lo = np.array([1e-30, -1e-30, 0.0, -0.0, 1e6, -1e6], np.float32)
    assert quantise(lo).tolist() == [1, -1, 0, 0, 127, -127]


def test_non_finite_and_wrong_dtype_are_refused():
    with pytest.raises(ValueError, match="finite"):
        quantise(np.array([0.0, np.nan], np.float32))
    with pytest.raises(ValueError, match="finite"):
        quantise(np.array([np.inf], np.float32))
    with pytest.raises(ValueError, match="int8"):
        dequantise(np.zeros(3, np.int16))
