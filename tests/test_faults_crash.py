"""Crashes, freezes and partitions of real agents, each in its own namespace, during mapping.

One scenario (3 agents replaying overlapping Intel segments, lease 2 s):

1. r2 is frozen with SIGSTOP until its peers declare it gone (past the lease), then resumed;
2. r3 is killed with SIGKILL exactly at two failpoints (:mod:`agent.failpoints`), each armed by
   restarting it with ``PGVD_FAILPOINT``: ``state-write`` (half of a map file's temporary copy
   on disk) and ``tiles-send`` (one tile of a new version sent, the rest and the manifest not).
   After each kill its state must load without a single error, hold every r3 version a peer
   holds, and the next start must remove the half-written copy;
3. the network is split into {r1} and {r2, r3} until each side sees the other gone, while every
   robot with scans left keeps mapping (each half must have one); then the split heals;
4. everybody must end with the same global map, the three true links, every final version.
"""

from __future__ import annotations

import signal
import tempfile
import time
from pathlib import Path

import pytest
from netfleet import (
    SOURCES,
    NetFleet,
    accepted_links,
    assert_held_maps_match_owners,
    digests,
    wait_agreed,
)
from netns import Lab, lab_or_skip

from agent.state import StateDir

pytestmark = [pytest.mark.netns, pytest.mark.fleet, pytest.mark.slow]

