"""Crashes, freezes and partitions of real agents, each in its own namespace, during mapping.

One scenario (3 agents replaying overlapping Intel segments, lease 2 s):

1. r2 is frozen with SIGSTOP until its peers declare it gone (past the lease), then resumed;
2. r3 is killed with SIGKILL three times, each a few ms after it published a new version (while
   it sends and persists), and restarted; its state directory must load without a single error
   and hold at least what it had published;
3. the network is split into {r1} and {r2, r3} until each side sees the other gone, while every
   robot keeps mapping; then the split heals;
4. everybody must end with the same global map, the three true links, every final version.
"""

from __future__ import annotations

import random
import signal
import tempfile
import time
from pathlib import Path

import pytest
from netfleet import SOURCES, NetFleet, accepted_links, digests, wait_agreed
from netns import Lab, lab_or_skip

from agent.state import StateDir

pytestmark = [pytest.mark.netns, pytest.mark.fleet, pytest.mark.slow]

LEASE_MS = 2000
ARGS = [
    "--speed",
    "60",
    "--link-timeout",
    "3",
    "--lease-ms",
    str(LEASE_MS),
    "--min-interval",
    "0.5",
]


def wait(predicate, timeout: float, period: float = 0.05) -> float | None:
    """Seconds until ``predicate()`` holds, or None after ``timeout``."""
    start = time.monotonic()
    while time.monotonic() - start < timeout:
        if predicate():
            return time.monotonic() - start
        time.sleep(period)
    return None


def sees(fleet: NetFleet, robot: str, other: str) -> bool | None:
    status = fleet.status(robot)
    return None if status is None else status["robots"].get(other, {}).get("alive")


def version(fleet: NetFleet, robot: str) -> int:
    return (fleet.status(robot) or {}).get("own_version") or 0


def published(fleet: NetFleet, robot: str) -> int:
    """Versions ``robot`` published since it (re)started (versions are timestamps, not counts)."""
    return (fleet.status(robot) or {}).get("counts", {}).get("versions_published", 0)


def progress(fleet: NetFleet, robot: str) -> float:
    done, total = (fleet.status(robot) or {}).get("source", {}).get("progress", (0, 1))
    return done / total


@pytest.fixture(scope="module")
def scenario() -> dict:
    lab_or_skip()
    out: dict = {"kills": []}
    rng = random.Random(9)
    with tempfile.TemporaryDirectory(prefix="pgvd-crash-") as tmp, Lab(3) as lab:
        fleet = NetFleet(lab, Path(tmp), extra=ARGS)
        hosts = {}
        for host, (robot, (source, frame)) in enumerate(SOURCES.items()):
            hosts[robot] = (host, source, frame)
            fleet.start(robot, host, source, frame)
        assert wait(lambda: all(sees(fleet, r, o) for r in SOURCES for o in SOURCES if o != r), 30)

        # 1. freeze r2 past the lease
        assert wait(lambda: progress(fleet, "r2") >= 0.1, 60) is not None
        fleet.signal("r2", signal.SIGSTOP)
        frozen_at = published(fleet, "r1")
        out["freeze_detected_s"] = wait(
            lambda: sees(fleet, "r1", "r2") is False and sees(fleet, "r3", "r2") is False, 20
        )
        out["versions_while_frozen"] = published(fleet, "r1") - frozen_at
        fleet.signal("r2", signal.SIGCONT)
        out["rejoin_s"] = wait(lambda: sees(fleet, "r1", "r2") and sees(fleet, "r2", "r1"), 20)

        # 2. kill -9 r3 right after it publishes (sending, persisting), restart, three times
        for _ in range(3):
            held = version(fleet, "r3")
            if wait(lambda held=held: version(fleet, "r3") > held, 20) is None:
                break  # r3's replay is over: no more versions to interrupt
            time.sleep(rng.uniform(0.0, 0.05))
            shown = version(fleet, "r3")
            fleet.kill("r3")
            maps, errors = StateDir(fleet.state_dir("r3")).load_maps()
            kill = {"published": shown, "persisted": maps["r3"].version}
            out["kills"].append({**kill, "errors": errors, "maps": sorted(maps)})
            (fleet.state_dir("r3") / "status.json").unlink(missing_ok=True)
            fleet.start("r3", *hosts["r3"])
            assert wait(lambda: fleet.status("r3") is not None, 20) is not None

        # 3. split {r1} | {r2, r3}, both halves keep mapping, then heal
        lab.partition([0], [1, 2])
        before = {r: published(fleet, r) for r in SOURCES}
        out["split_detected_s"] = wait(
            lambda: sees(fleet, "r1", "r2") is False and sees(fleet, "r2", "r1") is False, 20
        )
        time.sleep(1.0)
        out["versions_during_split"] = {r: published(fleet, r) - before[r] for r in SOURCES}
        lab.heal()
        out["heal_s"] = wait(lambda: sees(fleet, "r1", "r2") and sees(fleet, "r3", "r1"), 20)

        out["agreed_s"] = wait_agreed(fleet, 120)
        out["statuses"] = fleet.statuses()
    print("\n", {k: v for k, v in out.items() if k != "statuses"})
    return out


def test_a_frozen_agent_is_declared_gone_after_the_lease_and_rejoins(scenario: dict) -> None:
    # Noticed within the 20 s wait (the seconds are printed, not asserted: a loaded CI machine
    # delays status files); the lease is 2 s, measured detections were 2.1-3.2 s.
    assert scenario["freeze_detected_s"] is not None, "peers never noticed the frozen agent"
    assert scenario["rejoin_s"] is not None


def test_both_halves_keep_mapping_through_a_partition_that_heals(scenario: dict) -> None:
    assert scenario["split_detected_s"] is not None, "the split was never noticed"
    assert all(n > 0 for n in scenario["versions_during_split"].values()), scenario
    assert scenario["heal_s"] is not None


def test_kill_9_mid_send_loses_nothing_persisted(scenario: dict) -> None:
    assert scenario["kills"], "r3 was never killed"
    for kill in scenario["kills"]:
        assert kill["errors"] == []
        assert kill["persisted"] >= kill["published"]
        assert kill["maps"] == ["r1", "r2", "r3"]  # the peers' maps were persisted too


def test_everyone_ends_with_the_same_global_map(scenario: dict) -> None:
    assert scenario["agreed_s"] is not None
    statuses = scenario["statuses"]
    assert len(digests(statuses)) == 1
    for status in statuses.values():
        assert accepted_links(status) == {("r1", "r2"), ("r1", "r3"), ("r2", "r3")}
        assert status["drops"] == {}
