"""bench.studies.propagation's report: the gain of (8) by the composed pose's error."""

from __future__ import annotations

from bench.studies.propagation import by_error


def _chain(error_px: float, with_ce: float, without_ce: float, accepted: bool = True) -> dict:
    return {
        "accepted": accepted,
        "error": [error_px, 0.0, 0.0],
        "cross_entropy": {"with": {"all": with_ce}, "without": {"all": without_ce}},
    }


def test_by_error_bins_chains_by_translation_error():
    records = [
        _chain(0.2, 0.102, 0.100),  # right pose: the blur costs 2 %
        _chain(0.5, 0.101, 0.100),
        _chain(3.0, 0.090, 0.100),  # 3 px off: the blur gains 10 %
        _chain(9.0, 0.5, 0.1, accepted=False),  # not composed: not counted
    ]
    rows = by_error(records)
    assert rows[2] == "| 0-1 | 2 | -1.5 % | 0 |"
    assert rows[3] == "| 2 or more | 1 | 10.0 % | 1 |"
    assert len(rows) == 4  # no chain between 1 and 2 px: no row
