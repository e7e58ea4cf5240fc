"""The fleet core rule by rule, with no process, Zenoh or clock: real map crops in, actions out.

Two or more :class:`FleetNode` stand for robots; a test carries the ``Publish`` actions of one
to another's :meth:`FleetNode.on_message` as Zenoh would, and the time is whatever it says.
"""

from __future__ import annotations

from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent import wire
from agent.actions import (
    RULE_REASONS,
    Drop,
    Fetch,
    ForgetMap,
    PersistGlobal,
    PersistLinks,
    PersistMap,
    Publish,
    Register,
    Reply,
    WriteStatus,
)
from agent.book import MINOR_MASK
from agent.globalmap import Component, map_digest
from agent.links import LinkRecord, epoch_of
from agent.node import FleetNode, Instant, NodeOptions
from agent.state import StoredMap
from agent.status import HostFacts
from agent.status_reply import check_status, read_status
from agent.worker import GlobalState
from pgvd.grid import Grid, rigid_matrix
from pgvd.io import read_map
from protocol import Heartbeat, encode, encode_map
from protocol.auth import seal
from protocol.codec import FLAG_MAC, MAGIC, SCHEMA_VERSION
from protocol.errors import REASONS

KEY = b"the lab's fleet key"
T0 = 1_700_000_000.0  # wall clock at mono 0
HOST = HostFacts(pid=1, source={"kind": "map", "done": False}, merges=0, merge_seconds=0.0,
                 inbox_messages=0, inbox_bytes=0)  # fmt: skip


def at(t: float) -> Instant:
    return Instant(t, T0 + t)


def node(robot: str, fleet: str = "lab", key: bytes | None = KEY) -> FleetNode:
    return FleetNode(NodeOptions(robot, fleet, key), at(0.0))


@pytest.fixture(scope="module")
def crops(shared: Path) -> tuple[Grid, Grid]:
    """Two overlapping 256 x 256 crops of the Intel lab halves (intel_split_gt), 0.05 m."""
    d = shared / "maps" / "intel_split_gt"
    a, b = read_map(d / "intel_partA.yaml"), read_map(d / "intel_partB.yaml")
    return (
        Grid(a.logodds[150:406, 150:406].copy(), a.resolution, a.origin),
        Grid(b.logodds[300:556, 200:456].copy(), b.resolution, b.origin),
    )


def publish(peer: FleetNode, grid: Grid, t: float, final: bool = True) -> list[Publish]:
    """``peer``'s next version of ``grid``: gated (``final`` passes the gate, and starts an
    epoch), persisted, then published."""
    (persist,) = peer.on_source(grid, at(t), final=final)
    assert isinstance(persist, PersistMap) and persist.robot == peer.me
    return [
        a
        for a in peer.on_persisted(peer.me, persist.stored.version, at(t))
        if isinstance(a, Publish)
    ]


def deliver(to: FleetNode, messages: list[Publish] | list[Reply], t: float) -> list:
    return [a for m in messages for a in to.on_message(m.key, m.payload, at(t))]


def reasons(actions: list) -> list[str]:
    return [a.reason for a in actions if isinstance(a, Drop)]


def resealed(body: object, key: bytes = KEY) -> bytes:
    """A message whose body is ``body`` (msgpack) with a valid fleet MAC: it passes auth."""
    covered = MAGIC + bytes((SCHEMA_VERSION, FLAG_MAC)) + msgpack.packb(body, use_bin_type=True)
    return covered + seal(covered, key)


def link(
    a: str, b: str, matrix: np.ndarray, decided_by: str = "r2", versions: tuple = (1 << 31, 1 << 31)
) -> LinkRecord:
    cov = np.diag([4.0, 4.0, 1e-4])
    return LinkRecord(a, versions[0], b, versions[1], True, matrix, cov, 0.9, decided_by)


# --------------------------------------------------------------------------- admission


def test_a_peer_version_is_persisted_and_handed_to_the_worker_once(crops) -> None:
    r1, r2 = node("r1"), node("r2")
    sent = publish(r2, crops[0], 0.0)
    assert [p.key for p in sent] == ["pgvd/lab/tiles/r2", "pgvd/lab/manifest/r2"]
    actions = deliver(r1, sent, 0.1)
    assert [type(a) for a in actions] == [PersistMap, Register]
    stored = actions[0].stored
    assert actions[0].robot == "r2" and stored.version == r2.book.version("r2")
    np.testing.assert_array_equal(stored.grid.logodds, wire.on_the_wire(crops[0]).logodds)
    assert r1.book.version("r2") == stored.version
    assert r1.counters.get("maps_received") == 1
    # The same version again (a re-announce, a duplicate reply) is nothing new, and no drop.
    assert deliver(r1, sent, 0.2) == []


