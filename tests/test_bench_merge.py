"""A tiny run of bench/merge.py (every method, a few real pairs) so that the bench cannot rot.

Structure and sanity only: no timing is asserted.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("cv2")
pytest.importorskip("matplotlib")

from bench.data.pairs import make_pair
from bench.merge import errors, main, methods, upsample
from pgvd.carmen import read_carmen
from pgvd.grid import rigid_matrix


@pytest.fixture(scope="module")
def small_pair(shared):
    scans = read_carmen(shared / "logs" / "intel-corrected.log.gz")
    return make_pair(scans, (0.0, 0.4), (0.3, 0.7), seed=5, resolution=0.1)


@pytest.mark.slow
def test_tiny_bench_run(shared, tmp_path):
    argv = ["--quick", "--sources", "intel-log", "--methods", "pgvd", "hough", "exhaustive"]
    argv += ["--exhaustive-step", "3", "--no-scaling", "--out", str(tmp_path)]
    argv += ["--cache", str(tmp_path / "cache")]
    assert main(argv) == 0
    doc = json.loads((tmp_path / "merge.json").read_text())
    names = ["pgvd", "hough", "exhaustive"]
    assert "pgvd-det" in methods()  # MergeParams(probabilistic=False): the paper's Gamma_det
    assert list(doc["summary"]) == names
    pairs = {r["pair"] for r in doc["records"]}
    assert len(doc["records"]) == len(pairs) * len(names)
    sets = {r["set"] for r in doc["records"]}
    assert sets == {"standard", "low", "drifted", "negative"}
    for r in doc["records"]:
        assert r["seconds"] > 0 and r["source"] == "intel-log"
        if r["truth"] is not None:
            assert np.isfinite(r["cell_err"]) and 0 <= r["heading_deg"] <= 180
        assert not (r["success"] and r["set"] == "negative")
    for r in doc["records"]:
        if r["method"] == "pgvd":
            # Every MergeResult field but the images, and the headings that were searched.
            assert {"accepted", "matrix", "covariance", "score", "timings_ms"} <= set(r["result"])
            assert r["searched_deg"] and all(-180 <= d <= 180 for d in r["searched_deg"])
            assert len(r["searched_sigma_deg"]) == len(r["searched_deg"])
            # each finalist that reached the decision, judged against the truth
            # (bench.studies.recall)
            assert isinstance(r["finalist_success"], list)
            if r["overlap"] == 0:
                assert not any(r["finalist_success"])
    # The exhaustive reference finds the truth of an overlapping real pair.
    exhaustive = [r for r in doc["records"] if r["method"] == "exhaustive" and r["overlap"] > 0]
    assert any(r["success"] for r in exhaustive)
    table = (tmp_path / "merge.md").read_text()
    assert all(f"| {n} |" in table for n in names) and "| intel-log |" in table
    # what the run was measured with, so that two runs are compared only on the same libraries
    env = doc["environment"]
    assert env["libraries"]["numpy"] == np.__version__ and env["cpus"] >= 1
    assert f"numpy {np.__version__}" in table and "Python " in table
    assert (tmp_path / "merge.png").stat().st_size > 10_000


def test_errors_measure_heading_and_cells(small_pair):
    assert errors(small_pair, small_pair.truth) == (0.0, 0.0)
    heading, cell = errors(small_pair, small_pair.truth @ rigid_matrix(0.0, 3.0, 4.0))
    assert heading == pytest.approx(0.0, abs=1e-9) and cell == pytest.approx(5.0)
    heading, _ = errors(small_pair, rigid_matrix(np.radians(-2.0), 0, 0) @ small_pair.truth)
    assert heading == pytest.approx(2.0)


def test_upsample_keeps_the_truth(small_pair):
    up = upsample(small_pair, 2)
    assert up.a.shape == (2 * small_pair.a.shape[0], 2 * small_pair.a.shape[1])
    # The centre of B pixel p's 2x2 block lands on the centre of A pixel truth(p)'s block.
    p = np.array([10.0, 20.0, 1.0])
    q = small_pair.truth @ p
    block = np.array([2 * p[0] + 0.5, 2 * p[1] + 0.5, 1.0])
    np.testing.assert_allclose(up.truth @ block, [2 * q[0] + 0.5, 2 * q[1] + 0.5, 1.0])


def test_pgvd_det_column_fails_loudly_without_its_switch(monkeypatch):
    """pgvd-det is MergeParams(probabilistic=False); a core without it is an error, never a
    table that silently lacks the column."""
    import dataclasses
    import importlib

    @dataclasses.dataclass
    class WithoutSwitch:
        diagnostics: bool = True

    monkeypatch.setattr(importlib.import_module("pgvd.params"), "MergeParams", WithoutSwitch)
    with pytest.raises(TypeError, match="probabilistic"):
        methods()


def test_speed_table_gives_each_size_and_ratios_against_the_peers():
    from bench.tables import speed_table

    scaling = [
        {"method": "pgvd", "cells": 500, "seconds": 0.2, "cpu_seconds": 0.3},
        {"method": "hough", "cells": 500, "seconds": 0.4, "cpu_seconds": 0.6},
        {"method": "m-explore", "cells": 500, "seconds": 0.8, "cpu_seconds": 1.2},
        {"method": "pgvd", "cells": 1000, "seconds": 0.3},
        {"method": "hough", "cells": 1000, "seconds": 0.2},
    ]
    head, rule, small, large = speed_table(scaling)
    assert head == (
        "| cells | pgvd s | hough s | m-explore s | pgvd / hough | pgvd / m-explore "
        "| pgvd / hough (cpu) | pgvd / m-explore (cpu) |"
    )
    assert rule.count("---") == 8
    assert small == "| 500^2 | 0.20 | 0.40 | 0.80 | 0.50 | 0.25 | 0.50 | 0.25 |"
    # a method or a CPU time missing at a size gives a dash, not a ratio against nothing
    assert large == "| 1000^2 | 0.30 | 0.20 | - | 1.50 | - | - | - |"


def test_a_speckle_share_outside_0_to_1_is_refused(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--speckle", "1.5", "--no-scaling"])
    assert stop.value.code == 2
    assert "--speckle must be in [0, 1), got 1.5" in capsys.readouterr().err


def test_held_out_and_sources_together_are_refused(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--held-out", "--sources", "intel-log", "--no-scaling"])
    assert stop.value.code == 2
    assert "the held-out logs are not development sources" in capsys.readouterr().err
