"""Real ``pgvd agent`` processes, one per namespace of a :class:`netns.Lab`.

Each agent listens on ``tcp/<its address>:7447`` (tiles on ``udp/...:7448`` with ``udp=True``)
and is linked directly to every other host, so a lossy or partitioned path is the direct one
between two hosts (no relay around it). Shared memory is off: every byte crosses the veth pairs
and their loss rules. Status comes from each agent's ``status.json`` (the namespaces share the
file system).
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from netns import Lab, pgvd_argv

from agent import wire
from agent.launcher import agreement, sources_done
from agent.state import StoredMap

PORT = 7447
INTEL = Path(__file__).resolve().parents[1] / "agent" / "data" / "intel-corrected.log.gz"
#: Overlapping thirds of the bundled Intel log, each robot in its own random frame.
SOURCES = {
    "r1": (f"carmen:{INTEL}@0.0-0.5", "3,-4,20"),
    "r2": (f"carmen:{INTEL}@0.25-0.75", "-7,2,135"),
    "r3": (f"carmen:{INTEL}@0.5-1.0", "5,9,250"),
}


@dataclass
class NetFleet:
    """Agents r1..rN on the hosts of ``lab``; ``extra`` arguments go to every agent."""

    lab: Lab
    workdir: Path
    fleet: str = "t"
    extra: list[str] = field(default_factory=list)
    udp: bool = False
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    hosts: dict[str, int] = field(default_factory=dict)

    def start(
        self,
        robot: str,
        host: int,
        source: str,
        frame: str,
        *args: str,
        env: dict[str, str] | None = None,
    ) -> None:
        """A peer agent listening on its host's address, linked to every other host.

        Each pair is dialled by one side only (the lower host index): with both sides dialling,
        a lease that expires on one side only lets the other fold the reconnect into its stale
        transport and never re-send its declarations (eclipse-zenoh/zenoh#2806), and a healed
        partition once stayed split for good that way. With ``udp``, tiles go best-effort on a
        tile session over ``udp/<address>:7448``. ``env`` adds environment variables (e.g.
        ``PGVD_FAILPOINT``).
        """
        me = self.lab.hosts[host]
        others = [h for h in self.lab.hosts if h.index > host]
        net = ["--listen", me.endpoint(PORT)]
        net += [a for h in others for a in ("--connect", h.endpoint(PORT))]
        if self.udp:
            net += ["--tiles-listen", me.endpoint(PORT + 1, "udp")]
            net += [a for h in others for a in ("--tiles-connect", h.endpoint(PORT + 1, "udp"))]
        self.launch(robot, host, source, frame, *net, *args, env=env)

    def launch(
        self,
        robot: str,
        host: int,
        source: str,
        frame: str,
        *args: str,
        env: dict[str, str] | None = None,
    ) -> None:
        """An agent on ``host`` with exactly the network arguments ``args``."""
        self.hosts[robot] = host
        argv = [
            "agent", "--robot", robot, "--source", source, f"--frame={frame}",
            "--fleet", self.fleet, "--state-dir", str(self.state_dir(robot)),
            "--shm", "off", *self.extra, *args,
        ]  # fmt: skip
        self.procs[robot] = self.lab.popen(host, pgvd_argv(*argv), name=robot, env=env)

    def state_dir(self, robot: str) -> Path:
        return self.workdir / robot

    def status(self, robot: str) -> dict | None:
        try:
            return json.loads((self.state_dir(robot) / "status.json").read_text())
        except (OSError, ValueError):
            return None

    def statuses(self) -> dict[str, dict | None]:
        return {robot: self.status(robot) for robot in self.procs}

    def dead(self) -> list[str]:
        return [r for r, p in self.procs.items() if p.poll() is not None]

    def agreed(self) -> bool:
        """All alive, sources done, and everyone settled on the same components and versions."""
        assert not self.dead(), f"agents died: {self.dead()}: {self.lab.stderr_of(self.dead()[0])}"
        st = self.statuses()
        final = {r: s["own_version"] for r, s in st.items() if s}
        return sources_done(st) and agreement(st, final)

    def signal(self, robot: str, sig: int) -> None:
        self.procs[robot].send_signal(sig)

    def kill(self, robot: str) -> None:
        self.procs[robot].send_signal(signal.SIGKILL)
        self.procs[robot].wait(timeout=10)

    def bytes_sent(self) -> int:
        return sum((s or {}).get("bytes_sent", 0) for s in self.statuses().values())


def wait_agreed(fleet: NetFleet, timeout: float) -> float | None:
    """Seconds until the fleet agrees, or None after ``timeout``."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        if fleet.agreed():
            return time.monotonic() - start
        time.sleep(0.25)
    return None


def digests(statuses: dict[str, dict | None]) -> set[str]:
    return {s["global"]["digest"] for s in statuses.values() if s and s.get("global")}


def accepted_links(status: dict) -> set[tuple[str, str]]:
    return {(ln["a"], ln["b"]) for ln in status["links"] if ln["current"] and ln["accepted"]}


def assert_held_maps_match_owners(held: dict[str, dict[str, StoredMap]]) -> None:
    """Every map an agent holds of a peer is that peer's own latest version, cell for cell
    (as it travels on the wire): nothing was lost, whatever was dropped on the way."""
    for robot, maps in held.items():
        for peer, stored in maps.items():
            if peer != robot:
                own = wire.on_the_wire(held[peer][peer].grid)
                assert stored.version == held[peer][peer].version, (robot, peer)
                assert np.array_equal(stored.grid.logodds, own.logodds), (robot, peer)
