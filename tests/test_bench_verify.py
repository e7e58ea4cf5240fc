"""bench.verify: the predictions a pair is checked at, and how the report counts the checks."""

from __future__ import annotations

import numpy as np

from bench.verify import (
    WRONG_SHIFT_M,
    WRONG_TURNS_DEG,
    markdown,
    predictions,
    wall_centre,
)
from pgvd.grid import heading
from pgvd.params import MergeParams


def _where(pair, matrix: np.ndarray) -> tuple[float, float]:
    """How far ``matrix`` puts B's wall centroid from the truth (m), and its turn (deg)."""
    centre = np.append(wall_centre(pair, MergeParams()), 1.0)
    shift = float(np.hypot(*((matrix - pair.truth) @ centre)[:2])) * pair.a.resolution
    turn = np.degrees(np.angle(np.exp(1j * (heading(matrix) - heading(pair.truth)))))
    return shift, float(turn)


def test_predictions_are_near_or_wrong_as_named(intel_split):
    rng = np.random.default_rng(0)
    record = {"matrix": np.eye(3).tolist()}
    near, turns = [], set()
    for _ in range(40):
        kinds = dict(predictions(intel_split, record, rng, 0.5, 3.0))
        assert sorted(kinds) == ["near", "shifted", "turned"]
        near.append(_where(intel_split, kinds["near"]))
        shift, turn = _where(intel_split, kinds["shifted"])
        assert WRONG_SHIFT_M[0] <= shift <= WRONG_SHIFT_M[1] and abs(turn) < 1e-9
        shift, turn = _where(intel_split, kinds["turned"])
        assert shift < 1e-6  # turned about B's wall centroid: it stays where it belongs
        turns.add(round(turn) % 360)
    shifts, degrees = np.array(near).T
    # N(0, 0.5 m) per axis: |shift| is Rayleigh, mean 0.5 * sqrt(pi / 2) = 0.63 m
    assert 0.45 < shifts.mean() < 0.8
    assert 2.0 < degrees.std() < 4.0
    assert turns == {round(t) % 360 for t in WRONG_TURNS_DEG}


def test_a_negative_is_checked_where_the_search_put_it(intel_split):
    lone = type(intel_split)(intel_split.a, intel_split.b, None, 0.0, "negative")
    record = {"matrix": [[1.0, 0.0, 5.0], [0.0, 1.0, -2.0], [0.0, 0.0, 1.0]]}
    ((kind, matrix),) = predictions(lone, record, np.random.default_rng(0), 0.5, 3.0)
    assert kind == "negative" and np.array_equal(matrix, np.asarray(record["matrix"]))


def test_report_counts_each_kind_and_names_the_false_links():
    rows = [
        {"pair": "p1", "source": "s", "set": "low", "kind": "near", "outcome": "right"},
        {"pair": "p1", "source": "s", "set": "low", "kind": "shifted", "outcome": "rejected"},
        {"pair": "p2", "source": "s", "set": "low", "kind": "near", "outcome": "wrong"},
        {"pair": "p2", "source": "s", "set": "low", "kind": "turned", "outcome": "false"},
        {"pair": "n1", "source": "s", "set": "negative", "kind": "negative", "outcome": "false"},
    ]
    for r, m in zip(rows, (0.8, -1.0, 0.7, 0.6, 0.9), strict=True):
        r.update(margin=m, seconds=0.05, reason="accepted")
    rows[1]["reason"] = "refinement left the prediction's basin: moved 3.10 m and 0.2 deg"
    rows.append({**rows[0], "outcome": "rejected", "reason": "overlap too small: 1.0 m"})
    text = markdown(rows, "python3 -m bench verify", 0.5, 3.0)
    assert "| low | 1/3 (33 %) | 1/3 (33 %) | 0/1 (0 %) | 1/1 (100 %) | - |" in text
    # only near predictions' rejections are told apart: a wrong one is meant to be rejected
    assert "| low | overlap too small | 1 |" in text and "basin" not in text
    assert "| negative | - | - | - | - | 1/1 (100 %) |" in text
    assert "Wrong poses and false links: 3 of 6 checks:" in text
    # the worst first
    assert text.index("n1 (negative): margin 0.90") < text.index("p2 (near): margin 0.70")
