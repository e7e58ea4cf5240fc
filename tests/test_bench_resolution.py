"""bench.studies.resolution's report: counts per cell size, and bad arguments."""

from __future__ import annotations

import math

import pytest

from bench.studies.resolution import main, row


def _rec(overlap: float, accepted: bool, right: bool, margin: float) -> dict:
    return {
        "pair": "p",
        "overlap": overlap,
        "accepted": accepted,
        "right": right,
        "margin": margin,
        "error_m": 0.01 if right else 3.0,
        "seconds": 0.5,
    }


def test_row_counts_right_wrong_and_false_accepts() -> None:
    rows = [
        _rec(0.8, True, True, 0.9),
        _rec(0.6, True, True, 0.7),
        _rec(0.5, True, False, 0.6),  # accepted at a wrong pose
        _rec(0.4, False, False, math.nan),  # rejected before the decision
        _rec(0.0, True, False, 0.58),  # a false accept
        _rec(0.0, False, False, -0.4),
    ]
    cells = [c.strip() for c in row(0.025, rows).strip("|").split("|")]
    assert cells[:6] == ["0.025", "2/4", "1", "1/2", "0.70", "0.58"]
    assert cells[6] == "0.010"


def test_bad_resolution_is_one_clear_error(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        main(["--resolutions", "0", "0.05"])
    assert stop.value.code == 2
    assert "resolutions must be > 0" in capsys.readouterr().err
