"""bench.ceiling: the true pose handed to the decision, and the report's counts."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from bench.ceiling import markdown, other_finalists, truth_at_decision
from bench.pairs import MapPair
from pgvd.grid import rigid_matrix
from pgvd.io import read_map
from pgvd.merge import MergeParams

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _example() -> MapPair:
    truth = np.asarray(json.loads((EXAMPLES / "truth.json").read_text())["matrix"])
    a, b = read_map(EXAMPLES / "intel_a.yaml"), read_map(EXAMPLES / "intel_b.yaml")
    return MapPair(a, b, truth, 0.78, "intel-example", {})


def test_the_truth_is_accepted_or_beaten_by_what_the_maps_say() -> None:
    pair, params = _example(), MergeParams(diagnostics=False)
    wrong = rigid_matrix(0.0, 100.0, 0.0) @ pair.truth  # 5 m off
    # the bundled pair's truth wins over a pose 5 m off, and clearly
    got = truth_at_decision(pair, [wrong], params)
    assert got["outcome"] == "accepted" and got["margin"] >= params.min_margin
    # handed a wrong "truth", the real pose among the others beats it
    liar = dataclasses.replace(pair, truth=wrong)
    assert truth_at_decision(liar, [pair.truth], params)["outcome"] == "beaten"
    # only finalists off the success bounds are others
    assert [m.tolist() for m in other_finalists(pair, [pair.truth, wrong])] == [wrong.tolist()]


def test_the_report_counts_each_outcome_per_set_and_names_the_gains() -> None:
    def row(pair: str, set_: str, run: bool, outcome: str, margin: float) -> dict:
        return {"pair": pair, "set": set_, "source": "s", "run": run, "outcome": outcome,
                "margin": margin}  # fmt: skip

    rows = [
        row("p0", "low", False, "accepted", 0.7),
        row("p1", "low", True, "accepted", 0.9),
        row("p2", "low", False, "below", 0.3),
        row("p3", "drifted", False, "beaten", 0.8),
    ]
    text = markdown(rows, MergeParams(), "cmd")
    assert "| low | 3 | 1 | 2 | 1 | 0 | 0.70 |" in text
    assert "| drifted | 1 | 0 | 0 | 0 | 1 | - |" in text
    assert "| **all** | 4 | 1 | 2 | 1 | 1 | 0.70 |" in text
    assert "would win (1): p0" in text
