"""``pgvd demo``, the README's first command, end to end: real agent processes on localhost.

The runs are the bundled Intel log, the same log with a 10,000 s hole in its timestamps, and
simulated robots driving through the Intel map image; bad ``--log`` / ``--map`` inputs are
refused in one line before any agent starts.
"""

from __future__ import annotations

import argparse
import gzip
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agent.launcher import ROOT
from agent.scenario import LOG, MIN_SEGMENT_SCANS
from pgvd.grid import Grid
from pgvd.io import write_map

PNG = b"\x89PNG\r\n\x1a\n"
#: The hole cut into the timestamps of the gapped log, seconds.
GAP_S = 10_000.0


def demo(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "agent.cli", "demo", *args]
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=240)


def passed(res: subprocess.CompletedProcess, out: Path) -> dict:
    """The report of a demo that passed: every robot placed right, all agents agreeing."""
    assert res.returncode == 0, res.stdout + res.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["ok"] and report["verdict"] == "PASSED" and report["why"] == []
    assert report["same_global_map"] and report["dead_agents"] == []
    assert report["must_be_placed"]
    for robot in report["must_be_placed"]:
        p = report["placements"][robot]
        assert p["right"] and p["error_deg"] <= 2.0 and p["error_cells"] <= 3.0
    assert "PASSED: " in res.stdout
    return report


@pytest.mark.fleet
@pytest.mark.slow
def test_demo_places_both_robots_and_writes_its_outputs(tmp_path: Path) -> None:
    res = demo("--robots", "2", "--speed", "300", "--out", "out", cwd=tmp_path)
    report = passed(res, tmp_path / "out")
    assert report["overlaps_to_link"] == ["r1-r2"] and report["missing_links"] == []
    for robot in ("r1", "r2"):
        agent = report["agents"][robot]
        assert agent["global_members"] == ["r1", "r2"] and agent["bytes_sent"] > 0
        (link,) = agent["links_accepted"]
        assert link["error_deg"] <= 2.0 and link["error_cells"] <= 3.0
        assert (tmp_path / "out" / robot / "global.png").stat().st_size > 1000
        # the agents log what they do, not only what goes wrong
        log = (tmp_path / "out" / robot / "agent.log").read_text()
        assert f"agent {robot} up in fleet demo" in log
    assert (tmp_path / "out" / "side_by_side.png").read_bytes()[:8] == PNG


def _gapped_log(path: Path) -> None:
    """The bundled Intel log as plain text, its second half's scans :data:`GAP_S` later."""
    with gzip.open(LOG, "rt") as fh:
        lines = [ln for ln in fh if ln.startswith("FLASER")]
    out = []
    for i, line in enumerate(lines):
        tokens = line.split()
        if i >= len(lines) // 2:
            n = int(tokens[1])
            for k in (n + 8, n + 10):  # ipc_timestamp and logger_timestamp
                tokens[k] = f"{float(tokens[k]) + GAP_S:.6f}"
        out.append(" ".join(tokens) + "\n")
    path.write_text("".join(out))


@pytest.mark.fleet
@pytest.mark.slow
def test_demo_replays_a_gap_in_the_timestamps_without_waiting_it_out(tmp_path: Path) -> None:
    _gapped_log(tmp_path / "gapped.log")
    speed = 100.0
    t0 = time.monotonic()
    res = demo(
        "--log", "gapped.log", "--robots", "2", "--speed", str(speed), "--out", "out",
        cwd=tmp_path,
    )  # fmt: skip
    wall = time.monotonic() - t0
    passed(res, tmp_path / "out")
    # a replay that waited the gap out could not have finished before it passed
    assert wall < GAP_S / speed


@pytest.mark.fleet
@pytest.mark.slow
def test_demo_on_a_map_image_places_simulated_robots(tmp_path: Path, shared: Path) -> None:
    res = demo(
        "--map", str(shared / "maps" / "intel" / "intel.yaml"), "--robots", "3",
        "--speed", "100", "--out", "out", cwd=tmp_path,
    )  # fmt: skip
    report = passed(res, tmp_path / "out")
    assert report["agents"]["r1"]["global_members"] == ["r1", "r2", "r3"]
    assert "map intel.yaml" in res.stdout


def _write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _scans_only(path: Path, n: int) -> Path:
    with gzip.open(LOG, "rt") as fh:
        lines = [ln for ln in fh if ln.startswith("FLASER")][:n]
    path.write_text("".join(lines))
    return path


def _map(path: Path, free: tuple[slice, slice] | None) -> Path:
    """A 5 m square map image, all wall but ``free``."""
    logodds = np.full((100, 100), 4.0, np.float32)
    if free is not None:
        logodds[free] = -4.0
    write_map(path, Grid(logodds, 0.05))
    return path


