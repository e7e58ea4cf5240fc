"""The heading search of the merge on real maps: Radon candidates refined on the overlay."""

from __future__ import annotations

import numpy as np
import pytest

from bench.capture import Finalists
from pgvd.grid import Grid, heading, relative_matrix, rigid_matrix
from pgvd.heading_search import known_box, with_refined
from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.overlay import MapView, OverlayScores, OverlayWeights
from pgvd.params import MergeParams
from pgvd.pooling import coarsen
from pgvd.rotation import HeadingCandidate
from pgvd.transform import warp

#: The refinement as measured on the bench (off by default, see MergeParams.heading_span).
ON = MergeParams(heading_span=6.0, heading_step=3.0)


@pytest.fixture(scope="module")
def intel_parts(shared):
    """Coarse (0.2 m) A and B of the intel split, B turned by a known heading."""
    a = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    truth = relative_matrix(a, b)
    pb = b.probability()
    h, w = pb.shape
    side = int(np.ceil(np.hypot(h, w))) + 4
    turn = rigid_matrix(np.radians(37.0), 0.0, 0.0)
    turn[:2, 2] = (side - 1) / 2.0 - turn[:2, :2] @ np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    turned = warp(pb, turn, (side, side), order=0, cval=0.5)
    k = round(0.2 / a.resolution)
    ca = coarsen(a.probability(), k)
    ca = ca[known_box(ca)]
    return ca, coarsen(turned, k), heading(truth @ np.linalg.inv(turn))


def _gap_deg(a: float, b: float) -> float:
    return abs(float(np.degrees(np.angle(np.exp(1j * (a - b))))))


@pytest.mark.parametrize("off_deg", [-5.0, 4.0])
def test_a_candidate_a_few_degrees_off_is_refined_to_the_truth(intel_parts, off_deg):
    ca, cb, psi = intel_parts
    start = HeadingCandidate(psi + np.radians(off_deg), 1e-4, 0.9)
    out = with_refined([start], ca, cb, ON)
    # the Radon candidate is kept, and the refined one is added within the 2 degrees of
    # heading recall (bench.studies.recall): 3 degree steps on 0.4 m cells place it no closer
    assert out[0] == start and len(out) == 2
    assert _gap_deg(out[1].psi, psi) <= 2.0 + 1e-9, np.degrees([out[1].psi, psi])
    assert out[1].variance == start.variance


def test_a_candidate_at_the_truth_stays_and_span_zero_turns_the_refinement_off(intel_parts):
    ca, cb, psi = intel_parts
    right = HeadingCandidate(psi, 1e-4, 0.9)
    assert with_refined([right], ca, cb, ON) == [right]
    off = HeadingCandidate(psi + np.radians(4.0), 1e-4, 0.9)
    assert with_refined([off], ca, cb, MergeParams(heading_span=0.0)) == [off]


#: Where map312 is cut (fractions of its height): the parts share 15 % of it.
CUT_A, CUT_B = 0.575, 0.425


@pytest.fixture(scope="module")
def map312_parts(shared):
    """Two parts of fr079_albertB's map312 sharing 15 % of its height, and B's true offset."""
    p = read_map(shared / "maps" / "fr079_albertB" / "map312.yaml").probability()
    h = p.shape[0]
    cut_a, cut_b = round(CUT_A * h), round(CUT_B * h)
    return p[:cut_a], p[cut_b:], cut_b


def _peak_rank(overlay, weights, t: tuple[int, int]) -> int:
    """Rank of ``t`` (within a coarse cell) among the overlay's peaks by ``weights``."""
    peaks = overlay.peaks(50, 12, weights)
    return next(i for i, (x, y) in enumerate(peaks, 1) if abs(x - t[0]) + abs(y - t[1]) <= 2)


def test_free_space_and_heavier_conflicts_rank_a_small_true_overlap_first(shared):
    # Two parts of fr079_albertB's map312 (coarse, 0.2 m) sharing 15 % of its height, a
    # stretch of corridor: walls alone prefer look-alike slides with more walls and a few
    # conflicts (MergeParams.search_conflict_weight's measurement).
    p = read_map(shared / "maps" / "fr079_albertB" / "map312.yaml").probability()
    c = coarsen(p, round(MergeParams().coarse_resolution / 0.05))
    c = c[known_box(c)]
    cut_a, cut_b = round(CUT_A * c.shape[0]), round(CUT_B * c.shape[0])
    overlay = OverlayScores(MapView(c[:cut_a], 0.65, 0.3, 1), free=True).overlay(
        MapView(c[cut_b:], 0.65, 0.3, 1)
    )
    walls = OverlayWeights(MergeParams().disagreement_weight)
    assert _peak_rank(overlay, walls, (0, cut_b)) > 1
    assert _peak_rank(overlay, MergeParams().search_weights, (0, cut_b)) == 1


def test_no_search_finalist_where_both_rankings_agree(map312_parts):
    # This cut's true translation is the best by walls alone too: the option must then
    # add no rival to the decision and return the default's pose.
    pa, pb, cut_b = map312_parts
    a, b = Grid.from_probability(pa, 0.05), Grid.from_probability(pb, 0.05)
    truth = rigid_matrix(0.0, 0.0, float(cut_b))
    found = []
    for extra in (0, 4):
        finalists = Finalists()
        with finalists.watching():
            result = merge(a, b, MergeParams(diagnostics=False, search_finalists=extra))
        assert len(finalists.matrices) == 8
        assert result.accepted and np.abs(result.matrix - truth).max() < 1.0, result.reason
        found.append(result.matrix)
    np.testing.assert_allclose(found[0], found[1])
