"""Failpoints: no-ops unless armed; armed, they announce themselves and block for a kill -9."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from agent import failpoints
from agent.state import StateDir, StoredMap
from pgvd.grid import Grid

ROOT = Path(__file__).resolve().parents[1]
INTEL = ROOT / "agent" / "data" / "intel-corrected.log.gz"


def run(code: str, point: str, *args: str) -> subprocess.Popen:
    env = {**os.environ, failpoints.ENV: point}
    return subprocess.Popen(
        [sys.executable, "-c", code, *args],
        cwd=ROOT,
        env=env,
        stderr=subprocess.PIPE,
        text=True,
    )


def run_to_end(code: str, point: str, *args: str) -> subprocess.CompletedProcess:
    """``code`` run to its end with ``point`` armed (for points it must not reach)."""
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=ROOT,
        env={**os.environ, failpoints.ENV: point},
        capture_output=True,
        text=True,
        timeout=60,
    )


def first_line_then_kill(proc: subprocess.Popen) -> str:
    """The first stderr line of ``proc``, then make sure it is still blocked and kill -9 it."""
    assert proc.stderr is not None
    line = proc.stderr.readline()
    time.sleep(0.2)
    blocked = proc.poll() is None
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    assert blocked, "the process went on past its failpoint"
    assert proc.returncode == -signal.SIGKILL
    return line


def test_an_unarmed_failpoint_returns_at_once() -> None:
    assert failpoints.ARMED == ""  # the test suite itself never runs armed
    for name in failpoints.POINTS:
        failpoints.failpoint(name)  # returns: would block forever if armed
    failpoints.check_armed()


def test_an_armed_failpoint_announces_itself_and_blocks() -> None:
    code = "from agent.failpoints import failpoint; failpoint('tiles-send'); print('passed')"
    proc = run(code, "tiles-send")
    pid = proc.pid
    assert first_line_then_kill(proc) == f"FAILPOINT tiles-send {pid}\n"


def test_another_armed_point_does_not_stop_this_one() -> None:
    code = "from agent.failpoints import failpoint; failpoint('tiles-send')"
    proc = run_to_end(code, "state-write")
    assert proc.returncode == 0 and proc.stderr == ""


def test_an_unknown_failpoint_is_refused_by_the_agent_cli(tmp_path: Path) -> None:
    argv = ["agent", "--robot", "r1", "--source", f"carmen:{INTEL}", "--state-dir", str(tmp_path)]
    code = "import sys; from agent.cli import main; sys.exit(main())"
    proc = run_to_end(code, "state-wrte", *argv)
    assert proc.returncode == 2
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "state-wrte" in lines[0] and "state-write" in lines[0], lines


WRITER = """
import sys
import numpy as np
from agent.state import StateDir, StoredMap
from pgvd.grid import Grid
lo = np.full((200, 300), 2.5, dtype=np.float32)
grid = Grid(lo, 0.05, (0.0, 0.0, 0.0))
StateDir(sys.argv[1]).save_map("r1", StoredMap(2, grid), point="state-write")
"""


def test_kill_9_at_state_write_leaves_the_old_map_whole(tmp_path: Path) -> None:
    old = Grid(np.linspace(-3, 3, 40 * 50, dtype=np.float32).reshape(40, 50), 0.1, (1.0, 2.0, 0.0))
    StateDir(tmp_path).save_map("r1", StoredMap(1, old, {"cursor": 5}))
    proc = run(WRITER, "state-write", str(tmp_path))
    assert first_line_then_kill(proc).startswith("FAILPOINT state-write ")
    maps_dir = tmp_path / "maps"
    temporaries = [p for p in maps_dir.iterdir() if p.name.startswith(".r1.npz.")]
    assert len(temporaries) == 1 and temporaries[0].stat().st_size > 0  # half a copy on disk
    state = StateDir(tmp_path)  # the next start removes it and reads the old file whole
    assert state.removed_temporaries == [temporaries[0].name]
    assert sorted(p.name for p in maps_dir.iterdir()) == ["r1.npz"]
    maps, errors = state.load_maps()
    assert errors == [] and maps["r1"].version == 1 and maps["r1"].extra == {"cursor": 5}
    np.testing.assert_array_equal(maps["r1"].grid.logodds, old.logodds)


def test_state_write_stops_only_writes_that_name_it(tmp_path: Path) -> None:
    # a peer's map is saved without the point: an agent armed for its own map passes these
    code = WRITER.replace(', point="state-write"', "")
    proc = run_to_end(code, "state-write", str(tmp_path))
    assert proc.returncode == 0 and proc.stderr == ""
    assert StateDir(tmp_path).load_maps()[0]["r1"].version == 2