def _framing(crops) -> tuple[FleetNode, str, bytes]:
    return node("r1"), "pgvd/lab/tiles/r2", b"not a pgvd message at all"


def _auth(crops) -> tuple[FleetNode, str, bytes]:
    unkeyed = publish(node("r2", key=None), crops[0], 0.0)[-1]
    return node("r1"), unkeyed.key, unkeyed.payload


def _schema(crops) -> tuple[FleetNode, str, bytes]:
    return node("r1"), "pgvd/lab/tiles/r2", resealed(["gossip", "lab", "r2"])


def _limit(crops) -> tuple[FleetNode, str, bytes]:
    return node("r1"), "pgvd/lab/tiles/r2", resealed(["tiles", bytes(70_000)])


def _value(crops) -> tuple[FleetNode, str, bytes]:
    manifest = publish(node("r2"), crops[0], 0.0)[-1]
    body = msgpack.unpackb(manifest.payload[4:-32], raw=False)
    geometry = next(v for v in body if isinstance(v, list) and len(v) == 7)
    geometry[2] = float("nan")  # the resolution
    return node("r1"), manifest.key, resealed(body)


def _foreign_fleet(crops) -> tuple[FleetNode, str, bytes]:
    other = publish(node("r2", fleet="other"), crops[0], 0.0)[-1]
    return node("r1"), "pgvd/lab/manifest/r2", other.payload


def _unexpected_kind(crops) -> tuple[FleetNode, str, bytes]:
    return node("r1"), "pgvd/lab/manifest/r2", encode(Heartbeat("lab", "r2", 1, None), KEY)


def _key_mismatch(crops) -> tuple[FleetNode, str, bytes]:
    manifest = publish(node("r2"), crops[0], 0.0)[-1]
    return node("r1"), "pgvd/lab/manifest/r3", manifest.payload


def _own_robot_id(crops) -> tuple[FleetNode, str, bytes]:
    impostor = publish(node("r1"), crops[0], 0.0)[-1]  # another agent started as r1
    return node("r1"), impostor.key, impostor.payload


def _stale_version(crops) -> tuple[FleetNode, str, bytes]:
    r1, r2 = node("r1"), node("r2")
    first = publish(r2, crops[0], 0.0)
    publish(r2, crops[1], 2.0)
    deliver(r1, r2.answer_latest(None, None), 2.1)  # r1 holds the second version
    assert r1.book.version("r2") == r2.book.version("r2")
    return r1, first[-1].key, first[-1].payload


def _bad_link(crops) -> tuple[FleetNode, str, bytes]:
    skewed = np.diag([2.0, 2.0, 1.0])  # a scaling: not rigid
    return node("r1"), "pgvd/lab/link/r1/r2", wire.encode_link("lab", link("r1", "r2", skewed), KEY)


ADMISSION = {
    "framing": _framing,
    "auth": _auth,
    "schema": _schema,
    "limit": _limit,
    "value": _value,
    "foreign_fleet": _foreign_fleet,
    "unexpected_kind": _unexpected_kind,
    "key_mismatch": _key_mismatch,
    "own_robot_id": _own_robot_id,
    "stale_version": _stale_version,
    "bad_link": _bad_link,
}
#: Where each of the other reasons is tested: the agent never produces ``replay`` (its versions
#: are ordered by the book, not by :class:`protocol.auth.ReplayGuard`).
ELSEWHERE = {
    "own_map_unencodable": "test_an_own_map_beyond_the_wire_is_dropped_and_nothing_goes_out",
    "overload": "tests/test_agent_inbox.py::test_the_agent_counts_what_does_not_fit_as_overload",
    "superseded": "tests/test_agent_inbox.py::test_queued_tiles_of_a_superseded_version_dropped",
}


def test_every_drop_reason_has_its_test() -> None:
    assert set(ADMISSION) | set(ELSEWHERE) == set(REASONS + RULE_REASONS) - {"replay"}


