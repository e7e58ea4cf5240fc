"""Real agent processes on localhost, peer to peer, no router (issue 5's fleet checks).

One scenario runs once per module (it is the expensive part) and each test asserts one
of its outcomes:

1. r1-r3 replay overlapping segments of the Intel log, each in a random frame of its
   own; r4 replays the Freiburg 079 log (another building);
2. r3 is killed with SIGKILL half-way through its replay and restarted;
3. once all agree, r5 joins late: the others' sources are finished, so their maps reach
   it only through the ``latest`` queryables;
4. every agent is stopped with SIGTERM.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import zenoh

from agent.evaluate import link_error, true_matrix
from agent.launcher import ROOT, LocalFleet, agreement, sources_done, wait_for
from agent.state import StateDir
from agent.zenoh_config import ZenohOptions, build_config
from pgvd.grid import Grid
from protocol import encode_map

pytestmark = [pytest.mark.fleet, pytest.mark.slow]

INTEL = Path(__file__).resolve().parents[1] / "agent" / "data" / "intel-corrected.log.gz"
FRAMES = {"r1": "3,-4,20", "r2": "-7,2,135", "r3": "5,9,250", "r4": "0,0,60", "r5": "-2,-9,310"}
SPEED = "200"
#: The fleet runs keyed: every message carries an HMAC (protocol.auth).
KEY = b"fleet-test-key"


def _final(statuses: dict) -> dict[str, int]:
    return {r: s["own_version"] for r, s in statuses.items() if s}


def _agreed(fleet: LocalFleet) -> bool:
    dead = [r for r, a in fleet.agents.items() if not a.alive()]
    assert not dead, f"agents died: {dead}"
    st = fleet.statuses()
    return sources_done(st) and agreement(st, _final(st))


@pytest.fixture(scope="module")
def scenario(shared: Path, tmp_path_factory: pytest.TempPathFactory) -> dict:
    fr079 = shared / "logs" / "freiburg-079-corrected.log.gz"
    work = tmp_path_factory.mktemp("fleet")
    out: dict = {}
    key_file = work / "fleet.key"
    key_file.write_bytes(KEY + b"\n")
    common = ["--speed", SPEED, "--link-timeout", "3", "--key-file", str(key_file)]
    with LocalFleet("t", work, common) as fleet:
        sources = {
            "r1": f"carmen:{INTEL}@0.0-0.5",
            "r2": f"carmen:{INTEL}@0.25-0.75",
            "r3": f"carmen:{INTEL}@0.5-1.0",
            "r4": f"carmen:{fr079}@0.0-0.25",
        }
        for robot, src in sources.items():
            fleet.add(robot, src, [f"--frame={FRAMES[robot]}"])
        r3 = fleet.agents["r3"]

        def r3_half_way() -> bool:
            st = r3.status()
            return bool(
                st
                and st["own_version"]
                and st["source"]["progress"][0] * 2 >= st["source"]["progress"][1]
            )

        assert wait_for(r3_half_way, 60), "r3 never got half-way"
        r3.signal(signal.SIGKILL)
        r3.proc.wait()
        killed = StateDir(r3.state_dir).load_maps()[0]
        out["killed_versions"] = {r: m.version for r, m in killed.items()}
        out["killed_cursor"] = killed["r3"].extra["cursor"]
        (r3.state_dir / "status.json").unlink()
        fleet.restart("r3")
        assert wait_for(lambda: r3.status() is not None, 20)
        out["r3_first_status"] = r3.status()
        out["agreed4"] = wait_for(lambda: _agreed(fleet), 90)
        out["statuses4"] = fleet.statuses()

        late = fleet.add("r5", f"carmen:{INTEL}@0.1-0.6", [f"--frame={FRAMES['r5']}"])
        out["agreed5"] = wait_for(lambda: _agreed(fleet), 90)
        out["statuses5"] = fleet.statuses()
        out["late"] = late.status()
        out["status_cli"] = _status_cli(fleet.agents["r1"].endpoint)
        out["injected"] = _inject_bad_messages(fleet.agents["r1"].endpoint)
        wait_for(lambda: all((s or {}).get("drops") for s in fleet.statuses().values()), 10)
        out["after_injection"] = fleet.statuses()
        out["alive_after_injection"] = [r for r, a in fleet.agents.items() if a.alive()]

        exits = {}
        for robot, agent in fleet.agents.items():
            t0 = time.monotonic()
            agent.signal(signal.SIGTERM)
            try:
                code = agent.proc.wait(10)
            except Exception:
                code = None
            exits[robot] = (code, time.monotonic() - t0)
        out["exits"] = exits
        out["grids"] = {
            r: StateDir(a.state_dir).load_maps()[0][r].grid for r, a in fleet.agents.items()
        }
    return out


def _status_cli(endpoint: str) -> dict:
    """``pgvd status --json`` run as a user would, connecting to one agent."""
    cmd = [sys.executable, "-m", "agent.cli", "status", "--fleet", "t", "--connect", endpoint]
    res = subprocess.run([*cmd, "--json"], cwd=ROOT, capture_output=True, text=True, timeout=30)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


def _inject_bad_messages(endpoint: str) -> list[str]:
    """Publish garbage, an unkeyed map, a foreign fleet's and a spoofed robot's manifests."""
    opts = ZenohOptions(connect=(endpoint,))
    g = Grid(np.ones((8, 8), np.float32), 0.1)
    foreign = encode_map("other", "r9", 1, g, KEY)[1]
    spoofed = encode_map("t", "r1", 99, g, KEY)[1]
    unkeyed = encode_map("t", "r9", 1, g)[1]
    with zenoh.open(build_config(opts)) as session:
        assert wait_for(lambda: list(session.info.peers_zid()), 10)
        time.sleep(0.5)  # gossip: let the other agents link to this session too
        session.put("pgvd/t/tiles/r9", b"\x00garbage")
        session.put("pgvd/t/manifest/r9", foreign)
        session.put("pgvd/t/manifest/r9", spoofed)
        session.put("pgvd/t/manifest/r9", unkeyed)
        time.sleep(0.5)
    return ["framing", "auth", "foreign_fleet", "key_mismatch"]  # garbage, unkeyed, ...


def _intel_links(status: dict) -> list[dict]:
    return [ln for ln in status["links"] if ln["current"] and ln["accepted"]]


def test_three_agents_agree_with_links_within_2_deg_and_3_cells(scenario: dict) -> None:
    assert scenario["agreed4"]
    st = scenario["statuses4"]
    w2p = {r: np.array(s["source"]["world_to_pixel"]) for r, s in st.items()}
    digests = {s["global"]["digest"] for r, s in st.items() if r != "r4"}
    assert len(digests) == 1
    for s in st.values():
        links = _intel_links(s)
        assert {(ln["a"], ln["b"]) for ln in links} == {("r1", "r2"), ("r1", "r3"), ("r2", "r3")}
        for ln in links:
            shape_b = scenario["grids"][ln["b"]].shape
            deg, cells = link_error(ln["matrix"], true_matrix(w2p[ln["a"]], w2p[ln["b"]]), shape_b)
            assert deg <= 2.0 and cells <= 3.0, (ln, deg, cells)


def test_other_building_stays_a_separate_component(scenario: dict) -> None:
    for s in scenario["statuses4"].values():
        comps = {c["anchor"]: c["members"] for c in s["components"]}
        # r4 came last: it anchors nobody's frame but its own
        assert sorted(comps.values()) == [["r1", "r2", "r3"], ["r4"]] and comps["r4"] == ["r4"]
        r4_links = [ln for ln in s["links"] if ln["current"] and "r4" in (ln["a"], ln["b"])]
        assert len(r4_links) == 3 and not any(ln["accepted"] for ln in r4_links)
    assert scenario["statuses4"]["r4"]["global"]["members"] == ["r4"]


def test_kill_9_and_restart_loses_nothing(scenario: dict) -> None:
    first = scenario["r3_first_status"]
    killed = scenario["killed_versions"]
    # The restarted agent starts from its state dir: every map it had, at least at the
    # version it had (peers may already have sent newer ones), own version continued.
    held = {r: v["version"] or 0 for r, v in first["robots"].items()}
    assert all(held.get(r, 0) >= v for r, v in killed.items()), (held, killed)
    assert first["own_version"] >= killed["r3"]
    assert first["source"]["progress"][0] >= scenario["killed_cursor"] > 0
    final = scenario["statuses4"]["r3"]
    assert final["own_version"] > killed["r3"]
    assert final["global"]["digest"] == scenario["statuses4"]["r1"]["global"]["digest"]


def test_late_joiner_catches_up_through_the_queryable(scenario: dict) -> None:
    assert scenario["agreed5"]
    st = scenario["statuses5"]
    r5 = st["r5"]
    # The other sources were finished before r5 started: only the queryables had their maps.
    assert {r: v["version"] for r, v in r5["robots"].items()} == _final(st)
    assert r5["counts"]["fetches"] >= 4 and r5["counts"]["maps_received"] >= 4
    assert r5["global"]["members"] == ["r1", "r2", "r3", "r5"]
    assert len({s["global"]["digest"] for r, s in st.items() if r != "r4"}) == 1


def test_sigterm_exits_cleanly_within_2_s(scenario: dict) -> None:
    for robot, (code, seconds) in scenario["exits"].items():
        assert code == 0, robot
        assert seconds < 2.0, (robot, seconds)


def test_no_message_was_dropped_in_normal_operation(scenario: dict) -> None:
    for robot, s in scenario["statuses5"].items():
        # queued tiles of a version a newer one replaced are dropped by design, not a fault
        assert {k: n for k, n in s["drops"].items() if k != "superseded"} == {}, robot


def test_bad_messages_are_dropped_counted_and_survived(scenario: dict) -> None:
    assert scenario["alive_after_injection"] == ["r1", "r2", "r3", "r4", "r5"]
    for robot, s in scenario["after_injection"].items():
        assert set(s["drops"]) == set(scenario["injected"]), robot
        assert s["global"] == scenario["statuses5"][robot]["global"]  # nothing changed


def test_status_command_lists_robots_versions_links_and_traffic(scenario: dict) -> None:
    got = scenario["status_cli"]
    assert sorted(got) == ["r1", "r2", "r3", "r4", "r5"]
    for s in got.values():
        assert {r: v["version"] for r, v in s["robots"].items()} == _final(scenario["statuses5"])
        assert any(ln["accepted"] and ln["score"] > 0 for ln in s["links"])
        assert s["bytes_sent"] > 0 and s["bytes_received"] > 0
