"""bench.covariance_model_error: the term's weight by maximum likelihood, one building left out."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from bench.studies.covariance_model_error import fit_scale, main, model_terms, summary
from pgvd.grid import rigid_matrix

BASE = np.diag([1.0, 1.0, 1e-4])
TERM = np.diag([3.0, 3.0, 3e-4])


def _record(name: str, building: str, cov: np.ndarray, error: np.ndarray) -> dict:
    truth = rigid_matrix(0.3, 10.0, -5.0)
    return {
        "pair": name,
        "method": "pgvd",
        "kind": "overlap",
        "accepted": True,
        "set": "drifted",
        "source": f"{building}-sim",
        "building": building,
        "truth": truth.tolist(),
        "matrix": rigid_matrix(0.3 + error[2], 10.0 + error[0], -5.0 + error[1]).tolist(),
        "result": {"covariance": cov.tolist()},
        "heading_deg": 0.0,
        "cell_err": 0.0,
        "cell_tolerance": 3.0,
    }


def _runs(scale: float, n: int = 300) -> tuple[dict[str, dict], dict[str, dict]]:
    """Two runs of ``n`` poses whose errors are drawn from ``BASE + scale TERM``: without the
    term and with it at weight 2."""
    rng = np.random.default_rng(3)
    errors = rng.multivariate_normal(np.zeros(3), BASE + scale * TERM, size=n)
    buildings = ["intel", "willow", "avz"]
    before, after = {}, {}
    for i, e in enumerate(errors):
        name, building = f"p{i:03d}", buildings[i % 3]
        before[name] = _record(name, building, BASE, e)
        after[name] = _record(name, building, BASE + 2.0 * TERM, e)
    return before, after


@pytest.mark.parametrize("truth", [0.0, 1.5])
def test_the_weight_errors_were_drawn_with_is_found(truth: float) -> None:
    before, after = _runs(truth)
    records, errors, base, term = model_terms(before, after, 2.0)
    assert len(records) == 300 and term[0] == pytest.approx(TERM)
    assert fit_scale(errors, base, term) == pytest.approx(truth, abs=0.3)


def test_each_building_is_scored_with_a_weight_fitted_without_it() -> None:
    before, after = _runs(1.5)
    for name in ("p000", "p003"):  # two drifted poses, the rest standard
        for run in (before, after):
            run[name]["set"] = "standard"
    doc = summary(before, after, 2.0, 1.0)
    assert sorted(doc["leave_one_out"]) == ["avz", "intel", "willow"]
    for row in doc["leave_one_out"].values():
        assert row["all poses"]["scale"] == pytest.approx(1.5, abs=0.5)
        assert row["all poses"]["with"]["mean_nees"] < row["without"]["mean_nees"]
        assert row["in_use"]["mean_nees"] < row["without"]["mean_nees"]
    assert doc["leave_one_out"]["intel"]["drifted poses"]["with"]["n"] == 100
    assert doc["rows"]["standard"]["with"]["n"] == 2 and doc["changed"] == []


def test_a_changed_outcome_is_named_and_left_out(tmp_path: Path) -> None:
    before, after = _runs(1.5, n=30)
    after["p000"]["accepted"] = False
    for name, run in (("before", before), ("after", after)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"records": list(run.values())}))
    args = ["--before", str(tmp_path / "before.json"), "--after", str(tmp_path / "after.json")]
    assert main([*args, "--after-scale", "2"]) == 0
    text = (tmp_path / "covariance-model-error.md").read_text()
    assert "1 with a different outcome (accepted or matrix): p000." in text
    assert "| intel | 9 |" in text and "| willow | 10 |" in text and "| avz | 10 |" in text


def test_bad_input_is_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    missing = str(tmp_path / "none.json")
    assert main(["--before", missing, "--after", missing, "--after-scale", "1"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    before, after = _runs(0.0, n=6)
    for name, run in (("before", before), ("after", after)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"records": list(run.values())}))
    args = ["--before", str(tmp_path / "before.json"), "--after", str(tmp_path / "after.json")]
    assert main([*args, "--after-scale", "0"]) == 2
    assert "weight of the --after run must be > 0" in capsys.readouterr().err
