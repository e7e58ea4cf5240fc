"""``pgvd status`` formatting and its bad input (the live query is in the fleet tests)."""

from __future__ import annotations

from agent.cli import main
from agent.cmd_status import format_table

V7, V3 = (40 << 31) | 7, (41 << 31) | 3  # epoch 40 minor 7, epoch 41 minor 3

STATUS = {
    "own_version": V7,
    "global": {"digest": "ab" * 32, "anchor": "r1", "members": ["r1", "r2"]},
    "settled": True,
    "robots": {"r1": {"version": V7, "alive": True}, "r2": {"version": V3, "alive": False}},
    "links": [
        {
            "a": "r1",
            "version_a": V7,
            "b": "r2",
            "version_b": V3,
            "accepted": True,
            "score": 0.987,
            "rotation_deg": -91.5,
            "decided_by": "r2",
        }
    ],
    "bytes_sent": 1200,
    "bytes_received": 3400,
    "merges": 2,
    "drops": {"auth": 3, "limit": 12, "stale_version": 3},
}


def test_table_shows_robots_versions_links_traffic_and_drops() -> None:
    text = format_table({"r1": STATUS})
    assert "r1: own v40.7  global abababababab anchor r1 members r1,r2  settled" in text
    assert "r1:v40.7 r2:v41.3(gone)" in text
    assert "link    r1 v40.7 - r2 v41.3: accepted score 0.987 rot -91.5 deg (by r2)" in text
    assert "  traffic sent 1200 B, received 3400 B, merges 2\n" in text
    assert "  drops   limit=12, auth=3, stale_version=3" in text  # most first
    assert "  drops   none" in format_table({"r1": {**STATUS, "drops": {}}})
    assert format_table({}) == "no agent answered"


def test_bad_fleet_name_is_exit_2(capsys) -> None:
    assert main(["status", "--fleet", "a/b"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fleet name" in err