BAD_RUNS = {
    "log missing": (lambda d: ["--log", str(d / "nope.log.gz")], "log not found"),
    "log a directory": (lambda d: ["--log", str(d)], "is not a file"),
    "log not CARMEN": (
        lambda d: ["--log", str(_write(d / "a.log", b"PARAM robot_length 0.5\n"))],
        "no FLASER lines",
    ),
    "log gzip corrupt": (
        lambda d: ["--log", str(_write(d / "cut.log.gz", LOG.read_bytes()[:4000]))],
        "corrupt gzip stream",
    ),
    "log too short": (
        lambda d: ["--log", str(_scans_only(d / "short.log", 60)), "--robots", "2"],
        f"at least {MIN_SEGMENT_SCANS} needed",
    ),
    "map missing": (lambda d: ["--map", str(d / "nope.yaml")], "map not found"),
    "map unreadable": (
        lambda d: ["--map", str(_write(d / "bad.yaml", b"image: gone.pgm\nresolution: 0.05\n"))],
        "bad.yaml",
    ),
    "map without free space": (lambda d: ["--map", str(_map(d / "w.yaml", None))], "no free space"),
    "map too small to drive": (
        lambda d: ["--map", str(_map(d / "s.yaml", np.s_[40:60, 40:60]))],
        "too small to drive",
    ),
    "log and map": (lambda d: ["--log", str(LOG), "--map", "m.yaml"], "not allowed with"),
}


@pytest.mark.parametrize("case", sorted(BAD_RUNS))
def test_demo_refuses_a_bad_run_in_one_line_before_starting(tmp_path: Path, case: str) -> None:
    args, why = BAD_RUNS[case]
    res = demo(*args(tmp_path), "--out", "out", cwd=tmp_path)
    assert res.returncode == 2, res.stdout + res.stderr
    assert res.stderr.strip().count("\n") == 0 and why in res.stderr, res.stderr
    assert not (tmp_path / "out").exists()  # no agent started, nothing written


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--robots", "1"], "--robots"),
        (["--max-deg", "-1"], "--max-deg and --max-cells must be > 0"),
        (["--min-overlap", "2"], "--min-overlap must be in (0, 1]"),
    ],
)
def test_demo_bad_option_is_one_line(tmp_path: Path, args: list[str], why: str) -> None:
    res = demo(*args, cwd=tmp_path)
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and why in res.stderr


def test_progress_counts_the_current_links_only() -> None:
    from agent.cli.demo import _progress

    link = {"a": "r1", "b": "r2", "accepted": True, "current": True}
    status = {
        "source": {"progress": [5, 10]},
        "robots": {"r1": {}, "r2": {}},
        "links": [link, {**link, "current": False}, {**link, "accepted": False}],
    }
    assert " links 1 " in _progress({"r1": status, "r2": None})


def _shift(dx: float) -> np.ndarray:
    return np.array([[1.0, 0.0, dx], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def _fleet_view(r3_error_px: float) -> tuple[dict, dict]:
    """Three robots along a corridor, each 5 cells on from the last; r1-r2 and r2-r3 linked
    rightly, r1-r3 not linked; the global map puts r3 ``r3_error_px`` cells off."""
    from agent.evaluate import true_matrix

    w2p = {"r1": _shift(0.0), "r2": _shift(-5.0), "r3": _shift(-10.0)}
    grids = {r: Grid(np.ones((20, 20), np.float32), 0.1) for r in w2p}
    truth = {r: true_matrix(w2p["r1"], w2p[r]) for r in w2p}
    links = [
        {
            "a": a, "b": b, "accepted": True, "current": True, "version_a": 1, "version_b": 1,
            "matrix": true_matrix(w2p[a], w2p[b]).tolist(), "score": 0.9, "decided_by": "r1",
        }
        for a, b in (("r1", "r2"), ("r2", "r3"))
    ]  # fmt: skip
    transforms = {r: (truth[r] @ _shift(r3_error_px if r == "r3" else 0.0)).tolist() for r in w2p}
    comp = {"anchor": "r1", "members": ["r1", "r2", "r3"], "transforms": transforms}
    status = {
        "source": {},
        "links": links,
        "components": [comp],
        "global": {"anchor": "r1", "digest": "d", "members": comp["members"]},
    }
    statuses = {
        r: {**status, "source": {"world_to_pixel": w2p[r].tolist()}} for r in ("r1", "r2", "r3")
    }
    return statuses, grids


def _verdict(r3_error_px: float) -> dict:
    from agent.cli.demo import evaluate

    statuses, grids = _fleet_view(r3_error_px)
    args = argparse.Namespace(max_deg=2.0, max_cells=3.0, min_overlap=0.3)
    return evaluate(statuses, grids, agreed_at=10.0, t_start=0.0, dead=[], args=args)


def test_a_pair_placed_right_through_a_third_robot_is_reported_not_failed() -> None:
    report = _verdict(0.0)
    assert report["ok"] and report["verdict"] == "PASSED" and report["why"] == []
    assert report["overlaps_to_link"] == ["r1-r2", "r1-r3", "r2-r3"]
    assert report["missing_links"] == ["r1-r3"]
    assert report["placements"]["r3"]["right"] and report["placements"]["r3"]["error_cells"] == 0


def test_a_misplaced_robot_fails_the_demo_with_its_error() -> None:
    report = _verdict(6.0)
    assert not report["ok"] and report["verdict"] == "FAILED"
    assert report["why"] == ["r3 misplaced by 0.0 deg, 6.0 cells"]
    from agent.cli.demo import _title

    assert _title(report)[0] == "FAILED: r3 misplaced by 0.0 deg, 6.0 cells"
    assert report["placements"]["r3"]["error_cells"] == pytest.approx(6.0)
    assert report["placements"]["r2"]["right"]
