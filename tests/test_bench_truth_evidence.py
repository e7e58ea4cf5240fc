"""bench.studies.truth_evidence: the acceptance statistic at right poses, against the threshold."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from bench.data.sets import Entry
from bench.merge import upsample
from bench.studies.truth_evidence import (
    HEADING_STEPS,
    SHIFT_STEPS,
    around,
    bad_margins,
    check_run,
    main,
    reach,
    table,
    truth_margin,
)
from pgvd.merge import merge
from pgvd.params import MergeParams


def _rec(pair: str, set_: str, heading, margin, **kw) -> dict:
    return {
        "pair": pair,
        "method": kw.get("method", "pgvd"),
        "set": set_,
        "source": "x",
        "overlap": 0.0 if set_ == "negative" else 0.5,
        "heading_deg": heading,
        "cell_err": None if heading is None else 1.0,
        "cell_tolerance": 3.0,
        "success": kw.get("success", False),
        "truth": kw.get("truth"),
        "result": {"margin": margin},
    }


@pytest.fixture()
def no_build(monkeypatch):
    """Bad input must be refused before the bench's pairs are built (minutes)."""

    def refuse(*args, **kwargs):
        raise AssertionError("the bench was built for a run that should have been refused")

    monkeypatch.setattr("bench.studies.truth_evidence.build", refuse)


def test_the_bound_is_at_least_the_merges_own_margin_and_a_wrong_truth_scores_less(intel_split):
    params = MergeParams(diagnostics=False)
    result = merge(intel_split.a, intel_split.b, params)
    assert result.accepted
    bound = truth_margin(intel_split, params, (result.matrix,))
    # the merge's right pose is among those tried, and a rival only lowers a margin
    assert bound >= result.margin
    moved = intel_split.truth.copy()
    moved[:2, 2] += 3.0 / intel_split.a.resolution  # 3 m off along x
    off = dataclasses.replace(intel_split, truth=moved)
    assert truth_margin(off, params) < params.min_margin


def test_the_bound_is_measured_on_maps_pooled_as_the_decision_pools_them(intel_split):
    params = MergeParams(diagnostics=False)
    fine = upsample(intel_split, 2)  # 2.5 cm cells: the decision pools them 2x2
    assert abs(truth_margin(fine, params) - truth_margin(intel_split, params)) < 0.1


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


def test_bad_margins_are_pgvds_wrong_or_negative_winners_with_a_margin():
    records = [
        _rec("right", "standard", 0.1, 0.9),
        _rec("wrong", "standard", 40.0, 0.4),
        _rec("neg", "negative", float("nan"), 0.5),
        _rec("no-winner", "negative", None, None),
        _rec("other-method", "negative", 1.0, 0.99, method="hough"),
    ]
    assert bad_margins(records) == [("wrong", 0.4), ("neg", 0.5)]


def test_reach_counts_best_right_poses_and_the_threshold_each_target_needs():
    rows = [
        {"pair": f"s{i}", "set": "standard", "source": "x", "margin": m, "run_success": i == 0}
        for i, m in enumerate((0.9, 0.6, 0.55, -0.3))
    ] + [{"pair": "d0", "set": "drifted", "source": "x", "margin": 0.56, "run_success": False}]
    got = {g.group: g for g in reach(rows, 0.57, 0.53)}
    std = got["standard"]
    assert (std.pairs, std.success, std.at_threshold, std.above_worst) == (4, 1, 2, 3)
    assert std.needs == -0.3  # 97 % of 4 pairs is all 4: the worst of them
    assert got["drifted"].needs == 0.56 and got["drifted"].reaches
    assert not std.reaches and "low" not in got and got["standard, x"].pairs == 4
    lines = table(list(got.values()), 0.57, 0.53)
    assert lines[0].startswith("| group | pairs | pgvd success | best right pose >= 0.57")
    assert "| standard | 4 | 1/4 (25 %) | 2/4 (50 %) | 3/4 (75 %) | -0.30 | 97 % | no |" in lines


