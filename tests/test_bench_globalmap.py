"""bench.globalmap: the fleets it rebuilds and the tables it writes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from bench.globalmap import Fleet, main


def test_a_robots_next_version_adds_its_last_scans_on_the_same_canvas(shared: Path) -> None:
    fleet = Fleet(shared / "logs" / "intel-corrected.log.gz", 3)
    assert [ln.pair for ln in fleet.links] == [("r01", "r02"), ("r01", "r03"), ("r02", "r03")]
    version, first = fleet.maps["r02"]
    fleet.next_version("r02")
    again, second = fleet.maps["r02"]
    assert again == version + 1 and second.shape == first.shape
    assert np.count_nonzero(second.logodds) > np.count_nonzero(first.logodds)


def test_the_command_writes_its_tables(shared: Path, tmp_path: Path) -> None:
    args = ["--robots", "3", "--logs", "intel", "--repeat", "1", "--shared", str(shared)]
    assert main([*args, "--out", str(tmp_path)]) == 0
    (row,) = json.loads((tmp_path / "globalmap.json").read_text())
    assert (row["log"], row["robots"], row["members"]) == ("intel", 3, 3)
    assert set(row["ratio_to_cold"]) == {
        "in_turn", "cold", "new_version", "unchanged", "re_solved", "moved"
    }  # fmt: skip
    assert row["re_solved_warps"] == 0  # a re-solve by a hair re-warps nobody
    # a real move re-warps the robots it moved, reusing their maps blurred in their frames
    assert row["moved_warps"] > 0 and row["moved_blurs"] < row["moved_warps"]
    assert row["held_mb"] > 0
    # every robot but the anchor blurred once cold, then again for its new version
    assert row["blur_causes"]["first"] == 2 and row["blur_causes"]["version"] == 1
    table = (tmp_path / "globalmap.md").read_text()
    assert "`python3 -m bench globalmap --robots 3 --logs intel --repeat 1`" in table
    assert "| intel | 3 |" in table


def test_a_missing_log_is_refused_in_one_line(tmp_path: Path, capsys) -> None:
    assert main(["--logs", "nowhere", "--shared", str(tmp_path), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no log" in err
