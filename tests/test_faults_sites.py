"""Two sites, each with its own ``pgvd router``, agents in client mode, a lossy inter-site link.

Site A (namespace 0) holds r1 and r2, site B (namespace 1) holds r3. Each agent is a Zenoh client
of its own site's router (``deploy/client.json5``); the two routers are linked over a path with
20 % loss each way. Everything the agents exchange — tiles, manifests, links, liveliness and the
tile queryable — crosses the routers, and all three agents converge to one global map.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import pytest
from netfleet import SOURCES, NetFleet, accepted_links, digests, wait_agreed
from netns import ROOT, Lab, lab_or_skip, pgvd_argv, read_line

pytestmark = [pytest.mark.netns, pytest.mark.fleet, pytest.mark.slow]

SITE = {"r1": 0, "r2": 0, "r3": 1}
LOCAL_ROUTER = "tcp/127.0.0.1:7447"


def test_agents_behind_two_linked_routers_converge() -> None:
    lab_or_skip()
    with tempfile.TemporaryDirectory(prefix="pgvd-sites-") as tmp, Lab(2, loss_pct=20) as lab:
        routers = []
        for site in (0, 1):
            link = ["--connect", lab.hosts[1].endpoint(7447)] if site == 0 else []
            config = ["--config", str(ROOT / "deploy" / "router.json5")]
            argv = pgvd_argv("router", *config, "--listen", "tcp/0.0.0.0:7447", *link)
            routers.append(lab.popen(site, argv, name=f"router{site}"))
        for site, router in enumerate(routers):
            assert read_line(router).startswith("ready "), lab.stderr_of(f"router{site}")
        assert read_line(routers[1]).split()[:2] == ["open", "router"]
        fleet = NetFleet(lab, Path(tmp), extra=["--speed", "400", "--link-timeout", "3"])
        client = [
            "--zenoh-config",
            str(ROOT / "deploy" / "client.json5"),
            "--connect",
            LOCAL_ROUTER,
        ]
        start = time.monotonic()
        for robot, (source, frame) in SOURCES.items():
            fleet.launch(robot, SITE[robot], source, frame, *client)
        seconds = wait_agreed(fleet, 120)
        statuses = fleet.statuses()
        dropped = lab.dropped(0) + lab.dropped(1)
        wall = time.monotonic() - start
        print(f"\nsites: agreed in {seconds} s (wall {wall:.1f} s), {fleet.bytes_sent()} B sent,")
        print(f"{dropped} packets dropped by the loss rules")
        assert all(r.poll() is None for r in routers), "a router died"
    assert seconds is not None, "no agreement through the routers within 120 s"
    assert len(digests(statuses)) == 1
    for status in statuses.values():
        assert accepted_links(status) == {("r1", "r2"), ("r1", "r3"), ("r2", "r3")}
        assert all(r["alive"] for r in status["robots"].values()), status["robots"]
        # queued tiles of a version a newer one replaced are dropped by design, not a fault
        assert {k: n for k, n in status["drops"].items() if k != "superseded"} == {}
