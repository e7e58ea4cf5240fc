"""bench.studies.oracle: the truth handed to one stage of a real merge, and the report of what
it buys."""

from __future__ import annotations

from unittest import mock

import numpy as np

from bench.merge import evaluate
from bench.studies.oracle import (
    _MERGE_MODULE,
    markdown,
    search_misses,
    true_finalist,
    with_truth,
)
from pgvd.merge import merge
from pgvd.params import MergeParams
from pgvd.rotation import estimate_headings


def test_with_truth_adds_the_heading_after_the_radon_candidates(intel_split):
    pa, pb = intel_split.a.probability(), intel_split.b.probability()
    radon = estimate_headings(pa, pb, 6)
    got = with_truth(1.0)(pa, pb, 6)
    assert [h.psi for h in got[:-1]] == [h.psi for h in radon] and got[-1].psi == 1.0
    # the merge takes it as a candidate: 1 rad is searched, and no Radon candidate is near it
    assert all(abs(np.angle(np.exp(1j * (h.psi - 1.0)))) > np.radians(5) for h in radon)
    with mock.patch.object(_MERGE_MODULE, "estimate_headings", with_truth(1.0)):
        result = merge(intel_split.a, intel_split.b, MergeParams(diagnostics=False))
    assert any(abs(d - np.degrees(1.0)) < 1e-6 for d in result.headings_deg)


def test_true_finalist_finds_the_supported_hypothesis_at_the_truth(intel_split):
    seen: dict = {}
    with true_finalist(intel_split, seen):
        result = merge(intel_split.a, intel_split.b, MergeParams(diagnostics=False))
    # the split maps merge right on their own: the truth's hypothesis is a finalist already
    assert seen["coarse_err"] < 2.0 and seen["was_finalist"]
    assert evaluate(intel_split, result.accepted, result.matrix)["success"]
    # and the merge's private functions are restored afterwards
    assert _MERGE_MODULE.choose_finalists.__name__ == "choose_finalists"


def test_search_misses_selects_pose_not_found_at_a_searched_heading():
    base = {"set": "low", "success": False, "truth_heading_deg": 10.0, "searched_deg": [10.5]}
    assert search_misses({**base, "finalist_success": [False, False]})
    assert not search_misses({**base, "finalist_success": [False, True]})
    assert not search_misses({**base, "searched_deg": [14.0], "finalist_success": [False]})
    assert not search_misses({**base, "set": "negative", "finalist_success": []})


def _row(
    pair: str, set_: str, success: bool, accepted: bool, before: bool = False, **extra
) -> dict:
    return {
        "before": before,
        "pair": pair,
        "set": set_,
        "gap": 4.0,
        "margin": 0.8 if accepted else -0.2,
        "success": success,
        "accepted": accepted,
        "heading_deg": 0.8,
        "cell_err": 11.0,
        "cell_tolerance": 7.0,
        **extra,
    }


def test_markdown_counts_right_and_wrong_per_set():
    rows = [
        _row("s0", "standard", True, True),
        _row("s1", "standard", True, True, before=True),
        _row("d0", "drifted", False, True),
        _row("d1", "drifted", False, False),
    ]
    text = markdown(rows, "heading", "python3 -m bench oracle")
    assert "| drifted | 2 | 0 | 0 | 0 | 1 |" in text
    assert "| standard | 2 | 1 | 2 | 1 | 0 |" in text
    assert "accepted, wrong (0.80 deg, 11.0 cells, tolerance 7.0)" in text
    assert "| d1 | 4.0 | rejected | -0.20 |" in text
    rows = [
        _row("l0", "low", False, False, coarse_err=1.2, was_finalist=False),
        _row("l1", "low", True, True, coarse_err=0.4, was_finalist=False),
        _row("l2", "low", False, False, coarse_err=40.0, was_finalist=True),
    ]
    text = markdown(rows, "finalist", "python3 -m bench oracle --stage finalist")
    assert (
        "| low | 3 | 0 | 1 | 1 | 0 | 2 |" in text
        and "| l2 | 40.0 | yes | rejected | -0.20 |" in text
    )
