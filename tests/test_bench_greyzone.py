"""bench.studies.greyzone: the grey zone's bounds from the development merge bench."""

from __future__ import annotations

from pathlib import Path

from bench.studies.greyzone import main, upper_bound

MERGE = Path(__file__).resolve().parents[1] / "bench" / "results" / "merge.json"


def test_the_study_prints_the_bar_its_false_accepts_and_their_bound(capsys) -> None:
    assert main(["--merge", str(MERGE)]) == 0
    out = capsys.readouterr().out
    assert "first-try false accepts: 0 of " in out, out
    assert "bad winners in the grey zone [0.0, 0.57)" in out, out


def test_the_bound_of_zero_in_n_is_about_the_rule_of_three() -> None:
    assert abs(upper_bound(0, 163) - 3 / 163) < 0.001
    assert upper_bound(5, 5) == 1.0


def test_a_missing_run_is_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    assert main(["--merge", str(tmp_path / "none.json")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_the_first_try_bar_of_the_committed_run_and_its_bound(capsys) -> None:
    assert main(["--merge", str(MERGE)]) == 0
    out = capsys.readouterr().out
    assert "first-try bar (min_margin) 0.57, grey floor 0.0" in out, out
    assert "first-try false accepts: 0 of 163, 95 % upper bound 0.018" in out, out


def test_a_file_without_records_is_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    bad = tmp_path / "run.json"
    bad.write_text('{"summary": {}}')
    assert main(["--merge", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("greyzone: cannot read records") and err.count("\n") == 1