@pytest.mark.parametrize("reason", sorted(ADMISSION))
def test_a_message_breaking_a_rule_is_dropped_for_that_reason(crops, reason: str) -> None:
    r1, key, payload = ADMISSION[reason](crops)
    before = r1.book.versions()
    actions = r1.on_message(key, payload, at(5.0))
    assert reasons(actions) == [reason] and len(actions) == 1, actions
    assert r1.book.versions() == before and r1.book.links() == []
    assert r1.tick(at(9.0)) == [WriteStatus()]  # nothing to fetch, persist or publish


@settings(max_examples=200)
@given(key=st.text(max_size=80), payload=st.binary(max_size=300))
def test_whatever_arrives_is_dropped_with_a_known_reason_never_raised(
    key: str, payload: bytes
) -> None:
    r1 = node("r1")
    (drop,) = r1.on_message(key, payload, at(0.0))
    assert isinstance(drop, Drop) and drop.reason in REASONS + RULE_REASONS
    assert r1.book.versions() == {}


def test_a_tile_that_contradicts_its_manifest_is_dropped_and_the_version_fetched(crops) -> None:
    """Two agents both claiming r2 publish one version number with different maps."""
    r1, r2, twin = node("r1"), node("r2"), node("r2")
    manifest = publish(r2, crops[0], 0.0)[-1]
    tiles = publish(twin, crops[1], 0.0)[:-1]
    assert r1.on_message(manifest.key, manifest.payload, at(0.0)) == []
    assert reasons(deliver(r1, tiles, 0.1)) == ["value"]
    fetch = next(a for a in r1.tick(at(0.5)) if isinstance(a, Fetch))
    assert fetch.selector == "pgvd/lab/latest/r2/**"


def test_past_max_peers_a_new_robot_is_refused_as_a_limit(crops) -> None:
    r1 = node("r1")
    tiny = Grid(crops[0].logodds[:16, :16].copy(), 0.05)
    for i in range(wire.MAX_PEERS):
        _, manifest = encode_map("lab", f"p{i}", 1, tiny, KEY)
        assert reasons(r1.on_message(f"pgvd/lab/manifest/p{i}", manifest, at(0.0))) == []
    _, manifest = encode_map("lab", "one-too-many", 1, tiny, KEY)
    assert reasons(r1.on_message("pgvd/lab/manifest/one-too-many", manifest, at(0.0))) == ["limit"]


# ---------------------------------------------------------------------------- fetching


def test_a_version_missing_tiles_is_fetched_after_tiles_in_flight_had_time(crops) -> None:
    r1, r2 = node("r1"), node("r2")
    *_, manifest = publish(r2, crops[0], 0.0)  # the tiles are lost
    assert r1.on_message(manifest.key, manifest.payload, at(0.0)) == []
    assert r1.tick(at(0.2)) == [WriteStatus()]  # tiles may still be in flight
    (fetch,) = [a for a in r1.tick(at(0.4)) if isinstance(a, Fetch)]
    version = r2.book.version("r2")
    assert fetch.selector == "pgvd/lab/latest/r2/**"
    assert fetch.parameters is not None and fetch.parameters["v"] == str(version)
    assert r1.counters.get("fetches") == r1.counters.get("tile_fetches") == 1
    # The answer names exactly those tiles and completes the version; no fetch stays due.
    answer = r2.answer_latest(fetch.parameters["v"], fetch.parameters["tiles"])
    assert [type(a) for a in deliver(r1, answer, 0.5)] == [PersistMap, Register]
    assert r1.book.version("r2") == version
    assert not any(isinstance(a, Fetch) for a in r1.tick(at(5.0)))


def test_a_delta_without_its_base_fetches_the_whole_latest_version(crops) -> None:
    r1, r2 = node("r1"), node("r2")
    publish(r2, crops[0], 0.0)
    delta = publish(r2, crops[1], 2.0)  # against a version r1 never saw
    assert deliver(r1, delta, 2.0) == []
    (fetch,) = [a for a in r1.tick(at(2.4)) if isinstance(a, Fetch)]
    assert fetch == Fetch("pgvd/lab/latest/r2/**")  # which tiles exist is unknown
    assert (r1.counters.get("fetches"), r1.counters.get("tile_fetches")) == (1, 0)
    deliver(r1, r2.answer_latest(None, None), 2.5)
    assert r1.book.version("r2") == r2.book.version("r2")


