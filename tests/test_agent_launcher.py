"""agent.launcher: the environment its agent processes run in."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest

from agent.launcher import (
    DEFAULT_EPHEMERAL,
    MALLOC_ARENA_MAX,
    LocalFleet,
    agent_env,
    ephemeral_range,
    free_port,
    wait_for,
)

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


def test_a_free_port_is_below_the_ephemeral_range_and_can_be_listened_on() -> None:
    """Outgoing connections take ephemeral ports; a port handed to an agent to listen on
    must not be one of them (at 16 agents one was, and the agent died)."""
    lo, _ = ephemeral_range()
    ports = {free_port() for _ in range(20)}
    assert all(1024 <= p < lo for p in ports), ports
    for port in ports:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", port))


@pytest.mark.parametrize("text", ["", "junk", "70000 80000", "5000", "60999 32768"])
def test_an_unreadable_ephemeral_range_falls_back_to_linux_default(tmp_path, text: str) -> None:
    path = tmp_path / "ip_local_port_range"
    path.write_text(text)
    assert ephemeral_range(path) == DEFAULT_EPHEMERAL
    assert ephemeral_range(tmp_path / "missing") == DEFAULT_EPHEMERAL
    path.write_text("40000\t50000\n")
    assert ephemeral_range(path) == (40000, 50000)
