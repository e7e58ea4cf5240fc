"""The heading search of the merge on real maps: Radon candidates refined on the overlay."""

from __future__ import annotations

import numpy as np
import pytest

from pgvd.grid import heading, relative_matrix, rigid_matrix
from pgvd.io import read_map
from pgvd.merge import MergeParams, _known_box, _with_refined, coarsen
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
    ca = ca[_known_box(ca)]
    return ca, coarsen(turned, k), heading(truth @ np.linalg.inv(turn))


def _gap_deg(a: float, b: float) -> float:
    return abs(float(np.degrees(np.angle(np.exp(1j * (a - b))))))


@pytest.mark.parametrize("off_deg", [-5.0, 4.0])
def test_a_candidate_a_few_degrees_off_is_refined_to_the_truth(intel_parts, off_deg):
    ca, cb, psi = intel_parts
    start = HeadingCandidate(psi + np.radians(off_deg), 1e-4, 0.9)
    out = _with_refined([start], ca, cb, ON)
    # the Radon candidate is kept, and the refined one is added within the 2 degrees of
    # heading recall (bench.recall): 3 degree steps on 0.4 m cells place it no closer
    assert out[0] == start and len(out) == 2
    assert _gap_deg(out[1].psi, psi) <= 2.0 + 1e-9, np.degrees([out[1].psi, psi])
    assert out[1].variance == start.variance


def test_a_candidate_at_the_truth_stays_and_span_zero_turns_the_refinement_off(intel_parts):
    ca, cb, psi = intel_parts
    right = HeadingCandidate(psi, 1e-4, 0.9)
    assert _with_refined([right], ca, cb, ON) == [right]
    off = HeadingCandidate(psi + np.radians(4.0), 1e-4, 0.9)
    assert _with_refined([off], ca, cb, MergeParams(heading_span=0.0)) == [off]
