"""bench.ceiling: the share of pairs whose true pose any method found, against the targets."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.ceiling import by_pair, found, main, rows


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


def test_a_pose_is_found_returned_or_among_the_finalists():
    assert found(_rec("p", "pgvd", True))
    assert found(_rec("p", "pgvd", False, [False, True]))
    assert not found(_rec("p", "pgvd", False, [False]))
    assert not found(_rec("p", "exhaustive", False))


def test_any_method_finding_a_pair_counts_once_and_negatives_are_left_out():
    records = [
        _rec("a", "pgvd", False, [True]),
        _rec("a", "exhaustive", True),
        _rec("b", "pgvd", False, [False]),
        _rec("b", "exhaustive", True),
        _rec("c", "pgvd", True, [True], success=True),
        _rec("d", "pgvd", False, [False]),
        _rec("n", "pgvd", True, overlap=0.0),
    ]
    pairs = by_pair(records)
    assert sorted(pairs) == ["a", "b", "c", "d"]
    low = next(r for r in rows(pairs) if r.startswith("| low "))
    # pgvd succeeds on 1 and finds 2 (a, c); with the exhaustive run, 3 of 4 reach 60 %
    assert low == "| low | 4 | 1/4 (25 %) | 2/4 (50 %) | 3/4 (75 %) | 60 % | yes |"


def test_standard_pairs_get_a_row_per_building_against_its_own_target():
    records = [_rec(f"p{i}", "pgvd", i < 9, set="standard", source="x") for i in range(10)]
    table = rows(by_pair(records))
    assert "| standard | 10 | 0/10 (0 %) | 9/10 (90 %) | 9/10 (90 %) | 97 % | no |" in table
    assert "| standard, x | 10 | 0/10 (0 %) | 9/10 (90 %) | 9/10 (90 %) | 90 % | yes |" in table


def test_a_file_that_is_not_a_run_is_one_error_line(tmp_path: Path, capsys):
    bad = tmp_path / "merge.json"
    bad.write_text("{not json")
    with pytest.raises(SystemExit) as exc:
        main([str(bad)])
    assert exc.value.code == 2
    assert "not a bench run's merge.json" in capsys.readouterr().err
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps({"records": [_rec("n", "pgvd", True, overlap=0.0)]}))
    with pytest.raises(SystemExit):
        main([str(empty)])
    assert "no overlapping pair" in capsys.readouterr().err
