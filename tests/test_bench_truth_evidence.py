"""bench.truth_evidence: the acceptance statistic at the true pose, against the threshold."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from bench.sets import Entry
from bench.truth_evidence import (
    HEADING_STEPS,
    SHIFT_STEPS,
    around,
    bad_margins,
    main,
    reach,
    table,
    truth_margin,
)
from pgvd.merge import MergeParams, merge


def _rec(pair: str, set_: str, heading, margin, method: str = "pgvd") -> dict:
    return {
        "pair": pair,
        "method": method,
        "set": set_,
        "heading_deg": heading,
        "cell_err": None if heading is None else 1.0,
        "cell_tolerance": 3.0,
        "success": False,
        "result": {"margin": margin},
    }


def test_the_true_pose_scores_at_least_the_merges_winner_and_a_shift_scores_less(intel_split):
    params = MergeParams(diagnostics=False)
    result = merge(intel_split.a, intel_split.b, params)
    assert result.accepted
    at_truth = truth_margin(intel_split, params)
    # no rival at the truth: at least the merge's margin on its own (right) pose
    assert at_truth >= result.margin - 0.02
    assert at_truth >= params.min_margin
    moved = intel_split.truth.copy()
    moved[:2, 2] += 3.0 / intel_split.a.resolution  # 3 m off along x
    off = dataclasses.replace(intel_split, truth=moved)
    assert truth_margin(off, params) < params.min_margin


def test_around_turns_about_bs_centre_and_shifts_it_by_the_steps():
    matrix = np.array([[0.0, -1.0, 100.0], [1.0, 0.0, 20.0], [0.0, 0.0, 1.0]])
    centre = np.array([30.0, 40.0])
    poses = around(matrix, centre)
    assert len(poses) == len(HEADING_STEPS) * len(SHIFT_STEPS) ** 2
    landed = (matrix @ [*centre, 1.0])[:2]
    moves = {tuple(np.round((m @ [*centre, 1.0])[:2] - landed, 9)) for m in poses}
    assert moves == {(dx, dy) for dx in SHIFT_STEPS for dy in SHIFT_STEPS}
    turns = {round(float(np.degrees(np.arctan2(m[1, 0], m[0, 0])) - 90.0), 6) for m in poses}
    assert turns == set(HEADING_STEPS)
    assert any(np.allclose(m, matrix) for m in poses)


def test_bad_margins_are_wrong_or_negative_winners_with_a_margin():
    records = [
        _rec("right", "standard", 0.1, 0.9),
        _rec("wrong", "standard", 40.0, 0.4),
        _rec("neg", "negative", float("nan"), 0.5),
        _rec("no-winner", "negative", None, None),
        _rec("rejected-early", "low", None, 0.2),
        _rec("other-method", "negative", 1.0, 0.99, method="hough"),
    ]
    assert bad_margins(records, "pgvd") == [("wrong", 0.4), ("neg", 0.5), ("rejected-early", 0.2)]


def test_reach_counts_true_poses_at_the_threshold_and_above_the_worst_bad_margin():
    rows = [
        {"pair": f"s{i}", "set": "standard", "source": "x", "margin": m}
        for i, m in enumerate((0.9, 0.6, 0.55, -0.3))
    ] + [{"pair": "d0", "set": "drifted", "source": "x", "margin": 0.56}]
    got = {g.group: g for g in reach(rows, {"s0": True, "d0": False}, 0.57, 0.53)}
    std = got["standard"]
    assert (std.pairs, std.success, std.at_threshold, std.above_worst) == (4, 1, 2, 3)
    assert not std.reaches and got["drifted"].reaches  # 1/1 above 0.53 against 90 %
    assert "low" not in got and got["standard, x"].pairs == 4
    lines = table(list(got.values()), 0.57, 0.53, "pgvd")
    assert lines[0].startswith("| group | pairs | pgvd success | true pose >= 0.57")
    assert "| standard | 4 | 1/4 (25 %) | 2/4 (50 %) | 3/4 (75 %) | 97 % | no |" in lines


@pytest.mark.parametrize(
    "doc",
    [
        "not json",
        json.dumps({"runs": []}),
        json.dumps({"records": [1]}),
        json.dumps({"records": [{"method": "pgvd", "result": {"margin": 0.5}}]}),
        json.dumps({"records": [_rec("wrong", "standard", 40.0, 0.4), {"method": "pgvd"}]}),
    ],
)
def test_a_file_that_is_not_a_run_is_one_line_and_exit_2(tmp_path: Path, capsys, doc: str):
    run = tmp_path / "merge.json"
    run.write_text(doc)
    with pytest.raises(SystemExit) as exc:
        main([str(run), "--out", str(tmp_path / "out.md")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "merge.json" in err and "not a bench run" in err
    assert not (tmp_path / "out.md").exists()


def test_a_run_without_a_bad_winner_says_so(tmp_path: Path, capsys):
    run = tmp_path / "merge.json"
    right = {**_rec("right", "standard", 0.1, 0.9), "success": True}
    run.write_text(json.dumps({"records": [right]}))
    with pytest.raises(SystemExit) as exc:
        main([str(run)])
    assert exc.value.code == 2
    assert "no wrong or negative winner of pgvd" in capsys.readouterr().err


def test_main_measures_the_pairs_of_the_run_and_refuses_a_run_of_other_pairs(
    tmp_path: Path, capsys, monkeypatch, intel_split
):
    entry = Entry(intel_split, "intel-x", "intel", "standard", "overlap")
    monkeypatch.setattr("bench.truth_evidence.build", lambda *a, **k: [entry])
    out, png = tmp_path / "te.md", tmp_path / "te.png"
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"records": [_rec("wrong", "standard", 40.0, 0.4)]}))
    with pytest.raises(SystemExit) as exc:
        main([str(other), "--out", str(out)])
    assert exc.value.code == 2
    assert "1 of these pairs are not in the run (intel-split" in capsys.readouterr().err
    run = tmp_path / "merge.json"
    mine = {**_rec("intel-split", "standard", 0.1, 0.9), "success": True}
    run.write_text(json.dumps({"records": [mine, _rec("wrong", "standard", 40.0, 0.4)]}))
    assert main([str(run), "--out", str(out), "--png", str(png)]) == 0
    text = out.read_text()
    assert "largest margin of a wrong or negative winner of pgvd in the run is 0.40 (wrong)" in text
    row = "| standard, intel-x | 1 | 1/1 (100 %) | 1/1 (100 %) | 1/1 (100 %) | 90 % | yes |"
    assert row in text
    assert png.stat().st_size > 10_000
