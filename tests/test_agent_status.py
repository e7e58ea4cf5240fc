"""``pgvd status`` formatting and its bad input (the live query is in the fleet tests), and
the links a status shows."""

from __future__ import annotations

import json
import socket

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from agent.cli import main
from agent.cli.status import format_table
from agent.links import LinkRecord
from agent.status import link_json, link_states, links_json
from agent.status_reply import MAX_STATUS_BYTES, check_status, read_status
from protocol.auth import seal

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
    assert "source" not in text  # a source that reads its map says nothing
    failing = {"kind": "map", "read_errors": 4, "last_error": "m.yaml: no such file"}
    text = format_table({"r1": {**STATUS, "source": failing}})
    assert "  source  4 read errors, last: m.yaml: no such file" in text
    healed = {"r1": {**STATUS, "source": {**failing, "last_error": None}}}
    assert "  source  4 read errors, reads again" in format_table(healed)


def test_bad_fleet_name_is_exit_2(capsys) -> None:
    assert main(["status", "--fleet", "a/b"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "fleet name" in err


def test_bad_timeout_is_exit_2(capsys) -> None:
    assert main(["status", "--timeout", "-1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--timeout must be > 0" in err


def test_nobody_answering_is_exit_1(capsys) -> None:
    """A monitoring script tells an empty answer from a fleet's (exit 1: asked, not achieved)."""
    with socket.socket() as s:  # a port nobody listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(["status", "--connect", f"tcp/127.0.0.1:{port}", "--timeout", "0.5"]) == 1
    assert capsys.readouterr().out == "no agent answered\n"


KEY = b"the fleet key"


def test_a_signed_status_reads_back_and_a_forged_one_does_not() -> None:
    payload = json.dumps(STATUS).encode()
    mac = seal(payload, KEY)
    assert read_status(payload, mac, KEY) == STATUS
    assert read_status(payload, None, None) == STATUS  # no key: the MAC is not asked for
    forged = json.dumps({**STATUS, "merges": 99}).encode()
    for data, attachment, why in (
        (payload, None, "no fleet MAC"),
        (forged, mac, "MAC is wrong"),
        (payload, seal(payload, b"another key"), "MAC is wrong"),
        (b"\x00not json", seal(b"\x00not json", KEY), "not JSON"),
        (b" " * (MAX_STATUS_BYTES + 1), None, "exceeds"),
    ):
        with pytest.raises(ValueError, match=why):
            read_status(data, attachment, KEY)


@pytest.mark.parametrize(
    ("bad", "why"),
    [
        ([], "not a JSON object"),
        ({"own_version": "7"}, "own_version has the wrong type"),
        ({"settled": 1}, "settled has the wrong type"),
        ({"merges": True}, "merges has the wrong type"),
        ({"global": {"members": ["r1", 2]}}, "global.members has the wrong type"),
        ({"robots": {"r1": []}}, "robots.r1 is not an object"),
        ({"robots": {"r1": {"alive": "yes"}}}, "robots.r1.alive has the wrong type"),
        ({"links": [{}]}, r"links\[0\] lacks fields"),
        ({"links": [{**STATUS["links"][0], "score": "high"}]}, r"links\[0\].score"),
        ({"drops": {"auth": 1.5}}, "drops must map"),
        ({"source": []}, "source has the wrong type"),
        ({"source": {"read_errors": "4"}}, "source.read_errors has the wrong type"),
        ({"source": {"last_error": 3}}, "source.last_error has the wrong type"),
    ],
)
def test_status_fields_of_the_wrong_shape_are_refused(bad: object, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        check_status(bad)


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=8),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4)
    ),
    max_leaves=30,
)
status_like = st.fixed_dictionaries(
    {},
    optional={
        k: json_values | st.just(v)
        for k, v in {**STATUS, "source": {"read_errors": 2, "last_error": "x"}}.items()
    },
)


@given(status_like)
def test_whatever_is_accepted_can_be_printed(obj: dict) -> None:
    """A stranger's reply is refused with ValueError, or the table prints it without error."""
    try:
        status = check_status(obj)
    except ValueError:
        return
    assert format_table({"r1": status}).startswith("r1: own v")


def test_table_shows_each_links_state_margin_and_reason_and_counts_them() -> None:
    candidate = {
        **STATUS["links"][0], "accepted": False, "state": "candidate", "margin": 0.41,
        "reason": "grey zone: margin 0.41 below 0.57", "holds": 1,
    }  # fmt: skip
    text = format_table({"r1": {**STATUS, "links": [STATUS["links"][0], candidate]}})
    assert "  links   1 accepted, 1 candidate\n" in text, text
    assert (
        "r2 v41.3: candidate score 0.987 rot -91.5 deg (by r2) margin 0.41: "
        "grey zone: margin 0.41 below 0.57"
    ) in text, text
    with pytest.raises(ValueError, match=r"links\[0\].margin has the wrong type"):
        check_status({"links": [{**candidate, "margin": "high"}]})


def test_link_json_of_a_held_record_follows_the_versions() -> None:
    """A record's JSON is made once, but ``current`` is the versions' of each call, and an
    equal record made anew shows the same."""
    turn = np.array([[0.0, -1.0, 5.0], [1.0, 0.0, 2.0], [0.0, 0.0, 1.0]])
    rec = LinkRecord("r1", V7, "r2", V3, True, turn, np.eye(3) * 0.1, 0.9, "r1")
    now = link_json(rec, {"r1": V7, "r2": V3})
    later = link_json(rec, {"r1": V7, "r2": V3 + (1 << 31)})
    assert (now["current"], later["current"]) == (True, False)
    assert {**now, "current": False} == later
    assert list(now)[8:11] == ["decided_by", "current", "state"]
    assert abs(now["rotation_deg"]) == 90.0
    twin = LinkRecord("r1", V7, "r2", V3, True, turn.copy(), np.eye(3) * 0.1, 0.9, "r1")
    assert link_json(twin, {"r1": V7, "r2": V3}) == now


def test_the_links_of_a_status_are_remade_only_when_records_or_versions_change() -> None:
    """The list of the last call stands while the same records and versions come again; an
    equal record made anew, or a newer version, makes it anew, with the same content."""
    recs = [
        LinkRecord("r1", V7, b, V3, True, np.eye(3), np.eye(3) * 0.1, 0.9, "r1")
        for b in ("r2", "r3")
    ]
    versions = {"r1": V7, "r2": V3, "r3": V3}
    first = links_json(recs, versions)
    assert links_json(list(recs), dict(versions)) is first
    assert first == [link_json(rec, versions) for rec in recs]
    anew = [recs[0], LinkRecord("r1", V7, "r3", V3, True, np.eye(3), np.eye(3) * 0.1, 0.9, "r1")]
    assert links_json(anew, versions) == first
    newer = {**versions, "r3": V3 + (1 << 31)}
    assert [link["current"] for link in links_json(anew, newer)] == [True, False]
    assert link_states(anew, newer)["accepted"] == ["r1/r2"]
