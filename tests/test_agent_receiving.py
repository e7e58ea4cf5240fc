"""agent.daemon's receiving thread: a map being decoded holds back nothing else.

One real agent on a Zenoh session of its own, and a peer session that publishes a real map of
robot r2 tile by tile. The agent's decode is held at its first tile (a gate around the real
:meth:`agent.node.FleetNode.read`, as a large map's decode would hold it); meanwhile r2's
liveliness token appears, and the agent's status, queried over Zenoh, must show r2 alive.
When the main thread also decoded, the membership change waited behind the decode.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from pathlib import Path

import zenoh

from agent.actions import Drop
from agent.daemon import Agent, AgentOptions
from agent.node import FleetNode
from agent.sources import SourceSpec
from agent.zenoh_config import ZenohOptions, build_config
from pgvd.io import read_map
from protocol import Message, encode_map

MAPS = Path("maps") / "intel_split_gt"
VERSION = 7 << 31


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def status_of(session: zenoh.Session, robot: str) -> dict:
    """The agent's status as ``pgvd status`` reads it: a Zenoh query, answered or not."""
    for reply in session.get(f"pgvd/lab/status/{robot}", timeout=2.0):
        if reply.ok is not None:
            return json.loads(reply.ok.payload.to_bytes())
    return {}


def wait_for(what, seconds: float = 60.0) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if what():
            return True
        time.sleep(0.1)
    return False


def gate(node: FleetNode) -> tuple[threading.Event, threading.Event]:
    """Hold ``node``'s decodes until the second event is set; the first says one is held."""
    decoding, release = threading.Event(), threading.Event()
    read = node.read

    def held(key: str, payload: bytes) -> Message | Drop:
        decoding.set()
        release.wait(120)
        return read(key, payload)

    node.read = held  # type: ignore[method-assign]
    return decoding, release


def test_membership_is_heard_while_a_map_is_being_decoded(tmp_path: Path, shared: Path) -> None:
    port = free_port()
    opts = AgentOptions(
        "r1",
        SourceSpec("map", shared / MAPS / "intel_partA.yaml"),
        tmp_path / "r1",
        fleet="lab",
        zenoh=ZenohOptions(listen=[f"tcp/127.0.0.1:{port}"]),
        status_period=0.1,
    )
    agent = Agent(opts)
    decoding, release = gate(agent.node)
    stop = threading.Event()
    host = threading.Thread(target=agent.run, args=(stop,), daemon=True)
    host.start()
    tiles, manifest = encode_map("lab", "r2", VERSION, read_map(shared / MAPS / "intel_partB.yaml"))
    try:
        with zenoh.open(build_config(ZenohOptions(connect=[f"tcp/127.0.0.1:{port}"]))) as peer:
            # published until the agent's subscriber hears one: discovery takes a moment
            assert wait_for(lambda: peer.put("pgvd/lab/tiles/r2", tiles[0]) or decoding.is_set())
            for data in tiles[1:]:
                peer.put("pgvd/lab/tiles/r2", data)
            peer.put("pgvd/lab/manifest/r2", manifest)
            with peer.liveliness().declare_token("pgvd/lab/alive/r2"):
                heard = wait_for(
                    lambda: status_of(peer, "r1").get("robots", {}).get("r2", {}).get("alive")
                )
                held = not release.is_set() and len(agent.inbox) > 0
                release.set()
                assert heard and held  # r2 joined while its map waited for the decode
                received = wait_for(
                    lambda: status_of(peer, "r1")["robots"]["r2"]["version"] == VERSION
                )
                assert received  # once released, the decode went on and the map came in
    finally:
        release.set()
        stop.set()
        host.join(10.0)
    assert not host.is_alive()
