"""Real agents say what they decide: each link decision and each global map in agent.log, and
the links by lifecycle state in status.json (agent.trust)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from agent.launcher import LocalFleet, agreement, sources_done, wait_for

pytestmark = [pytest.mark.fleet, pytest.mark.slow]

INTEL = Path(__file__).resolve().parents[1] / "agent" / "data" / "intel-corrected.log.gz"


def test_agent_logs_hold_every_decision_and_the_status_its_state(tmp_path: Path) -> None:
    with LocalFleet("d", tmp_path, ["--speed", "200", "--link-timeout", "3"]) as fleet:
        fleet.add("r1", f"carmen:{INTEL}@0.0-0.5", ["--frame=3,-4,20"])
        fleet.add("r2", f"carmen:{INTEL}@0.25-0.75", ["--frame=-7,2,135"])

        def done() -> bool:
            st = fleet.statuses()
            return sources_done(st) and agreement(st)

        assert wait_for(done, 120), fleet.statuses()
        statuses = fleet.statuses()
    logs = {r: (tmp_path / r / "agent.log").read_text() for r in ("r1", "r2")}
    decisions = [
        line for text in logs.values() for line in text.splitlines() if " link pair=r1/r2 " in line
    ]
    assert decisions, logs
    pattern = re.compile(
        r" INFO link pair=r1/r2 versions=\d+\.\d+/\d+\.\d+ "
        r"outcome=(accepted|candidate|confirmed|rejected|withdrawn) margin=(-?\d\.\d\d|none) "
        r'holds=\d+ by=r[12] reason="[^"]*" how=[a-z ]+ seconds=\d+\.\d\d book=(taken|superseded)$'
    )
    assert all(pattern.search(line) for line in decisions), decisions
    # the anchor is the robot whose first version is older (ties: r1), the same on both
    anchors = {
        robot: set(re.findall(r" INFO globalmap anchor=(r[12]) robots=r1,r2 links=r1/r2 ", text))
        for robot, text in logs.items()
    }
    assert anchors["r1"] and anchors["r1"] == anchors["r2"], logs
    for status in statuses.values():
        assert status["link_states"]["accepted"] + status["link_states"]["confirmed"] == ["r1/r2"]
        (link,) = [ln for ln in status["links"] if ln["current"]]
        assert link["state"] in ("accepted", "confirmed") and link["reason"], link
