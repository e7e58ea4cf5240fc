"""bench.studies.ceiling: the share of pairs whose true pose any method found, against the
targets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.studies.ceiling import by_pair, found, load, main, rows


def _rec(pair: str, method: str, right: bool, finalists=None, success=False, **kw) -> dict:
    return {
        "pair": pair,
        "method": method,
        "set": kw.get("set", "low"),
        "source": kw.get("source", "s"),
        "overlap": kw.get("overlap", 0.2),
        "heading_deg": 0.1 if right else 30.0,
        "cell_err": 1.0,
        "cell_tolerance": 3.0,
        "success": success,
        "finalist_success": finalists,
    }


def _run(path: Path, records: list[dict]) -> Path:
    path.write_text(json.dumps({"records": records}))
    return path


def test_a_pose_is_found_returned_or_among_the_finalists():
    assert found(_rec("p", "pgvd", True))
    assert found(_rec("p", "pgvd", False, [False, True]))
    assert not found(_rec("p", "pgvd", False, [False]))
    assert not found(_rec("p", "exhaustive", False))
    no_key = _rec("p", "m-explore", False)
    del no_key["finalist_success"]
    assert not found(no_key)


def test_any_method_finding_a_pair_counts_once_and_negatives_are_left_out():
    records = [
        _rec("a", "pgvd", False, [True]),
        _rec("a", "exhaustive", True),
        _rec("b", "pgvd", False, [False]),
        _rec("b", "exhaustive", True),
        _rec("c", "pgvd", True, [True], success=True),
        _rec("d", "pgvd", False, [False]),
        _rec("d", "pgvd-heading", False, [False, True]),  # another method's finalist
        _rec("e", "pgvd", False, [False]),
        _rec("n", "pgvd", True, overlap=0.0),
    ]
    pairs = by_pair(records)
    assert sorted(pairs) == ["a", "b", "c", "d", "e"]
    low = next(r for r in rows(pairs) if r.startswith("| low "))
    # pgvd succeeds on 1 and finds 2 (a, c); with the other methods, 4 of 5 reach 60 %
    assert low == "| low | 5 | 1/5 (20 %) | 2/5 (40 %) | 4/5 (80 %) | 60 % | yes |"


def test_standard_pairs_get_a_row_per_building_against_its_own_target():
    records = [_rec(f"p{i}", "pgvd", i < 9, set="standard", source="x") for i in range(10)]
    table = rows(by_pair(records))
    assert "| standard | 10 | 0/10 (0 %) | 9/10 (90 %) | 9/10 (90 %) | 97 % | no |" in table
    assert "| standard, x | 10 | 0/10 (0 %) | 9/10 (90 %) | 9/10 (90 %) | 90 % | yes |" in table


def test_the_command_prints_the_table_of_the_runs_given_and_draws_it(tmp_path: Path, capsys):
    one = _run(tmp_path / "one.json", [_rec("a", "pgvd", False, [False])])
    two = _run(tmp_path / "two.json", [_rec("a", "exhaustive", True)])
    png = tmp_path / "ceiling.png"
    assert main([str(one), str(two), "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "| low | 1 | 0/1 (0 %) | 0/1 (0 %) | 1/1 (100 %) | 60 % | yes |" in out
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f"`{png}`" in out


@pytest.mark.parametrize(
    ("runs", "args", "said"),
    [
        ([None], [], "not a bench run's merge.json"),
        ([{"records": {"a": 1}}], [], "records is not a list of objects"),
        ([{"records": [{"pair": "a"}]}], [], "a record without method, set"),
        ([[_rec("n", "pgvd", True, overlap=0.0)]], [], "no overlapping pair"),
        ([[_rec("a", "pgvd", True)], [_rec("a", "pgvd", True)]], [], "recorded twice for a"),
        ([[_rec("a", "pgvd", True)]], ["--method", "pgvd-x"], "--method pgvd-x: not in the runs"),
    ],
)
def test_bad_input_is_one_error_line_and_exit_2(tmp_path: Path, capsys, runs, args, said):
    paths = []
    for i, run in enumerate(runs):
        path = tmp_path / f"run{i}.json"
        if run is None:
            path.write_text("{not json")
        else:
            path.write_text(json.dumps(run if isinstance(run, dict) else {"records": run}))
        paths.append(str(path))
    with pytest.raises(SystemExit) as exc:
        main([*paths, *args])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert said in err[-1], err


def test_load_keeps_every_run_s_records(tmp_path: Path):
    one = _run(tmp_path / "one.json", [_rec("a", "pgvd", True), _rec("b", "pgvd", False)])
    two = _run(tmp_path / "two.json", [_rec("a", "hough", True)])
    assert [(r["pair"], r["method"]) for r in load([one, two])] == [
        ("a", "pgvd"),
        ("b", "pgvd"),
        ("a", "hough"),
    ]
