"""Lossy links: the netns harness itself, and real Zenoh sessions across it at 20 % loss."""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
from netns import Lab, lab_or_skip, read_line

pytestmark = pytest.mark.netns

PROBE = "tests/zprobe.py"


def probe(role: str, count: int) -> list[str]:
    """The command line of a :mod:`zprobe` process."""
    return [sys.executable, PROBE, role, "--count", str(count)]


def zenoh_config(mode: str, listen: list[str], connect: list[str]) -> dict[str, object]:
    """Explicit endpoints, no multicast, no shared memory (so the loss applies), no open delay."""
    return {
        "mode": mode,
        "listen/endpoints": listen,
        "connect/endpoints": connect,
        "scouting/multicast/enabled": False,
        "scouting/delay": 0,
        "transport/shared_memory/enabled": False,
    }


def udp_burst(lab: Lab, src: int, dst: int, n: int = 2000) -> int:
    """Datagrams of 64 B that host ``dst`` receives out of ``n`` sent by host ``src``."""
    addr = lab.hosts[dst].addr
    # The receiver counts until told the sender is done (a line on stdin), then until 0.5 s
    # pass without a datagram. An idle timeout alone stops counting early if a loaded machine
    # pauses the sender for 0.5 s mid-burst: the likely cause of a CI failure that counted
    # 1416 of 2000 through a 20 % loss (8 sd low; the loss rule alone gives 1576-1612).
    # A buffer for the whole burst (33 = SO_RCVBUFFORCE), lest a busy receiver drop datagrams.
    # That pause was not the cause: a sender slowed to 2.5 s lost about 255 datagrams outside
    # the rule in 2 of 45 bursts, queued behind an ARP request the rule had dropped
    # (Lab.resolve); with the neighbour pinned first, none of 30 lost any.
    receive = (
        "import select, socket, sys; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
        "s.setsockopt(socket.SOL_SOCKET, 33, 16 << 20)\n"
        f"s.bind(('{addr}', 9999)); print('READY', flush=True); n = 0; watch = [s, sys.stdin]\n"
        "while True:\n"
        "  ready = select.select(watch, [], [], 0.5)[0]\n"
        "  if s in ready: s.recv(100); n += 1\n"
        "  elif sys.stdin in ready: sys.stdin.readline(); watch = [s]\n"
        "  elif len(watch) == 1: break\n"
        "print(n)"
    )
    send = (
        "import socket, time; s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)\n"
        f"for i in range({n}):\n  s.sendto(bytes(64), ('{addr}', 9999))\n"
        "  if i % 50 == 0: time.sleep(0.001)"
    )
    lab.resolve(src, dst)
    server = lab.popen(dst, [sys.executable, "-c", receive], stdin=True)
    assert read_line(server).strip() == "READY"
    subprocess.run(lab_cmd(lab, src, [sys.executable, "-c", send]), check=True, timeout=30)
    return int(server.communicate("done\n", timeout=10)[0].split()[-1])


def lab_cmd(lab: Lab, index: int, argv: list[str]) -> list[str]:
    return ["ip", "netns", "exec", lab.hosts[index].ns, *argv]


def test_lab_drops_the_set_share_and_partitions_heal() -> None:
    lab_or_skip()
    with Lab(3, loss_pct=20) as lab:
        got = udp_burst(lab, 0, 1)
        # 2000 Bernoulli(0.8) trials: mean 1600, sd 18; the bounds are > 8 sd away.
        # the rule's own count in the message: a low count with few rule drops is a loss
        # outside the rule (a queue on a loaded machine), not the rule misbehaving
        assert 1450 < got < 1750, f"received {got} of 2000, the rule dropped {lab.dropped(0)}"
        # With the neighbour pinned, the datagrams lost are the rule's; its count also holds
        # the odd other packet host 0 sends (IPv6 neighbour discovery): a few more at most.
        assert abs(lab.dropped(0) - (2000 - got)) <= 10
        for i in range(3):
            lab.set_loss(i, 0)
        assert udp_burst(lab, 0, 1) == 2000
        lab.partition([0], [1, 2])
        assert udp_burst(lab, 0, 1) == 0
        assert udp_burst(lab, 2, 1) == 2000
        lab.heal()
        assert udp_burst(lab, 0, 1) == 2000
        namespaces = [h.ns for h in lab.hosts]
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert not any(ns in listed for ns in namespaces), "lab namespaces must be gone after exit"


@pytest.mark.slow
def test_reliable_tcp_delivers_everything_at_20_percent_loss_each_way(
    record_property: pytest.RecordProperty,
) -> None:
    lab_or_skip()
    count = 400
    with Lab(2, loss_pct=20) as lab:
        listen = lab.hosts[1].endpoint(7447)
        sub_cfg = json.dumps(zenoh_config("peer", [listen], []))
        pub_cfg = json.dumps(zenoh_config("peer", [], [listen]))
        sub = lab.popen(1, [*probe("sub", count), "--config", sub_cfg], name="sub")
        assert read_line(sub).strip() == "READY", lab.stderr_of("sub")
        start = time.monotonic()
        pub_args = ["--size", "1024", "--interval", "0.005", "--config", pub_cfg]
        pub = lab.popen(0, [*probe("pub", count), *pub_args], name="pub")
        result = json.loads(sub.communicate(timeout=60)[0].splitlines()[-1])
        elapsed = time.monotonic() - start
        assert json.loads(pub.communicate(timeout=30)[0].splitlines()[-1])["matched"]
        dropped = lab.dropped(0) + lab.dropped(1)
    assert sorted(result["seqs"]) == list(range(count)), "reliable TCP must deliver every sample"
    assert result["seqs"] == sorted(result["seqs"]), "a reliable link delivers in order"
    assert result["alive"], "the publisher's liveliness token must cross the lossy link"
    assert dropped > 0, "the loss rules must have dropped packets for the test to mean anything"
    lat = np.array(result["latencies"]) * 1e3
    stats = {
        "delivered": len(result["seqs"]),
        "sent": count,
        "packets_dropped_by_nft": dropped,
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 2),
        "latency_ms_p99": round(float(np.percentile(lat, 99)), 2),
        "latency_ms_max": round(float(lat.max()), 2),
        "wall_s": round(elapsed, 2),
    }
    for key, value in stats.items():
        record_property(key, value)
    print("tcp 20% each way:", stats)