@pytest.mark.parametrize(
    ("doc", "says"),
    [
        ("not json", "not a bench run"),
        (json.dumps({"runs": []}), "not a bench run"),
        (json.dumps({"records": [1]}), "not a bench run"),
        (json.dumps({"records": [{"method": "pgvd", "result": {"margin": 0.5}}]}), "without"),
        (
            json.dumps(
                {
                    "records": [
                        {k: v for k, v in _rec("w", "low", 9.0, 0.4).items() if k != "success"}
                    ]
                }
            ),
            "a pgvd record without success",
        ),
        (json.dumps({"records": [_rec("right", "standard", 0.1, 0.9)]}), "no wrong or negative"),
        (json.dumps({"records": [_rec("odd", "standard", None, 0.9)]}), "NoneType"),
    ],
)
def test_a_file_that_is_not_a_usable_run_is_one_line_and_exit_2(
    tmp_path: Path, capsys, no_build, doc: str, says: str
):
    run = tmp_path / "merge.json"
    run.write_text(doc)
    with pytest.raises(SystemExit) as exc:
        main([str(run), "--out", str(tmp_path / "out.md")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "error:" in err and says in err
    assert not (tmp_path / "out.md").exists()


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["missing.json"], "not a bench run"),
        (["run", "--out", "no/such/dir/out.md"], "no directory"),
        (["run", "--png", "picture.jpg"], "must be a .png"),
        (["run", "--param", "no_such_field=1"], "no_such_field"),
    ],
)
def test_bad_arguments_are_refused_before_measuring(
    tmp_path: Path, capsys, no_build, monkeypatch, args: list[str], says: str
):
    monkeypatch.chdir(tmp_path)
    Path("run").write_text(json.dumps({"records": [_rec("wrong", "standard", 40.0, 0.4)]}))
    with pytest.raises(SystemExit) as exc:
        main([*args, "--out", "out.md"] if "--out" not in args else args)
    assert exc.value.code == 2
    assert says in capsys.readouterr().err


def test_a_run_of_other_pairs_or_altered_maps_is_refused(intel_split):
    entry = Entry(intel_split, "intel-x", "intel", "standard", "overlap")
    truth = intel_split.truth.tolist()
    mine = _rec("intel-split", "standard", 0.1, 0.9, truth=truth)
    plain = "python3 -m bench merge"
    assert check_run(plain, [mine], Path("r"), [entry]) == {"intel-split": mine}
    with pytest.raises(ValueError, match="no pgvd record of intel-split"):
        check_run(plain, [_rec("other", "standard", 0.1, 0.9)], Path("r"), [entry])
    other_seed = _rec("intel-split", "standard", 0.1, 0.9, truth=np.eye(3).tolist())
    with pytest.raises(ValueError, match="not this pair's"):
        check_run(plain, [other_seed], Path("r"), [entry])
    with pytest.raises(ValueError, match="altered maps"):
        check_run(plain + " --unknown free", [mine], Path("r"), [entry])


def test_main_measures_the_pairs_of_the_run_and_writes_report_table_and_picture(
    tmp_path: Path, capsys, monkeypatch, intel_split
):
    entry = Entry(intel_split, "intel-x", "intel", "standard", "overlap")
    monkeypatch.setattr("bench.studies.truth_evidence.build", lambda *a, **k: [entry])
    out, png = tmp_path / "te.md", tmp_path / "te.png"
    run = tmp_path / "merge.json"
    truth = intel_split.truth.tolist()
    # a run margin above every right pose's own: the bound would be broken, and says so
    mine = _rec("intel-split", "standard", 0.1, 0.99, success=True, truth=truth)
    run.write_text(json.dumps({"records": [mine, _rec("wrong", "standard", 40.0, 0.4)]}))
    assert main([str(run), "--out", str(out)]) == 0
    assert "Pairs the run accepted right above their bound: 1." in out.read_text()
    assert "accepted right above the bound: intel-split" in capsys.readouterr().err
    mine["result"]["margin"] = 0.6
    run.write_text(json.dumps({"records": [mine, _rec("wrong", "standard", 40.0, 0.4)]}))
    assert main([str(run), "--out", str(out), "--png", str(png)]) == 0
    text = out.read_text()
    assert "wrong or negative winner of pgvd in the run is 0.40 (wrong)" in text
    assert "Pairs the run accepted right above their bound: 0." in text
    assert "| standard, intel-x | 1 | 1/1 (100 %) | 1/1 (100 %) | 1/1 (100 %) |" in text
    assert "Scored with `--param`" not in text
    assert main([str(run), "--out", str(out), "--param", "min_margin=0.7"]) == 0
    assert "best right pose >= 0.70" in out.read_text()
    assert "Scored with `--param`" in out.read_text()
    rows = json.loads(out.with_suffix(".json").read_text())
    assert [r["pair"] for r in rows] == ["intel-split"] and rows[0]["margin"] >= 0.57
    assert png.stat().st_size > 10_000