def test_a_robot_is_fetched_at_most_once_a_second_unless_it_joins(crops) -> None:
    r1, r2, twin = node("r1"), node("r2"), node("r2")
    manifest = publish(r2, crops[0], 0.0)[-1]
    tiles = publish(twin, crops[1], 0.0)[:-1]
    r1.on_message(manifest.key, manifest.payload, at(0.0))
    deliver(r1, tiles, 0.0)  # contradicts: fetch in 0.3 s
    assert any(isinstance(a, Fetch) for a in r1.tick(at(0.3)))
    deliver(r1, tiles, 0.4)  # again: due at 0.7, but the last fetch was at 0.3
    assert not any(isinstance(a, Fetch) for a in r1.tick(at(0.8)))
    assert not any(isinstance(a, Fetch) for a in r1.tick(at(1.7)))
    assert any(isinstance(a, Fetch) for a in r1.tick(at(1.8)))  # postponed by a second
    # A robot that joins is fetched at once, with its links, whenever it was last fetched.
    joined = r1.on_alive("r2", True, at(1.9))
    assert joined == [
        Register(),
        Fetch("pgvd/lab/latest/r2/**", {"v": manifest_version(manifest), "tiles": "0,1,2,3"}),
        Fetch("pgvd/lab/links/r2/**"),
    ]


def manifest_version(manifest: Publish) -> str:
    return str(wire.Inbound("lab", KEY).decode(manifest.payload).version)


def test_membership_moves_the_book_and_ignores_this_robots_own_token() -> None:
    r1 = node("r1")
    assert r1.on_alive("r1", True, at(0.0)) == []
    assert r1.on_alive("r2", True, at(0.0))[:2] == [Register(), Fetch("pgvd/lab/latest/r2/**")]
    assert r1.book.snapshot().alive == {"r1", "r2"}
    assert r1.on_alive("r2", False, at(1.0)) == [Register()]  # gone: nothing to fetch
    assert r1.book.snapshot().alive == {"r1"}
    robots = r1.status(at(1.0), HOST)["robots"]
    assert robots == {"r2": {"version": None, "alive": False}}


def test_a_robot_gone_for_forget_after_is_forgotten_and_one_back_in_time_is_not(crops) -> None:
    r1 = FleetNode(NodeOptions("r1", "lab", KEY, forget_after=60.0), at(0.0))
    for peer, t in (("r2", 0.0), ("r3", 0.5)):
        deliver(r1, publish(node(peer), crops[0], t), t + 0.1)
        r1.on_alive(peer, True, at(t + 0.2))
    rec = LinkRecord("r2", r1.book.version("r2"), "r3", r1.book.version("r3"), True,
                     np.eye(3), np.eye(3), 0.9, "r2")  # fmt: skip
    r1.book.add_link(rec)
    r1.on_alive("r2", False, at(1.0))
    r1.on_alive("r3", False, at(1.0))
    r1.on_alive("r3", True, at(30.0))  # back before the bound: kept
    assert not any(isinstance(a, ForgetMap) for a in r1.tick(at(60.9)))
    actions = r1.tick(at(61.0))
    assert ForgetMap("r2") in actions and Register() in actions
    assert ForgetMap("r3") not in actions
    assert r1.book.version("r2") is None and r1.book.version("r3") is not None
    assert r1.book.links() == [] and "r2" not in r1.status(at(61.0), HOST)["robots"]
    assert r1.counters.get("robots_forgotten") == 1
    assert not any(isinstance(a, ForgetMap) for a in r1.tick(at(200.0)))  # once
    # If it comes back it is fetched again like any robot that joins.
    assert Fetch("pgvd/lab/latest/r2/**") in r1.on_alive("r2", True, at(201.0))


