"""Graph of the PGVD (Sec. IV-D): vertices, labelled edges, short edges dropped."""

from __future__ import annotations

import numpy as np
import pytest

from pgvd.graph import branch_count, build_graph


def _cross() -> np.ndarray:
    """A '+' skeleton: arms of 20 cells around (20, 20), plus a 3-cell spur off the right arm."""
    s = np.zeros((41, 50), bool)
    s[20, 0:41] = True
    s[0:41, 20] = True
    s[21:24, 32] = True  # short spur hanging off the right arm at column 32
    return s


def test_vertices_edges_and_short_edges_dropped():
    s = _cross()
    g = build_graph(s, s * 0.8, min_edge_length=5)
    vr, vc = np.nonzero(g.vertices)
    assert {(20, 20), (20, 32)} <= set(zip(vr.tolist(), vc.tolist(), strict=True))
    # the centre and the spur junction are the only branching places
    assert np.all((np.abs(vr - 20) <= 1) & ((np.abs(vc - 20) <= 1) | (np.abs(vc - 32) <= 1)))
    # S minus the 3x3-dilated vertices: left 0..18, up, down, right 22..30, 34..40; the
    # spur keeps 2 cells (rows 22-23) and is dropped
    lengths = sorted(e.length for e in g.edges)
    assert lengths == [7, 9, 19, 19, 19]
    assert g.labels.max() == 6
    for e in g.edges:
        assert e.confidence == pytest.approx(0.8)
        assert e.matrix.shape == (
            np.ptp(e.cells()[0]) + 1,
            np.ptp(e.cells()[1]) + 1,
        )  # the bounding box of eq. (25) is as small as possible
        assert np.all(g.labels[e.cells()] == e.label)


def test_staircase_line_has_no_vertex():
    s = np.zeros((12, 12), bool)
    for i in range(10):
        s[i, i] = s[i, i + 1] = True  # a thinned diagonal with staircase steps
    assert not np.any(branch_count(s)[s] > 2)
    g = build_graph(s, s.astype(float), min_edge_length=3)
    assert len(g.edges) == 1 and g.edges[0].length == 20


def test_shape_mismatch_rejected():
    with pytest.raises(ValueError):
        build_graph(np.zeros((4, 4), bool), np.zeros((4, 5)))
