"""bench.studies.greyzone: the grey zone and the first-try bar, read from a merge run."""

from __future__ import annotations

import json
from pathlib import Path

from bench.studies.greyzone import main

RUN = Path(__file__).resolve().parents[1] / "bench" / "results" / "merge.json"


def test_the_committed_run_gives_the_bar_no_bad_accept(capsys) -> None:
    assert main(["--merge", str(RUN)]) == 0
    text = capsys.readouterr().out
    assert "first-try bar (min_margin) 0.57, grey floor 0.0" in text, text
    assert "first-try false accepts: 0 of 163, 95 % upper bound 0.018" in text, text


def test_a_file_without_records_is_one_line_and_exit_2(tmp_path, capsys) -> None:
    bad = tmp_path / "run.json"
    bad.write_text(json.dumps({"summary": {}}))
    assert main(["--merge", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("greyzone: cannot read records") and "\n" not in err