def test_a_restored_robot_that_never_shows_up_is_forgotten_like_any_gone_one(crops) -> None:
    # A robot that left while this agent was down: every other agent forgot it, and this one
    # once kept it in its global map for good.
    r1 = FleetNode(NodeOptions("r1", "lab", KEY, forget_after=60.0), at(0.0))
    stored = {
        "r2": StoredMap(3 << 31, crops[0], first_epoch=3),
        "r3": StoredMap(5 << 31, crops[1], first_epoch=4),
    }
    # and a persisted link names r7, of whom nothing else is held
    r1.restore(stored, [link("r3", "r7", np.eye(3), versions=(5 << 31, 1 << 31))], at(10.0))
    r1.on_alive("r3", True, at(10.5))  # the membership history: r3 is there, r2 is not
    assert not any(isinstance(a, ForgetMap) for a in r1.tick(at(69.9)))
    actions = r1.tick(at(70.0))
    assert ForgetMap("r2") in actions and ForgetMap("r7") in actions
    assert ForgetMap("r3") not in actions and r1.book.links() == []
    assert r1.book.version("r2") is None and r1.book.version("r3") == 5 << 31


# ------------------------------------------------------------------- own-map publication


def test_an_own_version_is_persisted_before_it_is_published_or_served(crops) -> None:
    r1 = node("r1")
    (persist,) = r1.on_source(crops[0], at(0.0), final=True, resume={"cursor": 7})
    assert persist.robot == "r1" and persist.point == "state-write"
    assert persist.stored.extra == {"cursor": 7}
    np.testing.assert_array_equal(
        persist.stored.grid.logodds, crops[0].logodds
    )  # as the source holds it
    # Until it is on disk: not served, not announced, not in the book, no later version begun.
    assert r1.answer_latest(None, None) == []
    assert r1.book.version("r1") is None
    assert r1.on_source(crops[1], at(3.0), final=True) == []
    assert not any(isinstance(a, (Publish, PersistMap)) for a in r1.tick(at(3.0)))
    assert r1.on_persisted("r2", persist.stored.version, at(3.1)) == []  # not ours
    out = r1.on_persisted("r1", persist.stored.version, at(3.1))
    assert out[0] == Register()
    assert [(a.key, a.point) for a in out[1:]] == [
        ("pgvd/lab/tiles/r1", "tiles-send"),  # a crash test stops after the first tile
        ("pgvd/lab/manifest/r1", None),
    ]
    assert r1.book.version("r1") == persist.stored.version and r1.last_update == T0 + 3.1
    assert r1.answer_latest(None, None)[-1].key.endswith(f"/{persist.stored.version}/m")
    # The map held back meanwhile goes next.
    (second,) = [a for a in r1.tick(at(3.2)) if isinstance(a, PersistMap)]
    assert second.stored.version > persist.stored.version


def test_the_change_gate_holds_a_map_until_its_interval_passed(crops) -> None:
    r1 = node("r1")
    assert r1.on_source(crops[0], at(0.5)) == []  # 1 s since the start has not passed
    assert not any(isinstance(a, PersistMap) for a in r1.tick(at(0.9)))
    assert any(isinstance(a, PersistMap) for a in r1.tick(at(1.0)))


def ungated(robot: str) -> FleetNode:
    """A node whose change gate lets every changed map through, final or not."""
    return FleetNode(NodeOptions(robot, "lab", KEY, min_change=0.0, min_interval=0.0), at(0.0))


def test_versions_start_a_new_epoch_only_when_the_map_changed_enough(crops) -> None:
    r1 = ungated("r1")
    v1 = _version(publish(r1, crops[0], 0.0, final=False))
    assert epoch_of(v1) == int(T0) and v1 & MINOR_MASK == 0
    lo = crops[0].logodds.copy()
    lo[:3, :3] = np.where(lo[:3, :3] > 0, -2.0, 2.0)  # 9 cells change: well under 15 %
    v2 = _version(publish(r1, Grid(lo, crops[0].resolution, crops[0].origin), 2.0, final=False))
    assert v2 == v1 + 1
    v3 = _version(publish(r1, crops[1], 4.0, final=False))  # another part of the building
    assert epoch_of(v3) == int(T0 + 4.0) and v3 & MINOR_MASK == 0
    # the source's last map starts an epoch however little it changed: peers decide every
    # pair of this robot once more on it
    lo = crops[1].logodds.copy()
    lo[:3, :3] = np.where(lo[:3, :3] > 0, -2.0, 2.0)
    v4 = _version(publish(r1, Grid(lo, crops[1].resolution, crops[1].origin), 6.0))
    assert epoch_of(v4) == int(T0 + 6.0) and v4 & MINOR_MASK == 0


