"""bench/outcomes.py: the record-by-record comparison of two merge bench runs, on the
committed run's own records."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from bench.outcomes import compare_runs, main, pose_gap
from pgvd.grid import rigid_matrix

RUN = Path(__file__).resolve().parents[1] / "bench" / "results" / "merge.json"


@pytest.fixture(scope="module")
def records() -> list[dict]:
    return json.loads(RUN.read_text())["records"]


def test_a_run_agrees_with_itself(records):
    result = compare_runs(records, records, "pgvd", 1.0, 0.1)
    assert result.same
    assert result.compared == sum(r["method"] == "pgvd" for r in records) > 0


def test_a_flipped_outcome_and_a_moved_pose_are_listed(records):
    new = copy.deepcopy(records)
    ours = [r for r in new if r["method"] == "pgvd"]
    flipped = next(r for r in ours if not r["accepted"])
    flipped["accepted"] = True
    moved = next(r for r in ours if r["accepted"])
    moved["matrix"] = (rigid_matrix(0.0, 2.0, 0.0) @ np.array(moved["matrix"])).tolist()
    gone = ours[-1]
    new.remove(gone)
    result = compare_runs(records, new, "pgvd", 1.0, 0.1)
    assert [line.split()[0] for line in result.outcome] == [flipped["pair"]]
    assert [line.split(":")[0] for line in result.pose] == [moved["pair"]]
    assert result.missing == [gone["pair"]]


def test_pose_gap_measures_cells_and_degrees():
    m = rigid_matrix(np.radians(0.5), 3.0, 4.0)
    cells, degrees = pose_gap(np.eye(3), m, (100, 200))
    assert degrees == pytest.approx(0.5)
    assert cells >= 5.0


def test_cli_exit_codes(tmp_path, capsys):
    assert main([str(RUN), str(RUN)]) == 0
    assert "same outcomes and poses" in capsys.readouterr().out
    bad = tmp_path / "bad.json"
    bad.write_text("[]")
    assert main([str(RUN), str(bad)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_subset_run_is_compared_on_its_own_pairs(records):
    first = next(r for r in records if r["method"] == "pgvd")
    part = [r for r in records if r["source"] == first["source"]]
    assert compare_runs(records, part, "pgvd", 1.0, 0.1).missing
    result = compare_runs(records, part, "pgvd", 1.0, 0.1, subset=True)
    assert result.same and result.compared == sum(r["method"] == "pgvd" for r in part)
