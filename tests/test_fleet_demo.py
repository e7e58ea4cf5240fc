"""``pgvd demo``, the README's first command, end to end (2 agents, fast replay)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from agent.launcher import ROOT

pytestmark = [pytest.mark.fleet, pytest.mark.slow]


def demo(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "agent.cli", "demo", *args]
    env = {"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=240)


def test_demo_agrees_links_truly_and_writes_its_outputs(tmp_path: Path) -> None:
    res = demo("--robots", "2", "--speed", "300", "--out", "out", cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["ok"] and report["same_global_map"] and report["false_links"] == []
    assert report["overlaps_to_link"] == ["r1-r2"] and report["missing_links"] == []
    for robot in ("r1", "r2"):
        agent = report["agents"][robot]
        assert agent["global_members"] == ["r1", "r2"] and agent["bytes_sent"] > 0
        (link,) = agent["links_accepted"]
        assert link["error_deg"] <= 2.0 and link["error_cells"] <= 3.0
        assert (tmp_path / "out" / robot / "global.png").stat().st_size > 1000
    assert (tmp_path / "out" / "side_by_side.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "OK: same global map True" in res.stdout


@pytest.mark.parametrize(
    ("args", "why"),
    [
        (["--robots", "1"], "--robots"),
        (["--max-deg", "-1"], "--max-deg and --max-cells must be > 0"),
        (["--min-overlap", "2"], "--min-overlap must be in (0, 1]"),
    ],
)
def test_demo_bad_input_is_one_line(tmp_path: Path, args: list[str], why: str) -> None:
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