def test_the_sources_last_map_is_marked_final_for_every_peer(crops) -> None:
    """The manifest of the source's last version carries the final mark, the delta one
    published and the whole one served alike; a peer's book holds that robot as final, and
    as not final again once a newer version without the mark comes (a source resumed)."""
    r1, r2 = ungated("r1"), node("r2")
    inbound = wire.Inbound("lab", KEY)
    first = publish(r1, crops[0], 0.0, final=False)
    deliver(r2, first, 0.1)
    assert not inbound.decode(first[-1].payload).final and r2.book.snapshot().finals == set()
    last = publish(r1, crops[1], 2.0)  # final: a delta against the first version
    assert inbound.decode(last[-1].payload).final
    served = [a for a in r1.answer_latest(None, None) if a.key.endswith("/m")]
    assert [inbound.decode(m.payload).final for m in served] == [True]
    deliver(r2, last, 2.1)
    snap = r2.book.snapshot()
    assert snap.finals == {"r1"} and snap.maps["r1"][0] == _version(last)
    assert r1.book.snapshot().finals == {"r1"}  # its own map, as its worker reads it
    deliver(r2, publish(r1, crops[0], 4.0, final=False), 4.1)
    assert r2.book.snapshot().finals == set()


def _version(sent: list[Publish]) -> int:
    return wire.Inbound("lab", KEY).decode(sent[-1].payload).version


def test_after_a_restart_the_own_map_is_served_and_versions_move_on(crops) -> None:
    old = (int(T0) + 100) << 31 | 5  # persisted by a run whose clock was ahead
    r1 = ungated("r1")
    peer = StoredMap(3 << 31, crops[1], first_epoch=3)
    r1.restore({"r1": StoredMap(old, crops[0]), "r2": peer}, [], at(0.0))
    assert r1.book.versions() == {"r1": old, "r2": 3 << 31}
    assert r1.answer_latest(None, None)[-1].key == f"pgvd/lab/latest/r1/{old}/m"
    assert any(isinstance(a, Publish) and a.key.endswith("manifest/r1") for a in r1.tick(at(0.0)))
    # The change gate starts from the persisted map: the same map is no new version.
    assert r1.on_source(crops[0], at(5.0), final=True) == []
    # A small change goes on in the persisted epoch: a restart alone does not make every
    # link of this robot be registered again.
    lo = crops[0].logodds.copy()
    lo[:3, :3] = np.where(lo[:3, :3] > 0, -2.0, 2.0)
    minor = _version(publish(r1, Grid(lo, crops[0].resolution, crops[0].origin), 6.0, False))
    assert minor == old + 1
    new = _version(publish(r1, crops[1], 8.0, final=False))  # another part of the building
    assert epoch_of(new) == epoch_of(old) + 1  # a new epoch, and newer


def test_the_manifest_is_re_announced_every_period(crops) -> None:
    r1 = node("r1")
    publish(r1, crops[0], 0.0)
    announced = [
        t for t in (0.0, 1.0, 1.9, 2.0, 3.0, 4.1)
        if any(isinstance(a, Publish) and a.key.endswith("manifest/r1") for a in r1.tick(at(t)))
    ]  # fmt: skip
    assert announced == [0.0, 2.0, 4.1]


def test_an_own_map_beyond_the_wire_is_dropped_and_nothing_goes_out(crops) -> None:
    r1 = node("r1")
    nowhere = Grid(crops[0].logodds, crops[0].resolution, (float("nan"), 0.0, 0.0))
    (drop,) = r1.on_source(nowhere, at(0.0), final=True)
    assert drop.reason == "own_map_unencodable" and drop.sender == "r1"
    assert r1.answer_latest(None, None) == [] and r1.book.version("r1") is None


# ------------------------------------------------------------------------ queries


@pytest.mark.parametrize(
    ("version", "tiles", "reason"),
    [
        ("12", None, "schema"),
        ("1", ",".join(map(str, range(300))), "limit"),
        ("1", "5,5", "value"),
    ],
)
def test_a_malformed_fetch_is_dropped(version: str, tiles: str | None, reason: str) -> None:
    (drop,) = node("r1").answer_latest(version, tiles)
    assert (drop.reason, drop.sender) == (reason, "query")


def test_the_status_reply_carries_the_fleet_mac() -> None:
    r1 = node("r1")
    payload = b'{"robot": "r1", "settled": false}'
    reply = r1.answer_status(payload)
    assert reply.key == "pgvd/lab/status/r1"
    assert read_status(reply.payload, reply.attachment, KEY) == {"robot": "r1", "settled": False}
    assert node("r1", key=None).answer_status(payload).attachment is None


