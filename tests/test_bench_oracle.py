"""bench.oracle: the merge searches the true heading it is given, beside the Radon candidates."""

from __future__ import annotations

from unittest import mock

import numpy as np

from bench.oracle import _MERGE_MODULE, markdown, with_truth
from pgvd.io import read_map
from pgvd.merge import MergeParams, merge
from pgvd.rotation import estimate_headings


def test_with_truth_adds_the_heading_after_the_radon_candidates(shared):
    a = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    pa, pb = a.probability(), b.probability()
    radon = estimate_headings(pa, pb, 6)
    got = with_truth(1.0)(pa, pb, 6)
    assert [h.psi for h in got[:-1]] == [h.psi for h in radon] and got[-1].psi == 1.0
    # the merge takes it as a candidate: 1 rad is searched, and no Radon candidate is near it
    assert all(abs(np.angle(np.exp(1j * (h.psi - 1.0)))) > np.radians(5) for h in radon)
    with mock.patch.object(_MERGE_MODULE, "estimate_headings", with_truth(1.0)):
        result = merge(a, b, MergeParams(diagnostics=False))
    assert any(abs(d - np.degrees(1.0)) < 1e-6 for d in result.headings_deg)


def test_markdown_counts_right_and_wrong_per_set():
    rows = [
        {
            "pair": "s0",
            "set": "standard",
            "gap": 3.2,
            "margin": 0.9,
            "success": True,
            "accepted": True,
            "heading_deg": 0.1,
            "cell_err": 0.5,
            "cell_tolerance": 7.0,
        },
        {
            "pair": "d0",
            "set": "drifted",
            "gap": 5.0,
            "margin": 0.8,
            "success": False,
            "accepted": True,
            "heading_deg": 0.8,
            "cell_err": 11.0,
            "cell_tolerance": 7.0,
        },
        {
            "pair": "d1",
            "set": "drifted",
            "gap": 4.0,
            "margin": -0.2,
            "success": False,
            "accepted": False,
            "heading_deg": 40.0,
            "cell_err": 300.0,
            "cell_tolerance": 7.0,
        },
    ]
    text = markdown(rows, "python3 -m bench.oracle")
    assert "| drifted | 2 | 0 | 1 |" in text and "| standard | 1 | 1 | 0 |" in text
    assert (
        "accepted, wrong (0.80 deg, 11.0 cells, tolerance 7.0)" in text
        and "| d1 | 4.0 | rejected |" in text
    )
