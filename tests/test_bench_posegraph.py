"""bench.posegraph: one row of the sparse-against-dense table, and its bad options."""

from __future__ import annotations

import sys

import pytest

from bench import posegraph as bench
from pgvd import posegraph


def test_a_row_times_both_solvers_on_one_graph_and_restores_the_switch() -> None:
    held = posegraph.SPARSE_FROM
    row = bench.measure(6, 2.0, repeats=1)
    assert held == posegraph.SPARSE_FROM
    assert row["nodes"] == 6 and row["links"] == 12 and row["same_links_used"] is True
    assert row["max_difference_px"] < 1e-9
    assert row["sparse_over_dense"] > 0
    assert "| 6 | 12 |" in bench.table([row])


def test_bad_options_are_one_error_line(monkeypatch, capsys) -> None:
    monkeypatch.setattr(sys, "argv", ["posegraph", "--nodes", "1"])
    with pytest.raises(SystemExit) as exit_:
        bench.main()
    assert exit_.value.code == 2
    assert "--nodes must be >= 2" in capsys.readouterr().err
