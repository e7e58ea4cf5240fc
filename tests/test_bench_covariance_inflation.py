"""bench.covariance_inflation: two runs' outcomes compared and their covariances' growth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench.studies.covariance_inflation import changed_outcomes, factors, main, markdown
from pgvd.grid import rigid_matrix


def _record(name: str, cov: np.ndarray, accepted: bool = True, tx: float = 10.0) -> dict:
    truth = rigid_matrix(0.3, 10.0, -5.0)
    return {
        "pair": name,
        "method": "pgvd",
        "kind": "overlap",
        "accepted": accepted,
        "set": "standard",
        "source": "willow-sim",
        "building": "willow",
        "truth": truth.tolist(),
        "matrix": rigid_matrix(0.3, tx, -5.0).tolist(),
        "result": {"covariance": cov.tolist()},
        "heading_deg": 0.0,
        "cell_err": 0.0,
        "cell_tolerance": 3.0,
    }


def test_factors_are_the_most_and_least_growth_in_any_direction() -> None:
    before = np.array([np.diag([4.0, 1.0, 1e-4])])
    after = np.array([np.diag([4.0, 3.0, 2e-4])])
    most, least = factors(before, after)
    assert most == pytest.approx([3.0]) and least == pytest.approx([1.0])


def test_a_changed_outcome_is_named_and_left_out() -> None:
    cov = np.diag([4.0, 1.0, 1e-4])
    before = {n: _record(n, cov) for n in ("a", "b", "c")}
    after = {
        "a": _record("a", 2 * cov),
        "b": _record("b", cov, tx=11.0),
        "c": _record("c", cov, accepted=False),
    }
    assert changed_outcomes(before, after) == ["b", "c"]
    text = markdown(before, after, ("x.json", "y.json"))
    assert "2 with a different outcome (accepted or matrix): b, c." in text
    assert "| all | 1 | 2.00 | 2.00 | 2.00 | 2.0000 |" in text


def test_the_command_writes_its_report_and_refuses_a_bad_file(tmp_path: Path, capsys) -> None:
    cov = np.diag([4.0, 1.0, 1e-4])
    for name, scale in (("before", 1.0), ("after", 1.5)):
        doc = {"records": [_record("a", scale * cov)]}
        (tmp_path / f"{name}.json").write_text(json.dumps(doc))
    argv = ["--before", str(tmp_path / "before.json"), "--after", str(tmp_path / "after.json")]
    assert main(argv) == 0
    assert "| all | 1 | 1.50 |" in (tmp_path / "covariance-inflation.md").read_text()
    (tmp_path / "bad.json").write_text("{}")
    assert main(["--before", str(tmp_path / "bad.json"), "--after", argv[3]]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cannot read the merge records")
