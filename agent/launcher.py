"""Start a fleet of agent processes on localhost, watch their status files, tear them down.

Used by ``pgvd demo``, the fleet tests and ``bench/fleet.py``.  Every agent is a real
``python -m agent.cli agent`` process (fork+exec: no Zenoh session crosses a fork) that
listens on its own free port and uses all earlier agents as seeds; gossip links the rest.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import random
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM it if the launcher dies (Linux), so that a
    killed demo or test run never leaves agents holding ports behind."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


#: Where the kernel says its ephemeral ports are (``lo hi``), and the range assumed without it.
EPHEMERAL_RANGE_FILE = Path("/proc/sys/net/ipv4/ip_local_port_range")
DEFAULT_EPHEMERAL = (32768, 60999)
#: How many ports below the ephemeral range :func:`free_port` draws from.
LISTEN_SPAN = 8192


def ephemeral_range(path: Path = EPHEMERAL_RANGE_FILE) -> tuple[int, int]:
    """The ports the kernel hands to outgoing connections, ``(lo, hi)``; Linux's default
    when ``path`` cannot be read or parsed."""
    try:
        lo, hi = (int(x) for x in path.read_text().split())
    except (OSError, ValueError):
        return DEFAULT_EPHEMERAL
    return (lo, hi) if 0 < lo <= hi < 65536 else DEFAULT_EPHEMERAL


def free_port() -> int:
    """A TCP port nobody listens on right now (the agent binds it a moment later), drawn
    below the kernel's ephemeral range.

    A port from ``bind(0)`` is an ephemeral one, and in the moment between this call and
    the agent binding it, the connections the agents already running open to each other
    take ephemeral ports too: at 16 agents one of them took the port handed to the next
    agent, which died with "Address already in use".  Below that range only listeners
    bind.  ``bind(0)`` is the fallback when no port there is free.
    """
    lo, _ = ephemeral_range()
    first = max(1024, lo - LISTEN_SPAN)
    rng = random.Random()
    for port in rng.sample(range(first, lo), min(64, lo - first)):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


#: glibc's malloc arenas per agent process. glibc gives each thread that allocates its own
#: arena, up to 8 per core, each holding the freed memory of its thread: an agent's main,
#: receiving, writer and fusion threads plus Zenoh's held ~29 MB of arenas between them. Two
#: arenas keep the threads that allocate at once from waiting on one lock.
MALLOC_ARENA_MAX = "2"


def agent_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of an agent process: ``base`` (default ``os.environ``) with the
    project on ``PYTHONPATH``, unbuffered output and :data:`MALLOC_ARENA_MAX` (unless
    ``base`` sets its own)."""
    env = dict(os.environ if base is None else base)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH", "")) if p)
    # what the agent prints reaches agent.log at once, not lost in a buffer if it is killed
    env["PYTHONUNBUFFERED"] = "1"
    env.setdefault("MALLOC_ARENA_MAX", MALLOC_ARENA_MAX)
    return env


@dataclass
class AgentProcess:
    """One launched agent: its id, endpoint, directories, and the process once started."""

    robot: str
    source: str
    port: int
    state_dir: Path
    out_dir: Path
    seeds: list[str]
    extra: list[str] = field(default_factory=list)
    proc: subprocess.Popen | None = None

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.port}"

    def argv(self, fleet: str) -> list[str]:
        argv = [
            sys.executable, "-m", "agent.cli", "agent",
            "--robot", self.robot, "--source", self.source, "--fleet", fleet,
            "--state-dir", str(self.state_dir), "--out", str(self.out_dir),
            "--listen", self.endpoint,
        ]  # fmt: skip
        for seed in self.seeds:
            argv += ["--connect", seed]
        return argv + self.extra

    def start(self, fleet: str, log_path: Path) -> None:
        log = log_path.open("ab")
        self.proc = subprocess.Popen(
            self.argv(fleet),
            cwd=ROOT,
            env=agent_env(),
            stdout=log,
            stderr=subprocess.STDOUT,
            preexec_fn=_die_with_parent,
        )
        log.close()

    def status(self) -> dict | None:
        """The agent's last ``status.json``, or None if not written yet."""
        try:
            return json.loads((self.state_dir / "status.json").read_text())
        except (OSError, ValueError):
            return None

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def signal(self, sig: int) -> None:
        if self.alive():
            assert self.proc is not None
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(sig)

    def stop(self, timeout: float = 3.0) -> float | None:
        """SIGTERM, wait, SIGKILL if needed; the seconds the clean exit took (None if killed)."""
        if not self.alive():
            return None
        assert self.proc is not None
        t0 = time.monotonic()
        self.signal(signal.SIGTERM)
        try:
            self.proc.wait(timeout)
            return time.monotonic() - t0
        except subprocess.TimeoutExpired:
            self.signal(signal.SIGKILL)
            self.proc.wait()
            return None


class LocalFleet:
    """Agents on localhost, peer to peer, no router; a context manager that always cleans up."""

    def __init__(self, fleet: str, workdir: Path, common_args: Sequence[str] = ()) -> None:
        self.fleet = fleet
        self.workdir = Path(workdir).resolve()  # agents run with cwd = the project root
        self.common_args = list(common_args)
        self.agents: dict[str, AgentProcess] = {}

    def add(self, robot: str, source: str, extra: Sequence[str] = ()) -> AgentProcess:
        """Declare and start an agent seeded with every agent declared before it."""
        seeds = [a.endpoint for a in self.agents.values()]
        base = self.workdir / robot
        agent = AgentProcess(
            robot,
            source,
            free_port(),
            base / "state",
            base,
            seeds,
            self.common_args + list(extra),
        )
        base.mkdir(parents=True, exist_ok=True)
        self.agents[robot] = agent
        agent.start(self.fleet, base / "agent.log")
        return agent

    def restart(self, robot: str) -> AgentProcess:
        """Start ``robot`` again with the same port, directories and seeds."""
        agent = self.agents[robot]
        agent.start(self.fleet, self.workdir / robot / "agent.log")
        return agent

    def statuses(self) -> dict[str, dict | None]:
        return {r: a.status() for r, a in self.agents.items()}

    def stop_all(self) -> None:
        for agent in self.agents.values():
            agent.signal(signal.SIGTERM)
        deadline = time.monotonic() + 3.0
        for agent in self.agents.values():
            if agent.proc is None:
                continue
            try:
                agent.proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                agent.signal(signal.SIGKILL)
                agent.proc.wait()

    def __enter__(self) -> LocalFleet:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop_all()


def agreement(statuses: dict[str, dict | None], min_version: dict[str, int] | None = None) -> bool:
    """True when every agent is settled on the same components (anchor, members, digest).

    ``min_version`` optionally requires each robot's map to be at least that version
    everywhere (e.g. the final version of every source).
    """
    views = []
    for status in statuses.values():
        if status is None or not status.get("settled"):
            return False
        comps = sorted(
            (c["anchor"], tuple(c["members"]), c["digest"], tuple(sorted(c["versions"].items())))
            for c in status.get("components", [])
        )
        if min_version:
            held = {r: v.get("version") for r, v in status.get("robots", {}).items()}
            if any((held.get(r) or 0) < v for r, v in min_version.items()):
                return False
        views.append(comps)
    return bool(views) and all(v == views[0] for v in views)


def sources_done(statuses: dict[str, dict | None]) -> bool:
    return all(s is not None and s.get("source", {}).get("done") for s in statuses.values())


def wait_for(predicate, timeout: float, period: float = 0.2) -> bool:
    """Poll ``predicate()`` until true or ``timeout`` seconds pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(period)
    return bool(predicate())
