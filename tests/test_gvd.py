"""GVD by morphology and the PGVD recursion, eqs. (13)-(24)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pgvd.gvd import contact_points, count_distribution, gvd, pgvd


def _brute_force(p: list[float]) -> np.ndarray:
    """P(N = k) by enumerating all 2^n occupied/free outcomes of the contact points."""
    n = len(p)
    out = np.zeros(n + 1)
    for outcome in itertools.product((0, 1), repeat=n):
        prob = np.prod([pj if o else 1.0 - pj for pj, o in zip(p, outcome, strict=True)])
        out[sum(outcome)] += prob
    return out


@settings(max_examples=60)
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=9))
def test_recursion_equals_enumeration(p):
    f = count_distribution(np.array([p]))[0]
    np.testing.assert_allclose(f, _brute_force(p), atol=1e-12)
    assert f.sum() == pytest.approx(1.0, abs=1e-12)  # Theorem 1


@settings(max_examples=30)
@given(st.integers(1, 9), st.integers(1, 40), st.integers(0, 2**31 - 1))
def test_vectorised_rows_are_independent_and_padding_is_neutral(n, s, seed):
    rng = np.random.default_rng(seed)
    p = rng.random((s, n))
    f = count_distribution(p)
    np.testing.assert_allclose(f.sum(axis=1), 1.0, atol=1e-12)
    padded = count_distribution(np.hstack([p, np.zeros((s, 2))]))
    np.testing.assert_allclose(padded[:, : n + 1], f, atol=1e-12)
    np.testing.assert_allclose(padded[:, n + 1 :], 0.0, atol=1e-12)
    row = int(rng.integers(s))
    np.testing.assert_allclose(f[row], _brute_force(list(p[row])), atol=1e-12)


@settings(max_examples=30)
@given(st.integers(0, 9), st.integers(1, 40), st.integers(0, 11), st.integers(0, 2**31 - 1))
def test_counts_up_to_max_count_are_the_whole_distributions_bit_for_bit(n, s, max_count, seed):
    rng = np.random.default_rng(seed)
    p = rng.random((s, n)) * (rng.random((s, n)) > 0.3)  # some contacts surely free
    whole = count_distribution(p)
    low = count_distribution(p, max_count=max_count)
    assert low.shape == (s, min(n, max_count) + 1)
    assert np.array_equal(low, whole[:, : low.shape[1]])


def test_invalid_probabilities_rejected():
    with pytest.raises(ValueError):
        count_distribution(np.array([[1.5]]))
    with pytest.raises(ValueError):
        count_distribution(np.array([0.5, 0.5]))
    with pytest.raises(ValueError, match="max_count"):
        count_distribution(np.array([[0.5]]), max_count=-1)


def _corridor(far_wall: float) -> np.ndarray:
    """A horizontal corridor, free rows 10..20, walls on rows 9 and 21 (p=0.9 / ``far_wall``)."""
    p = np.full((31, 80), 0.5)
    p[10:21, :] = 0.1
    p[9, :] = 0.9
    p[21, :] = far_wall
    return p


def test_gvd_of_corridor_is_its_centre_line():
    s = gvd(_corridor(0.9) < 0.3)
    rows, cols = np.nonzero(s)
    interior = (cols > 12) & (cols < 67)
    assert interior.sum() > 40
    assert np.all(rows[interior] == 15)


def test_contact_points_of_corridor_cells_lie_on_both_walls():
    free = _corridor(0.9) < 0.3
    cells = (np.full(5, 15), np.arange(30, 35))
    cr, _, valid = contact_points(free, cells)
    for i in range(5):
        assert set(cr[i][valid[i]]) == {9, 21}


def test_pgvd_in_unit_interval_and_lower_where_contacts_are_uncertain():
    s, sp = pgvd(_corridor(0.9))
    s_u, sp_u = pgvd(_corridor(0.5))  # far side is unknown instead of a wall
    assert sp.min() >= 0.0 and sp.max() <= 1.0
    assert np.all(sp[~s] == 0.0)
    centre = (slice(15, 16), slice(20, 60))
    assert np.all(s[centre]) and np.all(s_u[centre])
    # two certain walls: p = 0.9 * 0.9; one wall and unknown space: 0.9 * 0.5
    assert sp[centre].mean() == pytest.approx(0.81, abs=0.02)
    assert sp_u[centre].mean() == pytest.approx(0.45, abs=0.02)


def test_pgvd_on_real_map_is_lower_at_frontiers(shared):
    from pgvd.gvd import free_space
    from pgvd.io import read_map
    from pgvd.pooling import coarsen

    p = coarsen(read_map(shared / "maps/intel_split_gt/intel_partA.yaml").probability(), 4)
    s, sp = pgvd(p)
    assert s.sum() > 500
    assert sp.min() >= 0.0 and sp.max() <= 1.0
    assert np.all(sp[~s] == 0)
    cr, cc, valid = contact_points(free_space(p), np.nonzero(s))
    touches_unknown = np.any(valid & (np.abs(p[cr, cc] - 0.5) < 0.1), axis=1)
    touches_walls_only = np.all(~valid | (p[cr, cc] > 0.65), axis=1)
    assert touches_unknown.sum() > 50 and touches_walls_only.sum() > 50
    two = valid.sum(axis=1) >= 2
    # between two walls (p = 0.9 each) a cell is GVD with p >= 0.81; beside unknown space less
    assert sp[s][touches_walls_only & two].mean() > 0.8
    assert sp[s][touches_unknown].mean() < 0.5
    # a skeleton spur whose inscribed circle touches one obstacle only is not GVD: p = 0
    assert np.all(sp[s][~two] == 0)
