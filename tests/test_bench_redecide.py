"""bench.studies.redecide: the decision replayed from a merge's finalists is the merge's own."""

from __future__ import annotations

import numpy as np
import pytest

from bench.capture import Finalists
from bench.studies.redecide import frontier, params_from, replay, split_margins, summary
from pgvd.decision import Decision, Scored, margin_against
from pgvd.io import read_map
from pgvd.merge import merge
from pgvd.overlay import Agreement
from pgvd.params import MergeParams


def test_params_from_reads_each_field_as_its_type():
    p = params_from(["min_margin=0.7", "finalists=5", "rho_veto=false", "drift_shift=0"])
    assert (p.min_margin, p.finalists, p.rho_veto, p.drift_shift) == (0.7, 5, False, 0.0)
    assert isinstance(p.finalists, int) and not p.diagnostics
    for bad in ("min_margin", "no_such_field=1", "finalists=many"):
        with pytest.raises(ValueError):
            params_from([bad])


def test_replay_gives_the_merges_decision(shared):
    a = read_map(shared / "maps" / "intel_split_gt" / "intel_partA.yaml")
    b = read_map(shared / "maps" / "intel_split_gt" / "intel_partB.yaml")
    params = MergeParams(diagnostics=False)
    finalists = Finalists()
    with finalists.watching():
        result = merge(a, b, params)
    assert result.accepted and len(finalists.matrices) > 1
    got = replay(a, b, [m.tolist() for m in finalists.matrices], params)
    assert got["accepted"] and got["margin"] == pytest.approx(result.margin, abs=1e-12)
    assert np.allclose(got["matrix"], result.matrix, atol=1e-9)
    # a stricter threshold rejects the same pose
    strict = params_from([f"min_margin={result.margin + 0.01}"])
    assert not replay(a, b, finalists.matrices, strict)["accepted"]


def test_summary_counts_right_wrong_and_false_accepts():
    rows = [
        {
            "pair": "s0",
            "set": "standard",
            "before": True,
            "right": True,
            "accepted": True,
            "margin": 1.0,
        },
        {
            "pair": "s1",
            "set": "standard",
            "before": False,
            "right": False,
            "accepted": True,
            "margin": 0.8,
        },
        {
            "pair": "n0",
            "set": "negative",
            "before": False,
            "right": False,
            "accepted": False,
            "margin": 0.5,
        },
    ]
    lines = summary(rows)
    assert lines[0] == "standard: 1/2 right and accepted (run: 1), 1 wrong accepts"
    assert lines[1] == "negative: 0/1 right and accepted (run: 0), 0 false accepts"
    assert lines[2] == "largest margin of a wrong or negative winner: 0.800 (s1)"


def _row(name: str, kind: str, right: bool, other: float, shift: float) -> dict:
    # a winner with 100 walls on walls and none on free space: its evidence is 100
    winner = Scored(np.eye(3), Agreement(100, 0))
    decision = Decision(winner, 0.0, other, shift)
    return {"pair": name, "set": kind, "right": right, "decision": decision}


def test_frontier_finds_the_best_pair_of_thresholds_on_the_split_margins():
    params = params_from(["margin_noise=0"])
    rows = [
        _row("close look-alike", "standard", True, 50.0, -np.inf),  # margins 0.5, no bound
        _row("corridor", "standard", True, 0.0, 60.0),  # 1.0, 0.4
        _row("bad", "negative", False, 40.0, 40.0),  # 0.6, 0.6
        _row("crisp", "standard", True, -np.inf, -np.inf),  # 1.0, 1.0: no rival at all
        _row("contradicted copies", "low", True, -np.inf, -40.0),  # no bound, 1.0 (as none)
    ]
    margins = split_margins(rows, params)
    assert margins.tolist() == [[0.5, np.inf], [1.0, 0.4], [0.6, 0.6], [1.0, 1.0], [np.inf, 1.0]]
    # the smaller split margin is the decision's own margin, against its larger rival
    for row, pair in zip(rows, margins, strict=True):
        d = row["decision"]
        assert min(pair) == pytest.approx(margin_against(d.winner, d.rival, 4.0, 0.0))
    # min_margin (0.57) on both accepts the crisp and the contradicted-copies pairs; either
    # margin may go lower as long as the other stays more than 0.03 above the bad
    # winner's 0.6, which gains one pair
    assert frontier(rows, params) == [
        "frontier (gap 0.03): at most 3 right accepts (standard 2, low 1, drifted 0), with "
        "t1 = 0.00 against other poses and t2 = 0.64 against shifted copies; min_margin "
        "0.57 on both accepts 2"
    ]