LEASE_MS = 2000
ARGS = [
    "--speed",
    # 40, not 60: at 60 r2's segment was at times replayed to its end before the split
    "40",
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


def crash_at(fleet: NetFleet, lab: Lab, where: tuple, point: str) -> dict:
    """Restart r3 with ``point`` armed, ``kill -9`` it there, restart it plain; what was seen."""
    fleet.signal("r3", signal.SIGTERM)
    fleet.procs["r3"].wait(timeout=20)
    fleet.start("r3", *where, env={"PGVD_FAILPOINT": point})
    maps_dir = fleet.state_dir("r3") / "maps"
    kill: dict = {"point": point}
    kill["reached_s"] = wait(lambda: f"FAILPOINT {point}" in lab.stderr_of("r3"), 60)
    # what is on disk while the writer is stopped: a real, partly written temporary copy
    kill["temporaries"] = {p.name: p.stat().st_size for p in maps_dir.glob(".*.npz.*")}
    fleet.kill("r3")
    time.sleep(0.5)  # peers' status files catch up (older views only weaken the check below)
    kill["peers_hold"] = {
        r: ((fleet.status(r) or {}).get("robots", {}).get("r3") or {}).get("version") or 0
        for r in ("r1", "r2")
    }
    state = StateDir(fleet.state_dir("r3"))  # what the restarted agent does first
    maps, errors = state.load_maps()
    kill.update(errors=errors, maps=sorted(maps), removed=state.removed_temporaries)
    kill["persisted"] = maps["r3"].version if "r3" in maps else None
    (fleet.state_dir("r3") / "status.json").unlink(missing_ok=True)
    restarted = time.monotonic()
    fleet.start("r3", *where)
    kill["restart_s"] = wait(lambda: fleet.status("r3") is not None, 20)
    # peers hold r3's version cut mid-send (or a newer one): from the restarted agent
    kill["peers_caught_up_s"] = wait(
        lambda: all(
            (((fleet.status(r) or {}).get("robots", {}).get("r3") or {}).get("version") or 0)
            >= (kill["persisted"] or 0)
            for r in ("r1", "r2")
        ),
        60,
    )
    kill["since_restart_s"] = time.monotonic() - restarted
    return kill


@pytest.fixture(scope="module")
def scenario(record_testsuite_property) -> dict:
    lab_or_skip()
    out: dict = {"kills": []}
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

        # 2. kill -9 r3 exactly mid-write of its own map, then exactly mid-send of a version
        for point in ("state-write", "tiles-send"):
            out["kills"].append(crash_at(fleet, lab, hosts["r3"], point))

        # 3. split {r1} | {r2, r3}, both halves keep mapping, then heal
        lab.partition([0], [1, 2])
        before = {r: published(fleet, r) for r in SOURCES}
        # A robot whose log segment is replayed to its end has nothing left to publish: only
        # the others can show that their half keeps mapping.
        out["replaying_at_split"] = [r for r in SOURCES if progress(fleet, r) < 1.0]
        out["split_detected_s"] = wait(
            lambda: sees(fleet, "r1", "r2") is False and sees(fleet, "r2", "r1") is False, 20
        )
        # Until every robot has published during the split (not a fixed second: on a loaded
        # machine a robot's next version can take longer than that), bounded.
        replaying = out["replaying_at_split"]
        wait(lambda: all(published(fleet, r) > before[r] for r in replaying), 20)
        out["versions_during_split"] = {r: published(fleet, r) - before[r] for r in SOURCES}
        lab.heal()
        # 45 s, not 20: a TCP connect begun during the split resends its SYN with backoff
        # (1, 2, 4, 8 s ...), so a reconnect can land well after the heal.
        out["heal_s"] = wait(lambda: sees(fleet, "r1", "r2") and sees(fleet, "r3", "r1"), 45)

        out["agreed_s"] = wait_agreed(fleet, 120)
        out["statuses"] = fleet.statuses()
        out["held"] = {r: StateDir(fleet.state_dir(r)).load_maps()[0] for r in SOURCES}
    print("\n", {k: v for k, v in out.items() if k not in ("statuses", "held")})
    for kill in out["kills"]:
        for key in ("reached_s", "restart_s", "peers_caught_up_s", "since_restart_s"):
            record_testsuite_property(f"{kill['point']}_{key}", kill[key])
    return out


def test_a_frozen_agent_is_declared_gone_after_the_lease_and_rejoins(scenario: dict) -> None:
    # Noticed within the 20 s wait (the seconds are printed, not asserted: a loaded CI machine
    # delays status files); the lease is 2 s, measured detections were 2.1-3.2 s.
    assert scenario["freeze_detected_s"] is not None, "peers never noticed the frozen agent"
    assert scenario["rejoin_s"] is not None


def test_both_halves_keep_mapping_through_a_partition_that_heals(scenario: dict) -> None:
    assert scenario["split_detected_s"] is not None, "the split was never noticed"
    replaying = scenario["replaying_at_split"]
    # each half still had scans to map, or the scenario would show nothing
    assert "r1" in replaying and {"r2", "r3"} & set(replaying), scenario
    assert all(scenario["versions_during_split"][r] > 0 for r in replaying), scenario
    assert scenario["heal_s"] is not None


def test_kill_9_mid_write_and_mid_send_loses_nothing(scenario: dict) -> None:
    kills = {k["point"]: k for k in scenario["kills"]}
    assert sorted(kills) == ["state-write", "tiles-send"]
    for kill in kills.values():
        assert kill["reached_s"] is not None, f"{kill['point']} never reached"
        assert kill["errors"] == []
        assert kill["maps"] == ["r1", "r2", "r3"]  # the peers' maps were persisted too
        # persist before publish: no peer holds an r3 version r3 itself lost
        assert all(kill["persisted"] >= v for v in kill["peers_hold"].values()), kill
        assert kill["restart_s"] is not None and kill["peers_caught_up_s"] is not None, kill
    write = kills["state-write"]
    # the kill landed with half a copy on disk; the old file loaded whole; the next start removed it
    assert [n.split(".")[1] for n in write["temporaries"]] == ["r3"], write  # its own map
    assert min(write["temporaries"].values()) > 0, write
    assert write["removed"] == sorted(write["temporaries"])


def test_everyone_ends_with_the_same_global_map(scenario: dict) -> None:
    assert scenario["agreed_s"] is not None
    statuses = scenario["statuses"]
    assert len(digests(statuses)) == 1
    for status in statuses.values():
        assert accepted_links(status) == {("r1", "r2"), ("r1", "r3"), ("r2", "r3")}
        # A tile or fetch reply of a superseded version can arrive after the newer one is held
        # (restarts and the heal reorder them): it is dropped as stale, and nothing is lost, as
        # the comparison of every held map with its owner's checks; so can a queued tile that a
        # newer version superseded before it was read. Any other drop is a fault.
        assert set(status["drops"]) <= {"stale_version", "superseded"}, status["drops"]
    assert_held_maps_match_owners(scenario["held"])
