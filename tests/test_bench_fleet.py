"""bench.fleet: a log that cannot feed the fleet is refused in one line; results per log."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from bench.fleet import agreed, combined_table, disagreement_numbers, write_results
from bench.fleet_accuracy import Building

ROOT = Path(__file__).resolve().parents[1]


def bench(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "bench", "fleet", *args]
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--log", "no-such.log.gz"], "--log: log not found: no-such.log.gz"),
        (["--log", "."], "--log: log . is not a file"),
        (["--log", "notes.txt"], "notes.txt: no FLASER lines, not a CARMEN laser log"),
        (["--robots", "1"], "--robots must be at least 2"),
        (["--robots", "x"], "invalid int value: 'x'"),
        (["--keep", "."], "--keep must be a new or empty directory: ."),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(tmp_path: Path, args: list[str], why: str) -> None:
    (tmp_path / "notes.txt").write_text("not a laser log\n")
    res = bench(*args, "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0 and why in res.stderr
    assert not (tmp_path / "out").exists() and not res.stdout


def test_a_log_too_short_for_the_fleet_is_refused_before_any_agent(shared: Path, tmp_path):
    intel = shared / "logs" / "intel-corrected.log.gz"  # 910 scans: 33 robots get 54 each
    res = bench("--robots", "2", "40", "--log", str(intel), "--out", str(tmp_path), cwd=tmp_path)
    assert res.returncode == 2, res.stderr
    assert res.stderr.strip().count("\n") == 0
    assert "give 40 robots 44 each, at least 50 needed" in res.stderr
    assert "fleet of" not in res.stdout


def row(log: str, robots: int, agreement: float) -> dict:
    """A result row as :func:`bench.fleet.run_fleet` returns it, with made-up numbers."""
    return {
        "log": log, "robots": robots, "agreed": True, "agreement_s": agreement,
        "merges_per_agent": 4.0, "merge_s_mean": 0.5, "agreement_in_registrations": 2.0,
        "bytes_sent_per_robot": 30_000, "bytes_received_per_robot": 90_000,
        "messages_received_per_robot": 80, "cpu_s_per_agent": 2.0, "cpu_s_max_agent": 2.5,
        "cpu_pct_per_agent": 10.0, "rss_mb_per_agent": 180.0, "rss_mb_max_agent": 190.0,
        "uss_mb_per_agent": 120.0, "uss_mb_max_agent": 130.0, "searches": 8, "checks": 4,
        "epochs_per_robot": 4.0, "searches_per_epoch": 2.0, "checks_per_epoch": 1.0,
        "searches_per_epoch_per_robot": 0.5, "checks_per_epoch_per_robot": 0.25,
        "wall_s": 30.0, "largest_component": robots, "poll_s": 0.1, "bench_cpu_pct": 3.0,
        "load_before_after": [0.5, 1.0], "distinct_global_maps": 1, "final_maps_missing": 0,
    }  # fmt: skip


def test_each_log_has_its_results_and_one_table_holds_every_log(tmp_path: Path) -> None:
    fr079 = Building("log", tmp_path / "freiburg-079-corrected.log.gz")
    intel = Building("log", tmp_path / "intel-corrected.log.gz")
    write_results([row("freiburg-079", 4, 7.0)], "python3 -m bench fleet", fr079, "off", tmp_path)
    write_results([row("intel", 4, 12.0), row("intel", 8, 3.5)], "cmd", intel, "off", tmp_path)
    # a second run of one log replaces its rows, it does not add to them
    write_results([row("intel", 4, 11.0)], "cmd", intel, "off", tmp_path)
    assert [
        r["agreement_s"] for r in json.loads((tmp_path / "fleet-log-intel.json").read_text())
    ] == [11.0]
    assert (
        "# Fleet benchmark: freiburg-079 log"
        in (tmp_path / "fleet-log-freiburg-079.md").read_text()
    )
    table = (tmp_path / "fleet-logs.md").read_text()
    assert table.count("| freiburg-079 | 4 | yes | 7.0 |") == 1
    assert table.count("| intel | 4 | yes | 11.0 |") == 1 and "| 12.0 |" not in table
    assert not (tmp_path / "fleet.md").exists()


def test_the_combined_table_has_a_row_per_log_and_fleet_size() -> None:
    lines = combined_table(
        [row("intel", 8, 3.5), row("freiburg-079", 4, 7.0), row("intel", 4, 1.0)]
    )
    body = lines.splitlines()[2:]
    assert [r.split("|")[1:3] for r in body] == [
        [" freiburg-079 ", " 4 "],
        [" intel ", " 4 "],
        [" intel ", " 8 "],
    ]
    assert all(r.count("|") == lines.splitlines()[0].count("|") for r in body)


def test_a_fleet_that_did_not_agree_says_which_maps_never_arrived() -> None:
    def status(held: dict[str, int | None], own: int, digest: str) -> dict:
        robots = {r: {"version": v} for r, v in held.items()}
        return {"own_version": own, "robots": robots, "global": {"digest": digest}}

    st = {
        "r1": status({"r1": 5, "r2": 7, "r3": 2}, 5, "a"),
        "r2": status({"r1": None, "r2": 7, "r3": 2}, 7, "b"),  # r1's map never reached r2
        "r3": status({"r1": 4, "r2": 7, "r3": 2}, 2, "b"),  # r3 holds an older r1
    }
    out = disagreement_numbers(st)
    assert out == {"distinct_global_maps": 2, "final_maps_missing": 2}
    assert agreed(row("intel", 3, 1.0) | {"agreed": False} | out) == (
        "NO: 2 global maps, 2 final maps missing"
    )
