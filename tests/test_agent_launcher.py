"""agent.launcher: the environment its agent processes run in."""

from __future__ import annotations

from pathlib import Path

import pytest

from agent.launcher import MALLOC_ARENA_MAX, LocalFleet, agent_env, wait_for

INTEL = Path(__file__).resolve().parents[1] / "agent" / "data" / "intel-corrected.log.gz"


def _environ(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode().split("=", 1) for item in raw if b"=" in item)


@pytest.mark.fleet
def test_a_launched_agent_runs_with_two_malloc_arenas(tmp_path: Path) -> None:
    if not Path("/proc/self/environ").exists():
        pytest.skip("no /proc")
    with LocalFleet("env", tmp_path, ["--speed", "200"]) as fleet:
        agent = fleet.add("r1", f"carmen:{INTEL}@0.0-0.2")
        assert wait_for(lambda: agent.status() is not None, 60), "the agent wrote no status"
        assert agent.proc is not None
        environ = _environ(agent.proc.pid)
    assert environ["MALLOC_ARENA_MAX"] == MALLOC_ARENA_MAX == "2"


def test_an_arena_count_set_by_the_caller_is_kept() -> None:
    env = agent_env({"MALLOC_ARENA_MAX": "4", "PATH": "/bin"})
    assert env["MALLOC_ARENA_MAX"] == "4"
    assert env["PATH"] == "/bin" and env["PYTHONUNBUFFERED"] == "1"