# ------------------------------------------------------------------------- links


def test_a_link_received_is_cached_once_and_persisted_at_the_next_status() -> None:
    r1 = node("r1")
    rec = link("r1", "r2", rigid_matrix(0.3, 5.0, -2.0))
    data = wire.encode_link("lab", rec, KEY)
    assert r1.on_message("pgvd/lab/link/r1/r2", data, at(0.0)) == [Register()]
    assert r1.on_message("pgvd/lab/link/r1/r2", data, at(0.1)) == []  # held already
    assert r1.counters.get("links_received") == 1
    (persist, status) = r1.tick(at(0.2))
    assert isinstance(persist, PersistLinks) and status == WriteStatus()
    assert [r.key for r in persist.records] == [rec.key]
    assert r1.flush() == [WriteStatus()]  # nothing new to persist


def test_links_of_robots_nobody_has_are_forgotten_and_not_served_on(crops) -> None:
    # A joiner fetched links of robots its peer still held but that had left: they were
    # kept, persisted and served to the next joiner for good.
    r1 = FleetNode(NodeOptions("r1", "lab", KEY, forget_after=60.0), at(0.0))
    r1.on_alive("r2", True, at(0.0))
    for a, b in (("r8", "r9"), ("r2", "r3")):
        peer = link(a, b, np.eye(3), decided_by=a)
        r1.on_message(f"pgvd/lab/link/{a}/{b}", wire.encode_link("lab", peer, KEY), at(1.0))
    r1.on_alive("r3", True, at(30.0))  # r3 turns up: its link stays
    assert len(r1.book.links()) == 2
    actions = r1.tick(at(61.0))
    assert ForgetMap("r8") in actions and ForgetMap("r9") in actions
    assert [(ln.a, ln.b) for ln in r1.book.links()] == [("r2", "r3")]
    assert [ln.a for ln in wire_links(r1)] == ["r2"]


def wire_links(r: FleetNode) -> list[LinkRecord]:
    inbound = wire.Inbound("lab", KEY)
    return [wire.link_record(inbound.decode(reply.payload)) for reply in r.answer_links()]


def test_a_link_decided_here_is_published_served_and_persisted() -> None:
    r1 = node("r1")
    rec = link("r1", "r2", rigid_matrix(-1.2, 10.0, 3.0), decided_by="r1")
    r1.book.add_link(rec)  # as the fusion worker does before it reports
    (sent,) = r1.on_link(rec, at(0.0))
    assert sent.key == "pgvd/lab/link/r1/r2"
    got = wire.link_record(wire.Inbound("lab", KEY).decode(sent.payload))
    np.testing.assert_allclose(got.matrix, rec.matrix)
    (reply,) = r1.answer_links()
    assert reply.key == "pgvd/lab/links/r1/0" and reply.payload == sent.payload
    assert isinstance(r1.flush()[0], PersistLinks)


# ----------------------------------------------------------------- global map, status


def component(versions: dict[str, int], grid: Grid, digest: str) -> Component:
    """r1 and r2 joined by their one link, anchored at r1 (transforms are not read here)."""
    return Component("r1", ("r1", "r2"), versions, {}, {}, (("r1", "r2"),), (), grid, digest)


def test_a_new_global_map_is_written_once_and_the_status_refreshed(crops) -> None:
    r1 = node("r1")
    assert r1.tick(at(0.0)) == [WriteStatus()]  # the periodic status, next at 1.0
    assert r1.tick(at(0.1)) == []
    grid = crops[0]
    comp = component({"r1": 1, "r2": 2}, grid, map_digest(grid))
    assert r1.on_global(GlobalState([comp], True, T0 + 0.4), at(0.4)) == [PersistGlobal(comp)]
    assert r1.settled_at == T0 + 0.4
    assert r1.tick(at(0.5)) == [WriteStatus()]  # due at once, not at the next period
    assert r1.on_global(GlobalState([comp], True, T0 + 0.6), at(0.6)) == []  # same map
    assert r1.settled_at == T0 + 0.4
    assert r1.on_global(GlobalState([comp], False, T0 + 0.7), at(0.7)) == []
    assert r1.settled_at is None


