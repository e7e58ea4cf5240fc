"""bench.studies.recall: heading recall, pose recall and the heading-sigma check of a bench
record."""

from __future__ import annotations

import numpy as np

from bench.studies.recall import heading_z, pose_recall, recall, sigma_line, table
from bench.tables import MAX_HEADING_DEG, pose_right


def _record(success: bool, finalists: list[bool] | None, truth: float = 10.0) -> dict:
    return {
        "pair": f"p{truth}",
        "success": success,
        "finalist_success": finalists,
        "truth_heading_deg": truth,
        "searched_deg": [truth + 3.0, -170.0 + truth],
        "searched_sigma_deg": [1.5, 0.5],
    }


def test_pose_recall_separates_the_search_from_the_decision():
    records = [
        _record(True, [False, True]),  # found and chosen
        _record(False, [True]),  # found, lost by the decision
        _record(False, [False, False]),  # never found
        _record(True, [False]),  # the winner's final refinement reached the truth
        _record(False, None),  # no finalists recorded: not counted
    ]
    assert pose_recall(records) == (3, 4, 1)


def test_heading_recall_and_sigma_read_the_nearest_searched_heading():
    rec = _record(False, [])
    assert recall([rec], tolerance=2.0)["misses"] == [("p10.0", 3.0)]
    assert recall([rec], tolerance=3.5)["hits"] == 1
    # the nearest searched heading is 3 degrees off with sigma 1.5: z = 2
    assert np.isclose(heading_z(rec), 2.0)
    # across the +-180 wrap, and a heading 170 degrees off is another mode: no z
    wrapped = {
        **rec,
        "truth_heading_deg": -179.0,
        "searched_deg": [179.0],
        "searched_sigma_deg": [0.5],
    }
    assert np.isclose(heading_z(wrapped), 4.0)
    assert heading_z({**rec, "searched_deg": [-160.0]}) is None
    assert "mean z^2 4.00" in sigma_line([rec]) and "within 2 sigma 100%" in sigma_line([rec])


def test_returned_pose_is_judged_by_the_success_bounds_accepted_or_not():
    ok = {"heading_deg": 0.5, "cell_err": 2.0, "cell_tolerance": 3.0, "accepted": False}
    assert pose_right(ok)
    assert not pose_right({**ok, "cell_err": 3.5})
    assert not pose_right({**ok, "heading_deg": MAX_HEADING_DEG + 0.1})
    # a method with no searched headings or finalists still gets its success and returned pose
    rows = table([{**_record(False, None), **ok, "set": "low", "source": "s"}], 2.0)
    assert rows[2].startswith("| low | 0/1 (0.0 %) | 1/1 (100.0 %) | - | - |")