def test_the_status_shows_the_fleet_as_the_core_holds_it(crops) -> None:
    r1, r2 = node("r1"), node("r2")
    publish(r1, crops[0], 0.0)
    deliver(r1, publish(r2, crops[1], 0.0), 0.1)
    r1.on_alive("r2", True, at(0.1))
    versions = r1.book.versions()
    rec = link(
        "r1", "r2", rigid_matrix(np.pi / 2, 5.0, -2.0), versions=(versions["r1"], versions["r2"])
    )
    r1.on_message("pgvd/lab/link/r1/r2", wire.encode_link("lab", rec, KEY), at(0.2))
    comp = component(versions, crops[0], "ab" * 32)
    r1.on_global(GlobalState([comp], True, T0 + 1.0), at(1.0))
    status = r1.status(at(2.0), HOST)
    assert check_status(status) is status
    assert (status["robot"], status["fleet"], status["time"], status["started"]) == (
        "r1",
        "lab",
        T0 + 2.0,
        T0,
    )
    assert status["own_version"] == versions["r1"] and status["last_update"] == T0
    assert status["robots"] == {
        "r1": {"version": versions["r1"], "alive": True},
        "r2": {"version": versions["r2"], "alive": True},
    }
    (shown,) = status["links"]
    assert (shown["a"], shown["b"], shown["rotation_deg"], shown["current"]) == (
        "r1",
        "r2",
        90.0,
        True,
    )
    assert status["global"] == {"anchor": "r1", "digest": "ab" * 32, "members": ["r1", "r2"]}
    (shown,) = status["components"]
    assert (shown["used"], shown["rejected"], shown["shape"]) == ([["r1", "r2"]], [], [256, 256])
    assert status["settled"] and status["settled_at"] == T0 + 1.0
    assert status["counts"]["maps_received"] == 1 and status["counts"]["links_received"] == 1


def test_a_candidate_received_is_held_apart_in_the_status_and_served_with_its_state(
    crops, caplog
) -> None:
    caplog.set_level("INFO", logger="pgvd.agent")
    r1, r2 = node("r1"), node("r2")
    publish(r1, crops[0], 0.0)
    deliver(r1, publish(r2, crops[1], 0.0), 0.1)
    versions = r1.book.versions()
    grey = LinkRecord(
        "r1", versions["r1"], "r2", versions["r2"], False, rigid_matrix(0.3, 5.0, -2.0),
        np.diag([4.0, 4.0, 1e-4]), 0.8, "r2", state="candidate", margin=0.41,
        reason="grey zone: margin 0.41 below 0.57",
    )  # fmt: skip
    assert r1.on_message("pgvd/lab/link/r1/r2", wire.encode_link("lab", grey, KEY), at(0.2))
    status = r1.status(at(1.0), HOST)
    assert status["link_states"]["candidate"] == ["r1/r2"]
    assert status["link_states"]["accepted"] == [] == status["link_states"]["withdrawn"]
    (shown,) = status["links"]
    assert (shown["state"], shown["margin"], shown["accepted"]) == ("candidate", 0.41, False)
    (served,) = wire_links(r1)
    assert (served.state, served.margin, served.reason) == ("candidate", 0.41, grey.reason)
    # a global map that changes is one line of the log
    comp = component(versions, crops[0], "cd" * 32)
    r1.on_global(GlobalState([comp], True, T0 + 1.0), at(1.0))
    assert any(r.getMessage().startswith("globalmap anchor=r1 robots=") for r in caplog.records)


def test_the_source_reads_done_only_once_its_last_map_is_published(crops) -> None:
    """A source whose last scan is in says done, but its last map waits to be persisted:
    a status that said done beside the version before it let the demo's agreement stop a
    fleet before its final maps were decided."""
    r1 = node("r1")
    publish(r1, crops[0], 0.0)
    done = HostFacts(pid=1, source={"kind": "carmen", "done": True}, merges=0,
                     merge_seconds=0.0, inbox_messages=0, inbox_bytes=0)  # fmt: skip
    (persist,) = r1.on_source(crops[1], at(1.0), final=True)
    waiting = r1.status(at(1.1), done)
    assert waiting["source"] == {"kind": "carmen", "done": False}
    r1.on_persisted("r1", persist.stored.version, at(1.2))
    published = r1.status(at(1.3), done)
    assert published["source"]["done"] is True
    assert published["own_version"] == persist.stored.version != waiting["own_version"]
